#!/usr/bin/env bash
# The main job on a fresh machine: set up .venv (PyTorch + torchslam) on first use, then
# `torchslam run` with this script's arguments (none: NI-SLAM on the built-in synthetic sequence).
#   bash scripts/run.sh
#   bash scripts/run.sh --data path/to/tum_sequence --system gcslam
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_setup.sh"
torchslam_setup ""
cd "$TORCHSLAM_ROOT"
exec torchslam run "$@"
