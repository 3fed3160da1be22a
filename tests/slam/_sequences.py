"""A sequence seen through an edit: planted bad frames, Ctrl-C, another camera or attitude stream;
a few frames of a real TUM folder copied for editing."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

from torchslam.data import Frame, Sequence

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
