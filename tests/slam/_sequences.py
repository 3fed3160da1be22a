"""A sequence seen through an edit: planted bad frames, Ctrl-C, another camera or attitude stream."""

from __future__ import annotations

from collections.abc import Callable

from torchslam.data import Frame

_ATTRIBUTES = ("name", "camera", "timestamps", "groundtruth", "attitude")


class EditedSequence:
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
