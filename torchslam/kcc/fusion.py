"""Depth translation and keyframe map fusion on orthographic images (NI-SLAM §6.2 and §8).

Both work on whole images with element-wise operations after moving the frame's images back
by the integer image shift found by the correlator.

Convention:
    ``shift`` is the integer content shift ``(s_x, s_y)`` of the frame relative to the keyframe
    (``KCCPrediction.index``), so the frame aligned to the keyframe is
    ``S_{-s}(x)[p] = x[p + s]`` (NI-SLAM's ``S_(-[x̃, ỹ])``). Unlike the circular shift of the
    correlator this one is *not* circular: pixels moved in from outside the image are invalid,
    so the far edge never pretends to match. ``t_z`` follows Eq. (20a): the mean of
    ``frame depth - keyframe depth``, the same "scene content moves by t" sign as ``t_xy``; the
    frame's camera sits at ``-t`` relative to the keyframe.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import torch
from torch import Tensor

import numpy as np

from ..devices import is_host, numpy_viewable
from ..errors import DTypeError, check_float, check_shape, parse_choice
from ._select import where
from .ortho import OrthoImages

__all__ = ["DepthStatistic", "DepthTranslation", "KeyframeMap", "depth_translation", "fuse_keyframe", "keyframe_map", "shift_image"]


@dataclass(frozen=True)
class KeyframeMap:
    """A keyframe's orthographic images with the per-pixel fusion weights of Eq. (23).

    Attributes:
        grey: (B, H, W) grey, 0 where the weight is 0.
        depth: (B, H, W) depth in metres, 0 where the weight is 0.
        weight: (B, H, W) accumulated weight ``w^z`` (the number of observations fused).
    """

    grey: Tensor
    depth: Tensor
    weight: Tensor

    @property
    def valid(self) -> Tensor:
        """(B, H, W) bool: pixels holding at least one observation."""
        return self.weight > 0


@dataclass(frozen=True)
class DepthTranslation:
    """Depth translation of a frame relative to its keyframe (Eq. (20)–(21)).

    Attributes:
        t_z: (B,) mean depth difference ``frame - keyframe`` over well-matched pixels, metres;
            0 where nothing matched.
        variance: (B,) population variance of those differences, m²; ``inf`` where nothing
            matched (no information, weight 0 in a pose graph).
        count: (B,) long number of well-matched pixels ``|W|``.
        matched: (B, H, W) bool set ``W`` in keyframe pixel coordinates.
        ok: (B,) bool, ``count > 0``.
    """

    t_z: Tensor
    variance: Tensor
    count: Tensor
    matched: Tensor
    ok: Tensor


def shift_image(image: Tensor, shift: Tensor, fill: float | bool = 0) -> Tensor:
    """Move images back by integer content shifts: ``out[p] = image[p + s]``, non-circular.

    Args:
        image: (B, H, W) images (any dtype, e.g. a bool mask).
        shift: (B, 2) integer shifts ``(s_x, s_y)`` in pixels.
        fill: value of pixels that come from outside the image.

    Returns:
        (B, H, W) shifted images.
    """
    check_shape(image, "B H W", "image")
    check_shape(shift, f"{image.shape[0]} 2", "shift")
    B, H, W = image.shape
    s = shift.round().long() if shift.is_floating_point() else shift.long()
    if B == 1 and is_host(s):
        # One item whose shift is on the host (reading it waits for no device): the valid part
        # is a rectangle, copied as a slice (no index arithmetic).
        sx, sy = (int(v) for v in s[0].tolist())
        out = torch.full_like(image, fill)
        h, w = H - abs(sy), W - abs(sx)
        if h > 0 and w > 0:
            out[:, max(0, -sy) : max(0, -sy) + h, max(0, -sx) : max(0, -sx) + w] = image[
                :, max(0, sy) : max(0, sy) + h, max(0, sx) : max(0, sx) + w
            ]
        return out
    s = s.to(image.device)
    rows = torch.arange(H, device=image.device)[None, :, None] + s[:, 1, None, None]  # (B, H, 1)
    cols = torch.arange(W, device=image.device)[None, None, :] + s[:, 0, None, None]  # (B, 1, W)
    inside = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)  # (B, H, W)
    idx = (rows.clamp(0, H - 1) * W + cols.clamp(0, W - 1)).reshape(B, H * W)
    out = image.reshape(B, H * W).gather(1, idx).reshape(B, H, W)
    return torch.where(inside, out, torch.full_like(out, fill))


def _views(images, name: str, dims: dict[str, int]) -> tuple[Tensor, Tensor, Tensor]:
    grey, depth, valid = images.grey, images.depth, images.valid
    check_shape(grey, "B H W", f"{name}.grey", dims)
    check_shape(depth, "B H W", f"{name}.depth", dims)
    check_shape(valid, "B H W", f"{name}.valid", dims)
    check_float(grey, f"{name}.grey")
    check_float(depth, f"{name}.depth")
    if valid.dtype != torch.bool:
        raise DTypeError(f"{name}.valid: expected a bool mask, got {valid.dtype}")
    return grey, depth, valid


def _aligned_frame(frame: OrthoImages, shift: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    return (
        shift_image(frame.grey, shift, 0.0),
        shift_image(frame.depth, shift, 0.0),
        shift_image(frame.valid, shift, False),
    )


def _kth_smallest(values: Tensor, k: int) -> Tensor:
    """(1,) the ``k``-th smallest (1-based) of (N,) ``values``, as ``values.kthvalue(k).values``.

    On the host through ``numpy.partition`` (the same order statistic, several times faster
    than ``kthvalue`` on the ~10^5 depth differences of a frame, one thread).
    """
    if numpy_viewable(values):
        return torch.from_numpy(np.partition(values.numpy(), k - 1)[k - 1 : k])
    return values.kthvalue(k).values.reshape(1)


def _masked_lower_median(values: Tensor, mask: Tensor) -> Tensor:
    """(B,) lower median of ``values[b][mask[b]]`` (as ``Tensor.median``), 0 where the mask is empty.

    For one item the selected values are compacted and ``kthvalue`` picks the order statistic in
    linear time, where ``nanmedian`` over the whole image with the rest set to NaN sorts; batches
    use the latter, and so does one item off the host (the compaction reads its size back).
    """
    B = values.shape[0]
    if B == 1 and is_host(values):
        sel = values.reshape(-1)[mask.reshape(-1)]
        if sel.numel() == 0:
            return values.new_zeros(1)
        return _kth_smallest(sel, (sel.numel() + 1) // 2)
    flat = torch.where(mask, values, torch.full_like(values, math.nan)).flatten(1)
    return torch.nan_to_num(flat.nanmedian(dim=1).values, nan=0.0)


def _centred_medians(diff: Tensor, candidate: Tensor, T_d: float) -> tuple[Tensor, Tensor, Tensor]:
    """One item's centre ``c`` (lower median of ``diff`` over ``candidate``), the lower median of
    ``diff`` over ``matched = candidate & (|diff - c| < T_d)``, and ``matched``; as
    ``_masked_lower_median`` twice, from one compaction.

    ``fl(d - c)`` is monotonic in ``d``, so the matched values are a contiguous run of the sorted
    candidates: the ``L`` candidates with ``d - c <= -T_d`` come before it. The median of the
    ``m`` matched values is therefore the ``(L + (m + 1) // 2)``-th smallest candidate, picked by
    a second ``kthvalue`` over the same compacted values.

    Args:
        diff: (1, H, W) depth differences.
        candidate: (1, H, W) bool.
        T_d: depth threshold.

    Returns:
        ((1,) centre, (1,) median of the matched differences, (1, H, W) bool matched); both
        medians are 0 where their set is empty.
    """
    sel = diff.reshape(-1)[candidate.reshape(-1)]
    zero = diff.new_zeros(1)
    if sel.numel() == 0:
        return zero, zero, candidate.clone()
    center = _kth_smallest(sel, (sel.numel() + 1) // 2)
    matched = candidate & ((diff - center).abs() < T_d)
    off = sel - center
    below = int((off <= -T_d).sum())
    m = int(((off > -T_d) & (off < T_d)).sum())
    if m == 0:
        return center, zero, matched
    return center, _kth_smallest(sel, below + (m + 1) // 2), matched


class DepthStatistic(str, enum.Enum):
    """How ``depth_translation`` reduces the well-matched depth differences to ``t_z``."""

    MEAN = "mean"  # the paper, Eq. (21)
    MEDIAN = "median"


def depth_translation(
    frame: OrthoImages,
    keyframe: OrthoImages | KeyframeMap,
    shift: Tensor,
    T_c: float = 0.1,
    T_d: float = 0.1,
    median_center: bool = False,
    statistic: DepthStatistic | str = DepthStatistic.MEAN,
) -> DepthTranslation:
    """Estimate the translation along the optical axis from well-matched pixels (NI-SLAM Eq. (20)–(21)).

    After moving the frame back by ``shift``, a pixel is well matched when both images are
    valid there, ``|Δgrey| < T_c`` and ``|Δdepth| < T_d`` (L1 per channel, Eq. (20b)).
    ``t_z`` is the mean and the variance the population variance of ``Δdepth`` over them.
    Note that ``T_d`` then bounds ``|t_z|`` itself: depth motions beyond ``T_d`` since the
    keyframe leave nothing matched, which ``ok = False`` reports. With ``median_center`` (beyond
    the paper) the depth test becomes ``|Δdepth - m| < T_d`` where ``m`` is the median of
    ``Δdepth`` over the pixels that pass the validity and grey tests, so any depth motion is
    measured while outliers are still rejected. With ``statistic="median"`` (beyond the paper)
    ``t_z`` is the lower median of ``Δdepth`` over the well-matched pixels instead of their mean:
    the depth test still admits pixels up to ``T_d`` (10 cm) off, and across depth edges, where
    the integer shift leaves the two images up to half a pixel apart, those differences are
    one-sided, and the median is not pulled by them as the mean is. The variance stays the
    spread around ``t_z``.

    Args:
        frame: orthographic images of the frame, (B, H, W) each.
        keyframe: the keyframe's orthographic images or fused map, (B, H, W) each.
        shift: (B, 2) integer content shift ``(s_x, s_y)`` (``KCCPrediction.index``).
        T_c: grey threshold, grey units.
        T_d: depth threshold, metres.
        median_center: centre the depth test on the median difference (see above).
        statistic: ``"mean"`` (the paper, Eq. (21)) or ``"median"`` of the matched differences.

    Returns:
        DepthTranslation; never NaN (see its fields for the empty case).
    """
    statistic = parse_choice(DepthStatistic, statistic, "statistic")
    dims: dict[str, int] = {}
    _views(frame, "frame", dims)
    zg, zd, zv = _views(keyframe, "keyframe", dims)
    check_shape(shift, "B 2", "shift", dims)
    xg, xd, xv = _aligned_frame(frame, shift)
    diff = xd - zd.to(xd.dtype)
    candidate = xv & zv & ((xg - zg.to(xg.dtype)).abs() < T_c)
    B = diff.shape[0]
    if median_center and statistic is DepthStatistic.MEDIAN and B == 1 and is_host(diff):
        # Both medians from one compaction of the candidates (see ``_centred_medians``), which
        # reads sizes back: on the host only (on an accelerator it would wait for the device).
        center, t_z, matched = _centred_medians(diff, candidate, T_d)
        m = matched.to(diff.dtype)
        count = matched.sum(dim=(1, 2))
        n = count.to(diff.dtype).clamp_min(1.0)
    else:
        center = diff.new_zeros(B)
        if median_center:
            center = _masked_lower_median(diff, candidate)  # (B,); 0 where no candidate
        matched = candidate & ((diff - center[:, None, None]).abs() < T_d)
        m = matched.to(diff.dtype)
        count = matched.sum(dim=(1, 2))
        n = count.to(diff.dtype).clamp_min(1.0)
        if statistic is DepthStatistic.MEDIAN:
            t_z = _masked_lower_median(diff, matched)
        else:
            t_z = (diff * m).sum(dim=(1, 2)) / n
    var = ((diff - t_z[:, None, None]).square() * m).sum(dim=(1, 2)) / n
    ok = count > 0
    var = torch.where(ok, var, torch.full_like(var, math.inf))
    return DepthTranslation(t_z=t_z, variance=var, count=count, matched=matched, ok=ok)


def keyframe_map(ortho: OrthoImages) -> KeyframeMap:
    """Start a keyframe map from its own orthographic images: weight 1 on valid pixels (§8).

    Args:
        ortho: the new keyframe's orthographic images.

    Returns:
        KeyframeMap with ``weight = valid`` as a float.
    """
    g, d, v = _views(ortho, "ortho", {})
    return KeyframeMap(grey=g, depth=d, weight=v.to(g.dtype))


def fuse_keyframe(
    keyframe: KeyframeMap,
    frame: OrthoImages,
    shift: Tensor,
    t_z: Tensor,
    matched: Tensor,
    psr: Tensor,
    T_M: float = 100.0,
) -> KeyframeMap:
    """Fuse a frame into its keyframe by a weighted moving average where PSR > T_M (NI-SLAM Eq. (23)–(24)).

    The frame's weight ``w^x`` starts as its validity and, after moving it back by ``shift``,
    is zeroed on pixels that *could* be compared with the keyframe but did not match
    (Eq. (24)): ``w^x = valid_x & (matched | ~valid_z)``. Pixels where the keyframe has a hole
    keep their weight, which is how holes get filled. Then, per pixel,

        s   = w^z + w^x
        z^C = (w^z z^C + w^x x^C) / s
        z^D = (w^z z^D + w^x (x^D - t_z)) / s
        w^z = s.

    The paper adds ``e = 1e-7`` to ``s`` to avoid division by zero. Here the same average is
    computed as ``z + (w^x / s)(x - z)`` with the ratio taken only where ``s > 0`` (other pixels
    stay 0), so an aligned identical frame leaves the keyframe bit-identical rather than scaled
    by ``s / (s + e)``, and a hole takes the frame's value exactly.

    Args:
        keyframe: current keyframe map, (B, H, W) fields.
        frame: the frame's orthographic images, (B, H, W) each.
        shift: (B, 2) integer content shift ``(s_x, s_y)`` (``KCCPrediction.index``).
        t_z: (B,) depth translation (``DepthTranslation.t_z``), metres.
        matched: (B, H, W) bool well-matched set (``DepthTranslation.matched``).
        psr: (B,) peak-to-sidelobe ratio of the match.
        T_M: fusion threshold; items with ``psr <= T_M`` are returned unchanged.

    Returns:
        The new KeyframeMap (inputs are not modified).
    """
    dims: dict[str, int] = {}
    check_shape(keyframe.grey, "B H W", "keyframe.grey", dims)
    check_shape(keyframe.depth, "B H W", "keyframe.depth", dims)
    check_shape(keyframe.weight, "B H W", "keyframe.weight", dims)
    check_float(keyframe.weight, "keyframe.weight")
    _views(frame, "frame", dims)
    check_shape(shift, "B 2", "shift", dims)
    check_shape(t_z, "B", "t_z", dims)
    check_shape(matched, "B H W", "matched", dims)
    check_shape(psr, "B", "psr", dims)
    if matched.dtype != torch.bool:
        raise DTypeError(f"matched: expected a bool mask, got {matched.dtype}")
    xg, xd, xv = _aligned_frame(frame, shift)
    wz = keyframe.weight
    dt = wz.dtype
    wx = (xv & (matched | ~keyframe.valid)).to(dt)
    s = wz + wx
    # Incremental form of the moving average, z + (w^x / s)(x - z): identical aligned content
    # stays bit-identical for any weights, and a hole (w^z = 0) takes the frame's value exactly.
    frac = wx / where(s > 0, s, 1.0)
    zg, zd = keyframe.grey.to(dt), keyframe.depth.to(dt)
    grey = zg + frac * (xg.to(dt) - zg)
    depth = zd + frac * ((xd.to(dt) - t_z.to(dt)[:, None, None]) - zd)
    fuse = (psr > T_M)[:, None, None]
    if is_host(fuse) and bool(fuse.all()):
        # Every item fuses (the system calls it for those only): the selection below would copy
        # the fused images unchanged. On the host the flags are read without waiting.
        return KeyframeMap(grey=grey, depth=depth, weight=s)
    return KeyframeMap(
        grey=where(fuse, grey, zg),
        depth=where(fuse, depth, zd),
        weight=where(fuse, s, wz),
    )
