#!/usr/bin/env bash
# The test suite on a fresh machine: set up .venv (PyTorch + torchslam[test]) on first use, then
# pytest with this script's arguments.
#   bash scripts/test.sh                 # the whole suite, quiet, on one pytest worker per core (at most 4)
#   bash scripts/test.sh tests/kcc -x    # pytest exactly as asked (one process)
# Without arguments the suite is spread over the machine's cores by pytest-xdist (part of the
# `test` extra): on the 2-core development machine it takes about 6 minutes instead of 9.
# TORCHSLAM_TEST_WORKERS=N sets the number of workers (1: one process, as pytest alone runs it).
set -euo pipefail
workers="${TORCHSLAM_TEST_WORKERS:-}"
if [ "$#" -eq 0 ] && [ -n "$workers" ]; then
    # Checked before anything is set up or installed.
    case "$workers" in
        *[!0-9]*|0|00*) echo "test.sh: TORCHSLAM_TEST_WORKERS=$workers: expected a whole number of workers, 1 or more" >&2; exit 2 ;;
    esac
fi
source "$(dirname "${BASH_SOURCE[0]}")/_setup.sh"
torchslam_setup test
cd "$TORCHSLAM_ROOT"
if [ "$#" -eq 0 ]; then
    if [ -z "$workers" ]; then
        # The cores this process may run on, at most 4: each worker holds its own PyTorch.
        workers=$(python -c 'import os; n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1); print(max(1, min(4, n)))')
    fi
    set -- -q
    if [ "$workers" -gt 1 ]; then
        if python -c 'import xdist' >/dev/null 2>&1; then
            set -- -q -n "$workers"
        else
            echo "test.sh: pytest-xdist is not installed: running the suite in one process" >&2
        fi
    fi
fi
exec python -m pytest "$@"
