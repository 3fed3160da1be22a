#!/usr/bin/env bash
# Build torchslam's wheel, install it into a fresh virtual environment WITHOUT the test extra,
# and run the main job, a shipped preset by name and the learned KCC channels (packaged weights)
# from outside the checkout; fail unless each run folder is complete. CI runs it after the test suite.
#   bash scripts/check_wheel.sh
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_setup.sh"
work="$(mktemp -d "${TMPDIR:-/tmp}/torchslam-wheel.XXXXXX")"
trap 'rm -rf "$work"' EXIT
py="${PYTHON:-python3}"

_say "wheel: building"
"$py" -m pip wheel -q --no-deps -w "$work/dist" "$TORCHSLAM_ROOT" >"$work/build.log" 2>&1 \
    || { cat "$work/build.log" >&2; _fail wheel "pip wheel failed"; }
wheel="$(ls "$work"/dist/torchslam-*.whl)"
"$py" - "$wheel" <<'PY' || _fail wheel "the wheel lacks the shipped presets or the learned KCC weights"
import sys, zipfile
names = zipfile.ZipFile(sys.argv[1]).namelist()
presets = [n for n in names if n.startswith("torchslam/presets/") and n.endswith(".yaml")]
print(f"setup: wheel: {sys.argv[1].rsplit('/', 1)[-1]}, {len(names)} files, presets: {', '.join(sorted(p.rsplit('/', 1)[-1] for p in presets))}", file=sys.stderr)
weights = "torchslam/kcc/weights/kcc_features.pt" in names
print(f"setup: wheel: learned KCC channels' weights {'present' if weights else 'MISSING'}", file=sys.stderr)
sys.exit(0 if len(presets) >= 4 and weights else 1)
PY

_say "wheel: fresh venv (no test extra)"
"$py" -m venv "$work/venv" || _fail venv "'$py -m venv' failed"
vpy="$work/venv/bin/python"
args=()
if [ -z "${TORCHSLAM_TORCH:-}" ] && ! { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }; then
    args=(--extra-index-url "$TORCHSLAM_TORCH_CPU_INDEX")
fi
"$vpy" -m pip install -q "${args[@]}" "${TORCHSLAM_TORCH:-$TORCHSLAM_TORCH_DEFAULT}" >"$work/torch.log" 2>&1 \
    || { cat "$work/torch.log" >&2; _fail torch "pip could not install PyTorch"; }
"$vpy" -m pip install -q "$wheel" >"$work/install.log" 2>&1 \
    || { cat "$work/install.log" >&2; _fail install "pip install of the wheel failed"; }
if "$vpy" -c 'import pytest' 2>/dev/null || "$vpy" -c 'import evo' 2>/dev/null; then
    _fail install "the plain wheel pulled in a test dependency (pytest or evo)"
fi

cd "$work"  # outside the checkout: only the installed package is importable
"$work/venv/bin/torchslam" run --help | grep -q "nislam_fast" || _fail help "'torchslam run --help' does not list the presets"
check_run() {
    local out="$1"; shift
    _say "wheel: torchslam run $*"
    "$work/venv/bin/torchslam" run --no-progress --out "$out" "$@" 2>"$out.stderr" \
        || { cat "$out.stderr" >&2; _fail run "torchslam run $* failed"; }
    if grep -q "not logged\|not written" "$out.stderr"; then
        cat "$out.stderr" >&2; _fail run "torchslam run $* skipped an output"
    fi
    local f
    for f in trajectory.txt keyframes.txt map.ply metrics.json config.yaml; do
        [ -s "$out/$f" ] || _fail run "$out/$f is missing or empty after 'torchslam run $*'"
    done
    ls "$out"/events.out.tfevents.* >/dev/null 2>&1 || _fail run "no TensorBoard events in $out"
    "$vpy" - "$out/metrics.json" "$@" <<'PY' || _fail run "metrics.json of 'torchslam run $*' is not a complete run"
import json, sys
m = json.load(open(sys.argv[1]))
ok = m.get("processed_frames", m.get("frames")) == 20 and m.get("tracked_frames", 0) > 0 and not m.get("interrupted")
print(f"setup: wheel: {' '.join(sys.argv[2:])}: {m.get('tracked_frames')} frames tracked, ATE {m.get('ate_rmse_m')}", file=sys.stderr)
sys.exit(0 if ok else 1)
PY
}
check_run "$work/run-default" --max-frames 20
check_run "$work/run-preset" --max-frames 20 --config nislam_fast
check_run "$work/run-learned" --max-frames 20 --set kcc.features=learned
_say "wheel: ok"
