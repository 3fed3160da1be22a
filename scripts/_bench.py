"""What the benchmarks in scripts/ share: device sync, repeated timing, paths, load, the tests' oracles.

A benchmark imports it as ``from _bench import ...`` (a script's own folder is first on
``sys.path``). Importing it sets the process's C heap as ``torchslam run`` does
(``torchslam.allocator.setup_allocator``: freed memory kept between frames, unless
``TORCHSLAM_MALLOC=system``), so benchmarks measure what a run gets; ``ALLOCATOR`` says what it did.
"""

from __future__ import annotations

import importlib.util
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import torch


def _setup_allocator():
    """Apply ``torchslam.allocator.setup_allocator`` and forget the torchslam modules it imported.

    The C heap's setting is the process's and stays; the modules are dropped so that a benchmark
    that imports another checkout's torchslam (``load_tree``) finds none imported yet.
    """
    before = set(sys.modules)
    from torchslam.allocator import setup_allocator

    setting = setup_allocator()
    for name in set(sys.modules) - before:
        if name == "torchslam" or name.startswith("torchslam."):
            del sys.modules[name]
    return setting


ALLOCATOR = _setup_allocator()
REPO_ROOT = Path(__file__).resolve().parents[1]
RESULTS = REPO_ROOT / "scripts" / "results"


