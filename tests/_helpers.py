"""Helpers the tests share: paths, seeded generators, tolerances, edited sequences, scripts.

Import them as ``from tests._helpers import ...``.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import torch

from torchslam.data import Frame, Sequence

REPO_ROOT = Path(__file__).resolve().parents[1]

# Per-dtype base tolerance (scaled per check, absolute or relative) of identities: exp/log round
# trips, FFT against direct sums.
TOL = {torch.float64: 1e-10, torch.float32: 2e-5}


def data_root() -> Path:
    """Folder of the real sequences: ``$TORCHSLAM_DATA`` or ``../shared/data`` beside the repo."""
    env = os.environ.get("TORCHSLAM_DATA")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "data")


def seeded(seed: int = 0) -> torch.Generator:
    """A CPU ``torch.Generator`` seeded with ``seed``."""
    return torch.Generator().manual_seed(seed)


def _load_file(module_name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses look their module up while it executes
    spec.loader.exec_module(module)
    return module


def load_script(name: str) -> ModuleType:
    """Import ``scripts/<name>.py`` as a module.

    The benchmarks import their shared ``scripts/_bench.py`` as ``_bench`` (a script's folder is
    on ``sys.path`` when it runs); here it is loaded by path under that name instead, so
    ``scripts/`` need not go on the tests' ``sys.path``.
    """
    if "_bench" not in sys.modules:
        _load_file("_bench", REPO_ROOT / "scripts" / "_bench.py")
    return _load_file(f"torchslam_script_{name}", REPO_ROOT / "scripts" / f"{name}.py")


# ----------------------------------------------------------------------------- systems


def run_with_ate(system, seq):
    """Run ``system`` over ``seq``; return the ``RunResult`` and the ATE of its output against
    ``seq.groundtruth``."""
    from torchslam.data import Trajectory
    from torchslam.eval import ate
    from torchslam.systems import run_sequence

    result = run_sequence(system, seq)
    out = result.output
    return result, ate(Trajectory(out.timestamps, out.T_wc), seq.groundtruth)


def run_nislam(seq, **cfg):
    """:func:`run_with_ate` of NI-SLAM with the config overrides ``cfg`` (nested dicts allowed)."""
    from torchslam.config import config_from_dict
    from torchslam.systems.nislam import NISlam, NISlamConfig

    return run_with_ate(NISlam(config_from_dict(NISlamConfig, cfg)), seq)


def run_gcslam(seq, **cfg):
    """:func:`run_with_ate` of GC-SLAM with the overrides ``cfg``, optimising inline unless
    ``threaded=True`` is among them (so a run is deterministic)."""
    from torchslam.config import config_from_dict
    from torchslam.systems.gcslam import GCSlam, GCSlamConfig

    return run_with_ate(GCSlam(config_from_dict(GCSlamConfig, {"threaded": False, **cfg})), seq)


# ----------------------------------------------------------------------------- sequences

_ATTRIBUTES = ("name", "camera", "timestamps", "groundtruth", "attitude")


class EditedSequence(Sequence):
    """``seq`` with each frame passed through ``edit`` (which may raise) on the way out.

    Keyword overrides replace the sequence's ``name``, ``camera``, ``timestamps``,
    ``groundtruth`` or ``attitude``.
    """

    def __init__(self, seq, edit: Callable[[Frame], Frame] | None = None, **overrides):
        unknown = set(overrides) - set(_ATTRIBUTES)
        if unknown:
            raise TypeError(f"EditedSequence: cannot override {sorted(unknown)}")
        self.seq = seq
        self.edit = edit or (lambda f: f)
        for attr in _ATTRIBUTES:
            setattr(self, attr, overrides[attr] if attr in overrides else getattr(seq, attr, None))

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int) -> Frame:
        return self.edit(self.seq[i])

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def interrupt_at(index: int) -> Callable[[Frame], Frame]:
    """An edit that presses Ctrl-C when frame ``index`` is requested."""

    def edit(f: Frame) -> Frame:
        if f.index == index:
            raise KeyboardInterrupt
        return f

    return edit


def copy_tum_frames(src: Path, dst: Path, frames: int) -> Path:
    """Copy the first ``frames`` colour and depth images of the TUM folder ``src`` (with its lists,
    ground truth, accelerometer and calibration) into ``dst``; return ``dst``.

    Name ``dst`` like ``src`` where the calibration comes from the folder-name preset.
    """
    dst.mkdir(parents=True)
    for name in ("rgb.txt", "depth.txt"):
        lines = (src / name).read_text().splitlines()
        body = [ln for ln in lines if ln.strip() and not ln.startswith("#")][:frames]
        (dst / name).write_text("\n".join([ln for ln in lines if ln.startswith("#")] + body) + "\n")
        for ln in body:
            rel = ln.split()[1]
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / rel, dst / rel)
    for name in ("groundtruth.txt", "accelerometer.txt", "calibration.txt"):
        if (src / name).is_file():
            shutil.copyfile(src / name, dst / name)
    return dst
