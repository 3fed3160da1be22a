"""The intra-op thread count a run uses: a measured default, overridden by a flag or a variable.

torchslam's per-frame work is many small tensor operations (FFTs of one ortho image, a few
thousand ORB matches, 6x6 blocks of a pose graph). Spread over several intra-op threads they
gain little on an idle machine, and beside any other CPU-bound process they collapse: OpenMP's
workers busy-wait at every parallel region for a core that another process holds, so NI-SLAM
on a loaded 2-core machine ran ~10x slower with two threads than with one
(``scripts/bench_threads.py`` measures this, and the README holds its table). Parallelism across
sequences (``torchslam batch``, lockstep groups, ``torchrun``) is where the cores pay off. So the
default is one intra-op thread; ``--threads N`` or ``TORCHSLAM_THREADS=N`` choose another
count (the flag wins over the variable).

The setting covers every pool a hot path uses: PyTorch's intra-op pool (OpenMP, and MKL through
it) and OpenCV's (ORB detection and Hamming matching). NumPy/SciPy run only index bookkeeping and
sparse-graph routines in torchslam (no BLAS calls), so OpenBLAS's pool is never entered. The
inter-op pool serves ``torch.jit.fork``, which torchslam does not use, and is left alone.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

from .errors import ConfigError

__all__ = [
    "POLICY_THREADS",
    "THREADS_ENV",
    "ThreadSetting",
    "apply_threads",
    "parse_threads",
    "policy_threads",
    "resolve_threads",
    "setup_threads",
]

THREADS_ENV = "TORCHSLAM_THREADS"
# The default intra-op thread count (see the module docstring for the measurement behind it).
POLICY_THREADS = 1
SOURCES = ("policy", "flag", "env")


@dataclass(frozen=True)
class ThreadSetting:
    """An intra-op thread count and where it came from.

    Attributes:
        threads: intra-op threads, >= 1.
        source: ``"flag"`` (``--threads`` or an explicit option), ``"env"`` (``TORCHSLAM_THREADS``)
            or ``"policy"`` (the default).
    """

    threads: int
    source: str

    def to_dict(self) -> dict[str, int | str]:
        """The ``threads`` and ``threads_source`` keys that ``metrics.json`` and summaries record."""
        return {"threads": self.threads, "threads_source": self.source}


def parse_threads(value: object, name: str) -> int:
    """Check a thread count given as an int or a decimal string; ``name`` goes into the error.

    Raises:
        ConfigError: not a whole number >= 1 (e.g. ``--threads 0``, ``TORCHSLAM_THREADS=two``).
    """
    message = f"{name}: expected a whole number of threads >= 1, got {value!r}"
    if isinstance(value, str):
        text = value.strip().removeprefix("+")
        if not text.isdigit():
            raise ConfigError(message)
        value = int(text)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(message)
    return value


def policy_threads() -> int:
    """The default intra-op thread count: one, whatever the core count (see the module docstring)."""
    return POLICY_THREADS


def resolve_threads(
    flag: object = None, environ: Mapping[str, str] | None = None, flag_name: str = "--threads"
) -> ThreadSetting:
    """Choose the thread count: ``flag`` if given, else ``TORCHSLAM_THREADS`` if set, else the policy.

    Args:
        flag: the explicit count (``--threads``, ``RunOptions.threads``), or None.
        environ: the environment to read ``TORCHSLAM_THREADS`` from (default ``os.environ``).
        flag_name: how the flag is named in an error.

    Raises:
        ConfigError: an invalid count, naming ``flag_name`` or ``TORCHSLAM_THREADS``. A set but
            invalid variable is an error even when the flag overrides it, so a typo never hides.
    """
    environ = os.environ if environ is None else environ
    raw = environ.get(THREADS_ENV)
    env_threads = None
    if raw is not None and raw.strip() != "":
        env_threads = parse_threads(raw, THREADS_ENV)
    if flag is not None:
        return ThreadSetting(parse_threads(flag, flag_name), "flag")
    if env_threads is not None:
        return ThreadSetting(env_threads, "env")
    return ThreadSetting(policy_threads(), "policy")


def apply_threads(setting: ThreadSetting) -> None:
    """Set PyTorch's intra-op pool (and MKL's with it) and OpenCV's to ``setting.threads``."""
    import cv2
    import torch

    torch.set_num_threads(setting.threads)
    # OpenCV: 0 runs its parallel loops on the calling thread alone; n > 1 uses n threads.
    cv2.setNumThreads(setting.threads if setting.threads > 1 else 0)


def setup_threads(flag: object = None, environ: Mapping[str, str] | None = None, flag_name: str = "--threads") -> ThreadSetting:
    """Resolve the thread count (:func:`resolve_threads`) and apply it; return what was applied."""
    setting = resolve_threads(flag, environ, flag_name)
    apply_threads(setting)
    return setting
