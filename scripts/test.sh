#!/usr/bin/env bash
# The test suite on a fresh machine: set up .venv (PyTorch + torchslam[test]) on first use, then
# pytest with this script's arguments (none: the whole suite, quiet).
#   bash scripts/test.sh
#   bash scripts/test.sh tests/kcc -x
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_setup.sh"
torchslam_setup test
cd "$TORCHSLAM_ROOT"
if [ "$#" -eq 0 ]; then set -- -q; fi
exec python -m pytest "$@"