def data_root() -> Path:
    """The real sequences: ``$TORCHSLAM_DATA``, else ``../shared/data`` beside the repository."""
    env = os.environ.get("TORCHSLAM_DATA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data"


def sync(device: str | torch.device) -> None:
    """Wait for the queued work of a CUDA ``device`` (no-op elsewhere), so a clock reads it."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


@dataclass(frozen=True)
class Timing:
    """Wall-clock seconds of the timed calls; ``best`` is the least disturbed on a shared machine."""

    seconds: list[float]

    @property
    def best(self) -> float:
        return min(self.seconds)

    @property
    def median(self) -> float:
        return statistics.median(self.seconds)


def time_calls(fn: Callable[[], object], repeat: int, device: str | torch.device = "cpu", warmup: int = 1) -> Timing:
    """Call ``fn`` ``warmup`` times untimed (caches, allocator, lazy imports), then ``repeat`` times timed."""
    for _ in range(warmup):
        fn()
    sync(device)
    seconds = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        sync(device)
        seconds.append(time.perf_counter() - t0)
    return Timing(seconds)


def load_average() -> list[float] | None:
    """The 1, 5 and 15 minute load averages, or None where the OS has none."""
    try:
        return list(os.getloadavg())
    except (AttributeError, OSError):
        return None


def test_references() -> ModuleType:
    """``tests/_references.py``, the slow oracles the tests hold, loaded by path.

    The oracles are test code, so they live with the tests; a benchmark that times the library
    against one loads that file here instead of putting the repository root on ``sys.path``.
    """
    name = "tests._references"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "tests" / "_references.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


GCSLAM_MODULES = ("torchslam.systems.gcslam", "torchslam.config", "torchslam.data.tum", "torchslam.data.synthetic",
                  "torchslam.data", "torchslam.eval")


def load_tree(path: Path, names: tuple[str, ...] = GCSLAM_MODULES) -> dict:
    """Import ``path``'s torchslam (the modules ``names``) and set its modules aside, so two checkouts share a process.

    Returns:
        ``{"mods": every torchslam module of that checkout, name: module for each of names}``;
        ``use_tree`` puts the modules back before that checkout's code runs.
    """
    import importlib

    sys.path.insert(0, str(path))
    try:
        mods = {n: importlib.import_module(n) for n in names}
    finally:
        sys.path.pop(0)
    tree = {k: sys.modules[k] for k in list(sys.modules) if k == "torchslam" or k.startswith("torchslam.")}
    for k in tree:
        del sys.modules[k]
    return {"mods": tree, **mods}


def use_tree(tree: dict) -> None:
    """Make ``tree``'s torchslam the imported one (``load_tree``)."""
    sys.modules.update(tree["mods"])


def write_json(path: Path | None, data) -> None:
    """Write ``data`` as indented JSON to ``path`` (its folder created), or nothing when ``path`` is None."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")


SYSTEMS = ("nislam", "gcslam-sparse", "gcslam-dense")


def system_by_name(name: str, **values):
    """A fresh system for a benchmark's name (``SYSTEMS``) at the defaults plus ``values`` (config keys).

    Raises:
        SystemExit: naming an unknown system.
    """
    from torchslam.config import config_from_dict
    from torchslam.systems.gcslam import GCSlam, GCSlamConfig
    from torchslam.systems.nislam import NISlam, NISlamConfig

    if name == "nislam":
        return NISlam(config_from_dict(NISlamConfig, values))
    if name in SYSTEMS:
        return GCSlam(config_from_dict(GCSlamConfig, {"frontend": name.split("-", 1)[1], **values}))
    raise SystemExit(f"--systems: unknown system {name!r} ({', '.join(SYSTEMS)})")


def reference_of(seq):
    """The trajectory a run of ``seq`` is scored against: the raw ground truth where there is one, else the per-frame one."""
    raw = getattr(seq, "groundtruth_raw", None)
    return raw if raw is not None else seq.groundtruth


def ate_cm(out, seq) -> float | None:
    """ATE RMSE in cm of a run's output against ``reference_of(seq)`` (None without ground truth)."""
    from torchslam.data import Trajectory
    from torchslam.eval import ate

    ref = reference_of(seq)
    return None if ref is None else 100 * float(ate(Trajectory(out.timestamps, out.T_wc), ref).stats["rmse"])


def tree_ate_cm(tree: dict, out, seq) -> float:
    """ATE RMSE in cm of a run's output with ``tree``'s evaluation, against the raw ground truth where there is one."""
    ref = reference_of(seq)
    return 100 * tree["torchslam.eval"].ate(tree["torchslam.data"].Trajectory(out.timestamps, out.T_wc), ref).stats["rmse"]


def print_stage_ratios(before: dict, after: dict, width: int = 20) -> None:
    """Print each stage's ms per frame, before -> after, with the ratio."""
    for k in sorted(set(before) | set(after)):
        b, a = before.get(k, 0.0), after.get(k, 0.0)
        print(f"    {k:{width}s} {b:7.2f} -> {a:7.2f} ms/frame ({b / a if a else float('nan'):.2f}x)")



# A pure-Python busy loop that ends when its parent does (a competing CPU-bound job).
BUSY_LOOP = "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    for _ in range(1_000_000):\n        pass\n"


def start_load(n: int) -> list[subprocess.Popen]:
    """Start ``n`` competing busy-loop processes (one core each) and give them a second to run."""
    procs = [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(n)]
    time.sleep(1.0)  # let them take their cores before measuring
    return procs


def stop_load(procs: list[subprocess.Popen]) -> None:
    """Stop what :func:`start_load` started."""
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def add_matrix_arguments(ap, out: Path) -> None:
    """The options of an end-to-end A/B over systems x sequences, idle and busy (``run_conditions``)."""
    ap.add_argument("--sequences", default="tum_fr1_xyz,7scenes_redkitchen,hololens_dvmvs")
    ap.add_argument("--systems", default="nislam,gcslam-sparse,gcslam-dense")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--busy-procs", type=int, default=1, help="competing busy-loop processes in the busy condition (0: no busy condition)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(out))


def run_conditions(busy_procs: int):
    """Yield ``"idle"``, then ``"busy"`` with ``busy_procs`` busy loops running until the caller's next step (none: idle only)."""
    for condition in ["idle"] + (["busy"] if busy_procs > 0 else []):
        load = start_load(busy_procs) if condition == "busy" else []
        try:
            yield condition
        finally:
            stop_load(load)
