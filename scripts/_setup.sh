# Shared set-up of scripts/run.sh and scripts/test.sh (sourced, not run on its own).
#
#   torchslam_setup EXTRA
#
# makes sure the repository's .venv exists and holds PyTorch and torchslam (with the extra EXTRA,
# e.g. "test", or none), installing only what is missing, then puts .venv/bin first on PATH.
# One line per step; a failing step prints one line naming the step and what to do, and exits 1.
#
# Environment:
#   PYTHON            the interpreter that creates .venv (default: python3)
#   TORCHSLAM_VENV    where the virtual environment lives (default: <repository>/.venv)
#   TORCHSLAM_TORCH   pip requirement for PyTorch, e.g. "torch==2.13.0" (default: the CPU build of
#                     torch 2.13.0 where nvidia-smi finds no GPU, the default build where it does)

TORCHSLAM_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TORCHSLAM_TORCH_CPU_INDEX="https://download.pytorch.org/whl/cpu"
TORCHSLAM_TORCH_DEFAULT="torch==2.13.0"

_say() { printf 'setup: %s\n' "$*" >&2; }
_fail() { printf 'setup failed at step "%s": %s\n' "$1" "$2" >&2; exit 1; }

# A stamp records what was installed (extra + the pyproject.toml it was installed from), so a
# second call installs nothing unless pyproject.toml changed or another extra is asked for.
_stamp_key() {
    local extra="$1" sum
    sum=$( (sha256sum "$TORCHSLAM_ROOT/pyproject.toml" 2>/dev/null || shasum -a 256 "$TORCHSLAM_ROOT/pyproject.toml") | cut -d' ' -f1)
    printf '%s %s\n' "${extra:-none}" "$sum"
}

torchslam_setup() {
    local extra="${1:-}"
    local venv="${TORCHSLAM_VENV:-$TORCHSLAM_ROOT/.venv}"
    local py="${PYTHON:-python3}"
    local vpy="$venv/bin/python"

    # 1. Python
    if [ ! -x "$vpy" ]; then
        command -v "$py" >/dev/null 2>&1 || _fail python "no '$py' on PATH; install Python 3.10 or newer, or set PYTHON=/path/to/python3"
        "$py" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else 1)' 2>/dev/null \
            || _fail python "$("$py" -V 2>&1) is older than torchslam supports (3.10 or newer); set PYTHON=/path/to/python3.11"
        _say "python: $("$py" -V 2>&1) ($(command -v "$py"))"
        # 2. virtual environment
        _say "venv: creating $venv"
        "$py" -m venv "$venv" >/dev/null 2>&1 \
            || _fail venv "'$py -m venv $venv' failed; on Debian/Ubuntu install python3-venv, or set PYTHON to another interpreter"
    else
        _say "venv: $venv ($("$vpy" -V 2>&1))"
    fi

    # 3. PyTorch
    if "$vpy" -c 'import torch' >/dev/null 2>&1; then
        _say "torch: $("$vpy" -c 'import torch; print(torch.__version__)') already installed"
    else
        local req args=()
        if [ -n "${TORCHSLAM_TORCH:-}" ]; then
            req="$TORCHSLAM_TORCH"
            _say "torch: installing $req (from TORCHSLAM_TORCH)"
        elif command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
            req="$TORCHSLAM_TORCH_DEFAULT"
            _say "torch: installing $req, default (CUDA) build: nvidia-smi found a GPU (set TORCHSLAM_TORCH to choose another)"
        else
            req="$TORCHSLAM_TORCH_DEFAULT"
            args=(--extra-index-url "$TORCHSLAM_TORCH_CPU_INDEX")
            _say "torch: installing $req, CPU build: no GPU found (set TORCHSLAM_TORCH to choose another)"
        fi
        "$vpy" -m pip install -q "${args[@]}" "$req" >"$venv/torch-install.log" 2>&1 \
            || _fail torch "pip could not install '$req' (log: $venv/torch-install.log); set TORCHSLAM_TORCH to a requirement that pip can install here"
    fi

    # 4. torchslam (editable, so the checkout is what runs)
    local stamp="$venv/.torchslam-installed" key spec="$TORCHSLAM_ROOT"
    key="$(_stamp_key "$extra")"
    [ -n "$extra" ] && spec="$TORCHSLAM_ROOT[$extra]"
    # Installed with any extra satisfies a request for none.
    if [ -f "$stamp" ] && { grep -qxF "$key" "$stamp" || { [ -z "$extra" ] && grep -q " ${key#* }\$" "$stamp"; }; } \
        && "$vpy" -c 'import torchslam' >/dev/null 2>&1; then
        _say "torchslam: installed${extra:+ (with [$extra])}"
    else
        _say "torchslam: installing${extra:+ with [$extra]} (pip install -e)"
        "$vpy" -m pip install -q -e "$spec" >"$venv/torchslam-install.log" 2>&1 \
            || _fail torchslam "pip install -e '$spec' failed (log: $venv/torchslam-install.log)"
        printf '%s\n' "$key" >>"$stamp"
    fi
    export PATH="$venv/bin:$PATH"
    export VIRTUAL_ENV="$venv"
}
