"""The CPU thread counts a run uses: a default chosen by benchmark, overridden by a flag or a variable.

torchslam's per-frame work is many small tensor operations (FFTs of one ortho image, 6x6 blocks
of a pose graph, a few thousand 3-D points). Spread over several PyTorch intra-op threads they
gain nothing on an idle machine, and beside any other CPU-bound process they collapse: OpenMP's
workers busy-wait at every parallel region for a core another process holds, so on a loaded
machine NI-SLAM and FastGO run several times slower with two threads than with one
(``scripts/bench_threads.py``; the figures are in docs/results/cpu.md, "Threads"). OpenCV's pool
(ORB detection and Hamming matching in GC-SLAM's sparse front-end) waits without spinning, so
using every core does not slow it, idle or beside a busy process. So by default PyTorch gets one
intra-op thread and OpenCV every core the process may run on. ``--threads N`` or
``TORCHSLAM_THREADS=N`` (the flag wins over the variable) set both pools to N. Parallelism across
sequences (``torchslam batch``, lockstep groups, ``torchrun``) is where more cores pay off.

MKL follows PyTorch's setting. NumPy/SciPy run only index bookkeeping and sparse-graph routines
in torchslam (no BLAS calls), so OpenBLAS's pool is never entered; the inter-op pool serves
``torch.jit.fork``, which torchslam does not use. Both are left alone.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass

from .errors import ConfigError

__all__ = [
    "POLICY_THREADS",
    "THREADS_ENV",
    "ThreadSetting",
    "apply_threads",
    "available_cpus",
    "name_os_thread",
    "parse_threads",
    "policy_setting",
    "policy_threads",
    "resolve_threads",
    "setup_threads",
]

THREADS_ENV = "TORCHSLAM_THREADS"
# The default PyTorch intra-op thread count (see the module docstring for the measurement).
POLICY_THREADS = 1


@dataclass(frozen=True)
class ThreadSetting:
    """Thread counts and where they came from.

    Attributes:
        threads: PyTorch intra-op threads, >= 1.
        source: ``"flag"`` (``--threads`` or an explicit option), ``"env"`` (``TORCHSLAM_THREADS``)
            or ``"policy"`` (the default).
        opencv_threads: OpenCV's threads (ORB, matching), >= 1; ``threads`` unless the policy chose.
    """

    threads: int
    source: str
    opencv_threads: int

    def to_dict(self) -> dict[str, int | str]:
        """The keys ``metrics.json`` and summaries record: ``threads``, ``threads_source``, ``opencv_threads``."""
        return {"threads": self.threads, "threads_source": self.source, "opencv_threads": self.opencv_threads}


def parse_threads(value: object, name: str) -> int:
    """Check a thread count given as an int or a decimal string; ``name`` goes into the error.

    Raises:
        ConfigError: not a whole number >= 1 (e.g. ``--threads 0``, ``TORCHSLAM_THREADS=two``).
    """
    message = f"{name}: expected a whole number of threads >= 1, got {value!r}"
    if isinstance(value, str):
        text = value.strip().removeprefix("+")
        if not (text.isascii() and text.isdigit()):
            raise ConfigError(message)
        value = int(text)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(message)
    return value


def available_cpus() -> int:
    """The cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def policy_threads() -> int:
    """The default PyTorch intra-op thread count: one, whatever the core count (module docstring)."""
    return POLICY_THREADS


def policy_setting(cpus: int) -> ThreadSetting:
    """The default: one PyTorch intra-op thread, OpenCV on all ``cpus`` cores."""
    return ThreadSetting(policy_threads(), "policy", max(1, cpus))


def resolve_threads(
    flag: object = None, environ: Mapping[str, str] | None = None, flag_name: str = "--threads", cpus: int | None = None
) -> ThreadSetting:
    """Choose the thread count: ``flag`` if given, else ``TORCHSLAM_THREADS`` if set, else the policy.

    Args:
        flag: the explicit count (``--threads``, ``RunOptions.threads``), or None.
        environ: the environment to read ``TORCHSLAM_THREADS`` from (default ``os.environ``).
        flag_name: how the flag is named in an error.
        cpus: the cores the policy may give OpenCV (default :func:`available_cpus`).

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
        n = parse_threads(flag, flag_name)
        return ThreadSetting(n, "flag", n)
    if env_threads is not None:
        return ThreadSetting(env_threads, "env", env_threads)
    return policy_setting(available_cpus() if cpus is None else cpus)


def apply_threads(setting: ThreadSetting) -> None:
    """Set PyTorch's intra-op pool (and MKL's with it) and OpenCV's pool to the setting's counts."""
    import cv2
    import torch

    torch.set_num_threads(setting.threads)
    # OpenCV: 0 runs its parallel loops on the calling thread alone; n > 1 uses n threads.
    cv2.setNumThreads(setting.opencv_threads if setting.opencv_threads > 1 else 0)


def setup_threads(
    flag: object = None, environ: Mapping[str, str] | None = None, flag_name: str = "--threads", cpus: int | None = None
) -> ThreadSetting:
    """Resolve the thread counts (:func:`resolve_threads`) and apply them; return what was applied."""
    setting = resolve_threads(flag, environ, flag_name, cpus)
    apply_threads(setting)
    return setting


def name_os_thread(name: str) -> bool:
    """Give the calling thread ``name`` where the operating system shows it (``top -H``, ``ps -L``).

    Python names its threads for itself only; the kernel lists every thread of a run as the
    program's name. torchslam names the threads and child processes it starts (``tslam-...``), so
    that a look at a running job, or ``scripts/bench_cpu.py``, tells which part uses the CPU.
    Linux only (``/proc/self/task/<id>/comm``, at most 15 bytes, longer names are cut); elsewhere,
    or when it cannot be written, nothing changes. Returns whether the name was set.
    """
    encoded = name.encode("utf-8", "replace")[:15]
    try:
        with open(f"/proc/self/task/{threading.get_native_id()}/comm", "wb") as f:
            f.write(encoded)
    except OSError:
        return False
    return True
