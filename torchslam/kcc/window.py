"""Spatial window of the KCC channels: tapers the static border of the orthographic images.

An orthographic image of a frame's cloud is drawn around the frame's own camera: as the camera
moves, the scene content moves through the image while the image border, and the edge of the
region the camera sees, stay where they are. A correlator that sees that static structure at
full strength votes for zero shift, so every estimated translation is pulled towards zero. On
real frame pairs 2-12 frames apart, with ground-truth attitude, the estimated camera translation
was 4 % (x) and 13 % (y) short of the true one on TUM fr1/xyz and 14 % and 10 % on 7-Scenes
(``scripts/bench_window.py``).

Multiplying both the keyframe's and the frame's channels by a smooth window that falls to zero
at the border (the cosine window of correlation-filter trackers) weakens that pull: the content
near the border, where the two images disagree most, enters with little weight. With it the
same pairs were +1 % and 3 % short on fr1/xyz and 8 % and 9 % on 7-Scenes; pairs 15-25 frames
apart went from 9 % / 19 % to 3 % / 6 % (fr1/xyz) and from 16 % / 14 % to 10 % / 16 %
(7-Scenes). Those 7-Scenes figures predate the registration of its colour to depth
(``torchslam.data.calibration``); registered, its pairs 2-12 apart are 5 % / 6 % short without
the window and 1 % / 3 % with it. Whole runs were not more accurate, though: ATE on the shipped fr1/xyz frames rose
from 1.45 to 2.43 cm (ground-truth attitude) and from 1.11 to 2.65 cm (simulated), on 7-Scenes
from 7.33 to 7.53 and from 7.07 to 7.92 cm with its colour unregistered, and fell from 2.97 to
2.59 and from 3.05 to 2.84 cm with it registered; four synthetic sequences changed by under
0.06 cm. These runs make only four to eight keyframes, so one keyframe's error can decide
them. ``KCCConfig.window`` therefore defaults to ``Window.NONE``. torchslam uses
the Hann window sampled at pixel centres, ``w[i] = sin²(π (i + ½) / n)`` per axis, so no row or
column is exactly zero, and the 2-D window is the product of the two axes.
"""

from __future__ import annotations

import enum
import math

import torch
from torch import Tensor

from ..cache import FifoCache
from ..errors import check_shape, parse_choice

__all__ = ["Window", "apply_window", "frame_taper", "kcc_window", "taper_frame"]


class Window(str, enum.Enum):
    """The window applied to the KCC channels (``KCCConfig.window``).

    NONE: no window (the paper).
    HANN: the separable Hann window at pixel centres (see the module docstring).
    """

    NONE = "none"
    HANN = "hann"


def kcc_window(kind: Window | str, height: int, width: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor | None:
    """The (H, W) window of ``kind``, or None for ``Window.NONE`` (cached per size, dtype and device).

    Args:
        kind: the window.
        height: image height H, pixels.
        width: image width W, pixels.
        dtype: floating dtype of the window.
        device: its device.
    """
    kind = parse_choice(Window, kind, "window")
    if kind is Window.NONE:
        return None

    def axis(n: int) -> Tensor:
        return torch.sin(math.pi * (torch.arange(n, dtype=torch.float64) + 0.5) / n).square()

    return _separable((kind,), axis, height, width, dtype, device)


_WINDOWS: FifoCache[Tensor] = FifoCache(16)


def _separable(name: tuple, axis, height: int, width: int, dtype: torch.dtype, device) -> Tensor:
    """The (H, W) product ``axis(H)[:, None] * axis(W)[None, :]`` of float64 1-D profiles, in
    ``dtype`` on ``device``, kept per (``name``, size, dtype, device)."""
    device = torch.device("cpu") if device is None else torch.device(device)
    key = (*name, int(height), int(width), dtype, device)
    return _WINDOWS.get_or_compute(key, lambda: (axis(height)[:, None] * axis(width)[None, :]).to(dtype=dtype, device=device))


def apply_window(x: Tensor, kind: Window | str) -> Tensor:
    """Multiply (B, C, H, W) KCC channels by the window ``kind`` (``x`` itself for ``Window.NONE``)."""
    check_shape(x, "B C H W", "x")
    w = kcc_window(kind, x.shape[-2], x.shape[-1], x.dtype, x.device)
    return x if w is None else x * w


def frame_taper(height: int, width: int, pixels: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor | None:
    """The (H, W) border taper of a frame's KCC channels (``KCCConfig.frame_taper``), or None for 0 pixels.

    A raised cosine over the outer ``pixels`` of each side, 1 inside: at distance ``d`` from the
    border (pixel centres, ``d = min(i + 1/2, n - i - 1/2)``) the weight is
    ``(1 - cos(pi d / pixels)) / 2`` below ``pixels``. The 2-D taper is the product of the axes.

    Only the frame's channels are tapered, never the keyframe's. A frame's window is centred on
    its predicted content, so its border, fixed to the window, sits where the keyframe's border
    sits when the prediction is right: with both images cut off sharply at the same window
    border, the correlation favours the shift that lines the borders up, and every match is
    drawn towards its prediction (and the prediction, made from earlier matches, towards zero
    motion). Tapered on one side only, the border has no counterpart in the other image to line
    up with. (``Window.HANN`` on both images keeps a common border structure.)
    """
    if not pixels:
        return None

    def axis(n: int) -> Tensor:
        i = torch.arange(n, dtype=torch.float64)
        d = torch.minimum(i + 0.5, n - i - 0.5)
        return torch.where(d >= pixels, torch.ones_like(d), 0.5 - 0.5 * torch.cos(math.pi * d / pixels))

    return _separable(("frame_taper", int(pixels)), axis, height, width, dtype, device)


def taper_frame(x: Tensor, pixels: int) -> Tensor:
    """(B, C, H, W) frame channels times ``frame_taper`` (``x`` itself for 0 pixels); in place on
    ``x`` where no gradient flows (the channels are the caller's fresh tensor)."""
    check_shape(x, "B C H W", "x")
    w = frame_taper(x.shape[-2], x.shape[-1], pixels, x.dtype, x.device)
    if w is None:
        return x
    return x * w if x.requires_grad else x.mul_(w)
