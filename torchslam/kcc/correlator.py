"""Kernel cross-correlator (KCC): train on a keyframe, predict the image shift of a frame (NI-SLAM §5–§7).

Everything is batched over ``(B, C, H, W)`` images and runs through ``torch.fft.rfft2``.

Kernel (NI-SLAM Eq. (12)–(16)), with ``N = C * H * W`` the number of elements of one image:

    κ_z(x)[τ] = exp(-max(0, ‖x‖² + ‖z‖² - 2 c[τ]) / (σ² N)),   c = F⁻¹(Σ_c x̂_c ⊙ conj(ẑ_c)),

i.e. a Gaussian of the *mean* squared difference per element between ``x`` and ``z`` circularly
shifted by ``τ``. The paper leaves the normalisation of Eq. (16) implicit; dividing by ``N`` is
the usual choice for Gaussian correlation kernels and makes ``σ`` (0.2 in the paper) independent
of the image size. The ``max(0, ·)`` only removes negative round-off.

Energies by Parseval. ``rfft2`` keeps only the non-negative frequencies of the last axis, so the
columns that stand for a conjugate pair (all except DC and, for even ``W``, Nyquist) must count
twice: ``‖x‖² = (1/HW) Σ_k w_k |x̂_k|²`` with ``w = 1`` for those two columns and ``2`` otherwise.
torchslam uses this weighted sum, which equals the spatial ``Σ x²`` to round-off (tested). A plain
sum over the half spectrum instead under-counts each energy by a constant ``Δ``: half the energy
outside the ``k_x = 0`` (and Nyquist) columns, about ``N v / 2`` for channels of variance ``v``
along the rows. Because the energies enter the kernel only as ``exp(-(‖x‖² + ‖z‖²)/(σ² N))``
(with no clamp active), that error multiplies every kernel value by ``exp((Δ_x + Δ_z)/(σ² N))``;
in ``ĥ* = ĝ/(κ̂_z(z) + λ)`` this is the same as dividing ``λ`` by ``a = exp(2 Δ_z/(σ² N))`` and
scaling ``g`` by a constant. With ``σ = 0.2``, ``a ≈ 5`` for raw grey of standard deviation 0.25
and ``a ≈ e^25`` for standardised channels: the regulariser silently vanishes. The test suite
checks this equivalence explicitly. (With a clamp of the argument at 0, as is usual, the
under-counted energies make it negative near the peak and the kernel saturates at 1 instead.)

Training and prediction (Eq. (11), (17)): the desired output ``g`` is a delta at ``[0, 0]``
(``ĝ = 1``), ``ĥ* = 1 / (κ̂_z(z) + λ)`` and ``g(x) = F⁻¹(κ̂_z(x) ⊙ ĥ*)``.

Convention:
    If the frame's image is the keyframe's image with its content moved by ``s`` pixels,
    ``x[p] = z[p - s]`` (``torch.roll(z, (s_y, s_x), (-2, -1))``), then ``g(x)`` peaks at ``s``.
    Shifts are reported as ``(s_x, s_y)`` = (columns, rows), wrapped to the signed range
    ``[-⌊n/2⌋, ⌈n/2⌉ - 1]``. With orthographic images of resolution ``r``, ``t_xy = r * s`` is
    the metric translation of the scene content in the keyframe attitude frame (Eq. (18)); the
    frame's camera sits at ``-t_xy`` relative to the keyframe's.
"""

from __future__ import annotations

import enum
import math
from typing import ClassVar
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..cache import FifoCache
from ..devices import is_host
from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, DTypeError, Limit, ShapeError, check_float, check_limits, check_shape, parse_choice
from ..optim import positive_parameter, positive_value
from ._select import where
from .fusion import DepthStatistic
from .window import Window, apply_window, frame_taper, kcc_window, taper_frame
from .peak import Peak, _argmax, _check_response, _per_item, _refine_quadratic, _wrap, peak_to_sidelobe, shift_variance, soft_argmax

__all__ = [
    "ChannelNorm",
    "FeatureKind",
    "KCCConfig",
    "KCCFilter",
    "KCCPrediction",
    "KernelCorrelator",
    "Peak",
    "Subpixel",
    "find_peak",
    "kcc_features",
    "kcc_features_masked",
    "kcc_predict",
    "kcc_response",
    "kcc_train",
    "kernel_correlation",
    "masked_kernel_map",
    "peak_to_sidelobe",
    "shift_variance",
    "soft_argmax",
    "spectral_energy",
    "standardize_masked",
]


class Subpixel(str, enum.Enum):
    """How the integer arg-max of the correlation output is refined.

    NONE: integer peak only (the paper).
    QUADRATIC: vertex of a least-squares 2-D quadratic on the 3x3 neighbourhood (with
        wrap-around). Cheap, but biased by up to ~0.17 px on the sharp, sinc-like KCC peaks.
    FOURIER: Newton iterations on the trigonometric interpolant of ``g`` smoothed by a Gaussian
        of ``smoothing`` pixels, evaluated exactly from the spectrum (O(HW) per step). Smoothing
        with a symmetric kernel does not move the maximum of a symmetric peak but suppresses the
        high-frequency ringing and aliasing the Gaussian kernel introduces; on Fourier-shifted
        real images it is accurate to ~0.02 px.
    """

    NONE = "none"
    QUADRATIC = "quadratic"
    FOURIER = "fourier"


class ChannelNorm(str, enum.Enum):
    """How grey and depth orthographic images become KCC channels.

    RAW: grey in [0, 1] and depth in metres as rendered, 0 at invalid pixels (the paper).
    STANDARDIZE: each image and channel separately shifted to zero mean and scaled to unit
        standard deviation over its valid pixels; invalid pixels are 0 (the mean). This balances
        the two channels whatever the depth range, makes the kernel insensitive to a constant
        depth offset (motion along the optical axis) and keeps the hole pattern of the mask
        from dominating the correlation. On frame pairs of ``tum_fr1_xyz`` (ground-truth
        attitude, σ = 0.2) it gave about half the image-shift error of RAW and higher PSR.
    """

    RAW = "raw"
    STANDARDIZE = "standardize"


class FeatureKind(str, enum.Enum):
    """Where the KCC channels of an orthographic image come from.

    HANDCRAFTED: grey and depth (``kcc_features`` with ``channel_norm`` and ``fill_holes``), the paper's.
    LEARNED: a small convolutional network on the orthographic grey, depth and validity
        (``torchslam.kcc.features.KCCFeatureNet``), trained through the correlator on synthetic
        sequences; its weights ship with the package (``KCCConfig.features_weights``).
    """

    HANDCRAFTED = "handcrafted"
    LEARNED = "learned"


@dataclass(frozen=True)
class KCCConfig:
    """Settings of the NI-SLAM front-end core; defaults are the paper's (§10.1) where it gives them.

    Attributes:
        sigma: Gaussian kernel width σ (Eq. (12)), relative to the per-element RMS difference.
        lam: regulariser λ of the filter (Eq. (11)).
        T_c: grey threshold of a well-matched pixel (Eq. (20b)), grey units in [0, 1].
        T_d: depth threshold of a well-matched pixel (Eq. (20b)), metres.
        T_K: PSR below which a new keyframe is created (Eq. (22)).
        T_M: PSR above which the frame is fused into the keyframe (§8).
        ortho_height: orthographic image height in pixels (the paper does not state the size;
            360 x 480 follows the reference implementation).
        ortho_width: orthographic image width in pixels.
        coverage: fraction of sampled points the orthographic image must cover (§4.2).
        sample_step: one point in ``sample_step`` is sampled to choose the resolution (§4.2).
        psr_window: side of the square excluded around the peak from the PSR sidelobe.
        subpixel: peak refinement (beyond the paper, which uses the integer peak).
        subpixel_smoothing: Gaussian smoothing in pixels for ``Subpixel.FOURIER``.
        subpixel_iterations: Newton iterations for ``Subpixel.FOURIER``.
        channel_norm: how grey and depth become KCC channels.
        fill_holes: odd window of the hole filling of the KCC input (1 = off, the paper); see
            ``kcc_features``.
        window: spatial window of the KCC channels of keyframe and frame (``Window``; the paper
            uses none): tapers the static image border, which pulls shifts towards zero. It
            halves that pull on frames a few centimetres apart but not at the distances tracking
            reaches before a new keyframe, and did not improve trajectories, so it is off by
            default (``torchslam.kcc.window``).
        frame_taper: pixels of a raised-cosine taper at the border of each frame's channels,
            the keyframe's left whole (beyond the paper; 0: off, the paper). See
            ``torchslam.kcc.window.frame_taper`` for why one side only.
        depth_median_center: select well-matched depths around their median instead of around
            0 (beyond the paper; see ``depth_translation``).
        depth_statistic: ``t_z`` as the ``"mean"`` (the paper) or ``"median"`` of the
            well-matched depth differences (``depth_translation``).
        masked_kernel: sum each shift's kernel distance over the pixels both images hold (their
            masks' overlap at that shift) instead of over the whole window with 0 at holes
            (beyond the paper; see ``masked_kernel_map``): holes and invalid regions that move
            with the camera then no longer pull the peak towards no motion.
        soft_argmax: use the differentiable soft arg-max instead of the hard peak for the shift.
        temperature: soft arg-max temperature, in units of the correlation output (≈1 at a
            perfect match).
        features: the channels' source (``FeatureKind``): the hand-crafted grey and depth, or
            the learned network's channels.
        features_weights: checkpoint of the learned channels' network (``KCCFeatureNet``);
            empty for the weights that ship with torchslam. Only read with
            ``features="learned"``.
    """

    sigma: float = 0.2
    lam: float = 0.1
    T_c: float = 0.1
    T_d: float = 0.1
    T_K: float = 50.0
    T_M: float = 100.0
    ortho_height: int = 360
    ortho_width: int = 480
    coverage: float = 0.8
    sample_step: int = 25
    psr_window: int = 11
    subpixel: Subpixel = Subpixel.FOURIER
    subpixel_smoothing: float = 1.0
    subpixel_iterations: int = 5
    channel_norm: ChannelNorm = ChannelNorm.STANDARDIZE
    fill_holes: int = 3
    window: Window = Window.NONE
    frame_taper: int = 0
    depth_median_center: bool = False
    depth_statistic: DepthStatistic = DepthStatistic.MEAN
    masked_kernel: bool = False
    soft_argmax: bool = False
    temperature: float = 0.02
    features: FeatureKind = FeatureKind.HANDCRAFTED
    features_weights: str = ""

    LIMITS: ClassVar[dict[str, Limit]] = {
        "sigma": POSITIVE, "lam": POSITIVE, "T_c": POSITIVE, "T_d": POSITIVE, "T_K": NON_NEGATIVE, "T_M": NON_NEGATIVE,
        "ortho_height": AT_LEAST_1, "ortho_width": AT_LEAST_1, "coverage": Limit(gt=0, le=1), "sample_step": AT_LEAST_1,
        "psr_window": Limit(ge=1, odd=True), "subpixel_smoothing": POSITIVE, "subpixel_iterations": AT_LEAST_1,
        "fill_holes": Limit(ge=1, odd=True), "temperature": POSITIVE, "frame_taper": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "subpixel", parse_choice(Subpixel, self.subpixel, "subpixel"))
        object.__setattr__(self, "channel_norm", parse_choice(ChannelNorm, self.channel_norm, "channel_norm"))
        object.__setattr__(self, "window", parse_choice(Window, self.window, "window"))
        object.__setattr__(self, "depth_statistic", parse_choice(DepthStatistic, self.depth_statistic, "depth_statistic"))
        object.__setattr__(self, "features", parse_choice(FeatureKind, self.features, "features"))
        if not isinstance(self.features_weights, str):
            raise ConfigError(f"features_weights: expected a file path (a string), got {self.features_weights!r}")
        check_limits(self)
        if not self.T_M > self.T_K:
            raise ConfigError(f"T_M: expected T_M > T_K (the paper's condition), got T_M={self.T_M}, T_K={self.T_K}")


# --------------------------------------------------------------------------------------------
# helpers


def _half_weights(width: int, ref: Tensor) -> Tensor:
    """(W//2+1,) Parseval weights of an rfft axis: DC (and Nyquist for even W) once, others twice."""
    w = torch.full((width // 2 + 1,), 2.0, dtype=ref.dtype, device=ref.device)
    w[0] = 1.0
    if width % 2 == 0:
        w[-1] = 1.0
    return w


def _abs2(z: Tensor) -> Tensor:
    # real^2 + imag^2 rather than abs()**2: finite gradients at 0.
    return z.real.square() + z.imag.square()


def _energy(x_hat: Tensor, width: int, weighted: bool = True) -> Tensor:
    """(B,) energy Σ x² of (B, C, H, W) images from their (B, C, H, W//2+1) rfft2 spectra."""
    H = x_hat.shape[-2]
    p = _abs2(x_hat)
    if weighted:
        w = _half_weights(width, p)
        p = p.mul_(w) if not (torch.is_grad_enabled() and p.requires_grad) else p * w
    return p.sum(dim=(-3, -2, -1)) / (H * width)


def box_sum(x: Tensor, k: int) -> Tensor:
    """Sum over the k x k window centred on each pixel of (B, C, H, W) images, zero outside (separable)."""
    H, W = x.shape[-2:]
    if k == 1:
        return x.clone()
    if k == 3 and not (torch.is_grad_enabled() and x.requires_grad):
        return _box_sum3(x)
    h = k // 2
    xp = F.pad(x, (h, h, 0, 0))
    rows = xp[..., 0:W] + xp[..., 1 : 1 + W]
    for i in range(2, k):  # k is a small window side, not a pixel count
        rows += xp[..., i : i + W]
    rp = F.pad(rows, (0, 0, h, h))
    out = rp[..., 0:H, :] + rp[..., 1 : 1 + H, :]
    for i in range(2, k):
        out += rp[..., i : i + H, :]
    return out


def _box_sum3(x: Tensor) -> Tensor:
    """``box_sum(x, 3)`` without the padded copies: the same sums in the same order.

    Each axis sums ``(a_{j-1} + a_j) + a_{j+1}`` with the missing neighbours at the border as
    ``+0``, exactly as the padded form adds them (``0 + a`` is ``a + 0``), so the values and
    even the signs of zeros agree.
    """
    rows = torch.empty_like(x)
    torch.add(x[..., :-1], x[..., 1:], out=rows[..., 1:])
    torch.add(x[..., :1], 0.0, out=rows[..., :1])
    rows[..., :-1] += x[..., 1:]
    rows[..., -1:] += 0.0
    out = torch.empty_like(x)
    torch.add(rows[..., :-1, :], rows[..., 1:, :], out=out[..., 1:, :])
    torch.add(rows[..., :1, :], 0.0, out=out[..., :1, :])
    out[..., :-1, :] += rows[..., 1:, :]
    out[..., -1:, :] += 0.0
    return out


def _check_images(x: Tensor, name: str, dims: dict[str, int]) -> None:
    check_shape(x, "B C H W", name, dims)
    check_float(x, name)


# --------------------------------------------------------------------------------------------
# features and kernel


def kcc_features(
    grey: Tensor,
    depth: Tensor,
    valid: Tensor,
    mode: ChannelNorm | str = ChannelNorm.STANDARDIZE,
    fill_holes: int = 3,
) -> Tensor:
    """Stack orthographic grey and depth images into the two KCC channels.

    Hole filling (beyond the paper): an orthographic image of a 640x480 cloud at 360x480 has
    holes in about half its pixels, in a moiré pattern of the camera and orthographic grids.
    That pattern does not move with the content under sub-pixel shifts, and limited planted
    sub-pixel translations through ``orthographic_project`` to ~0.6 px. Filling each hole with
    the mean of the valid pixels in a ``fill_holes x fill_holes`` window (normalised box filter,
    no wrap-around) brings them under 0.1 px. Pixels with no valid neighbour stay holes. Only
    the correlator's input is filled; depth translation and fusion use the rendered pixels.

    Args:
        grey: (B, H, W) grey values in [0, 1].
        depth: (B, H, W) depth in metres.
        valid: (B, H, W) bool validity.
        mode: ``ChannelNorm.RAW`` (the paper) or ``ChannelNorm.STANDARDIZE`` (see the enum).
        fill_holes: odd window side of the hole filling; 1 turns it off (the paper).

    Returns:
        (B, 2, H, W) channels ``(grey, depth)``, 0 at pixels that remain invalid.
    """
    return kcc_features_masked(grey, depth, valid, mode, fill_holes)[0]


def kcc_features_masked(
    grey: Tensor,
    depth: Tensor,
    valid: Tensor,
    mode: ChannelNorm | str = ChannelNorm.STANDARDIZE,
    fill_holes: int = 3,
) -> tuple[Tensor, Tensor]:
    """``kcc_features`` and the mask of the pixels it holds a value at.

    Returns:
        (B, 2, H, W) channels (``kcc_features``) and the (B, 1, H, W) mask, in their dtype: 1
        where the pixel is valid or was filled from a valid neighbour, 0 where it stays a hole.
    """
    dims: dict[str, int] = {}
    check_shape(grey, "B H W", "grey", dims)
    check_shape(depth, "B H W", "depth", dims)
    check_shape(valid, "B H W", "valid", dims)
    check_float(grey, "grey")
    check_float(depth, "depth")
    if valid.dtype != torch.bool:
        raise DTypeError(f"valid: expected a bool mask, got {valid.dtype}")
    mode = parse_choice(ChannelNorm, mode, "mode")
    if not (isinstance(fill_holes, int) and fill_holes >= 1 and fill_holes % 2 == 1):
        raise ConfigError(f"fill_holes: expected a positive odd integer, got {fill_holes!r}")
    dtype = grey.dtype
    depth = depth.to(dtype)
    m = valid[:, None].to(dtype)  # (B, 1, H, W)
    if fill_holes == 1:
        x = torch.stack([grey, depth], dim=1)  # (B, 2, H, W)
    else:
        # Ratio of box sums of x*m and of m: the mean over the valid pixels of each window.
        if torch.is_grad_enabled() and (grey.requires_grad or depth.requires_grad):
            xm = torch.cat([grey[:, None] * m, depth[:, None] * m, m], dim=1)  # (B, 3, H, W)
        else:  # the same products written into their channels, without the copies
            B, H, W = grey.shape
            xm = grey.new_empty(B, 3, H, W)
            torch.mul(grey[:, None], m, out=xm[:, 0:1])
            torch.mul(depth[:, None], m, out=xm[:, 1:2])
            xm[:, 2:3] = m
        sums = box_sum(xm, fill_holes)  # (B, 3, H, W)
        num, den = sums[:, :2], sums[:, 2:]
        has = den > 0
        # x * m is x itself where valid; den counts pixels, so where(has, den, 1) is clamp_min(1).
        x = where(valid[:, None], xm[:, :2], num / den.clamp_min(1.0))
        m = (valid[:, None] | has).to(dtype)
    if mode is ChannelNorm.RAW:
        return x * m, m
    return standardize_masked(x, m), m


def _fill_mask(valid: Tensor, fill_holes: int, dtype: torch.dtype) -> Tensor:
    """(B, 1, H, W) mask of ``kcc_features_masked``: valid, or a hole with a valid pixel in its window."""
    m = valid[:, None].to(dtype)
    if fill_holes == 1:
        return m
    return (valid[:, None] | (box_sum(m, fill_holes) > 0)).to(dtype)


def standardize_masked(x: Tensor, m: Tensor) -> Tensor:
    """Shift each image and channel of ``x`` to zero mean and unit variance over the mask, 0 off it.

    Args:
        x: (B, C, H, W) images.
        m: (B, 1, H, W) 0/1 mask in the dtype of ``x``.

    Returns:
        (B, C, H, W); a channel constant over the mask stays 0 instead of dividing by zero.
    """
    n = m.sum(dim=(-2, -1), keepdim=True).clamp_min(1.0)
    mean = (x * m).sum(dim=(-2, -1), keepdim=True) / n
    centred = x - mean
    grad = torch.is_grad_enabled() and (x.requires_grad or m.requires_grad)
    # Without gradients the products are taken in place on their fresh operands: same values.
    sq = centred.square() if grad else centred.square().mul_(m)
    var = (sq * m if grad else sq).sum(dim=(-2, -1), keepdim=True) / n
    inv = torch.where(var > 0, torch.rsqrt(var.clamp_min(torch.finfo(x.dtype).tiny)), torch.zeros_like(var))
    return centred * inv * m if grad else centred.mul_(inv).mul_(m)


def spectral_energy(x_hat: Tensor, width: int) -> Tensor:
    """Return the energy ``Σ x²`` of real images from their ``rfft2`` half spectra (Parseval).

    Args:
        x_hat: (B, C, H, W//2+1) complex ``torch.fft.rfft2`` of (B, C, H, W) real images.
        width: the spatial width ``W`` (the half spectrum cannot tell odd from even ``W``).

    Returns:
        (B,) energy summed over channels and pixels, with the half-spectrum weights described in
        the module docstring.
    """
    check_shape(x_hat, "B C H K", "x_hat")
    if not x_hat.is_complex():
        raise DTypeError(f"x_hat: expected a complex spectrum, got {x_hat.dtype}")
    if x_hat.shape[-1] != width // 2 + 1:
        raise ShapeError(f"x_hat: expected last dimension {width // 2 + 1} for width {width}, got {x_hat.shape[-1]}")
    return _energy(x_hat, width)


def _kernel_map(x_hat: Tensor, z_hat: Tensor, ex: Tensor, ez: Tensor, sigma: Tensor, H: int, W: int) -> Tensor:
    """(B, H, W) Gaussian kernel map κ_z(x) from spectra and energies (Eq. (16))."""
    C = x_hat.shape[1]
    cross = torch.fft.irfft2((x_hat * z_hat.conj()).sum(dim=1), s=(H, W))  # (B, H, W)
    scale = sigma.square() * (C * H * W)
    if torch.is_grad_enabled() and any(t.requires_grad for t in (cross, ex, ez, scale)):
        d2 = (ex + ez)[:, None, None] - 2.0 * cross
        return torch.exp(-d2.clamp_min(0.0) / scale)
    # The same operations in place on the fresh ``cross`` (a - 2c is -2c + a exactly, and
    # -(d / s) is (-d) / s): the values above without four full-size temporaries.
    d2 = cross.mul_(-2.0).add_((ex + ez)[:, None, None]).clamp_min_(0.0)
    return d2.neg_().div_(scale).exp_()


def kernel_correlation(x: Tensor, z: Tensor, sigma) -> Tensor:
    """Compute the Gaussian kernel map ``κ_z(x)`` of every circular shift through the FFT (Eq. (16)).

    Args:
        x: (B, C, H, W) test images.
        z: (B, C, H, W) keyframe images.
        sigma: kernel width, a float or a 0-d / (B,) tensor.

    Returns:
        (B, H, W) ``κ(x, S_τ(z))`` at each shift ``τ = (row, col)`` where ``S_τ(z)[p] = z[p - τ]``.
    """
    dims: dict[str, int] = {}
    _check_images(x, "x", dims)
    _check_images(z, "z", dims)
    z = z.to(x.dtype)
    H, W = x.shape[-2:]
    x_hat, z_hat = torch.fft.rfft2(x), torch.fft.rfft2(z)
    s = _per_item(sigma, x, "sigma")
    return _kernel_map(x_hat, z_hat, _energy(x_hat, W), _energy(z_hat, W), s, H, W)


def _mask_terms(x: Tensor, mask: Tensor) -> Tensor:
    """(B, 2, H, W//2+1) spectra of a mask and of ``Σ_c x_c² / mask`` (0 off the mask)."""
    # x is 0 where the mask is, so dividing by the mask clamped to the smallest normal gives 0 there.
    q = x.square().sum(dim=1, keepdim=True) / mask.clamp_min(torch.finfo(mask.dtype).tiny)
    return torch.fft.rfft2(torch.cat([mask, q], dim=1))


def _masked_kernel_map(x_hat: Tensor, z_hat: Tensor, x_terms: Tensor, z_terms: Tensor, sigma: Tensor, H: int, W: int) -> Tensor:
    """(B, H, W) masked Gaussian kernel map from spectra (``masked_kernel_map``)."""
    C = x_hat.shape[1]
    mx, qx = x_terms[:, 0], x_terms[:, 1]
    d2_hat = qx * z_terms[:, 0].conj() + mx * z_terms[:, 1].conj() - 2.0 * (x_hat * z_hat.conj()).sum(dim=1)
    d2 = torch.fft.irfft2(d2_hat, s=(H, W)).clamp_min(0.0)
    return torch.exp(-d2 / (sigma.square() * (C * H * W)))


def masked_kernel_map(x: Tensor, z: Tensor, sigma, x_mask: Tensor, z_mask: Tensor) -> Tensor:
    """Gaussian kernel map of every circular shift over the pixels both images hold (``KCCConfig.masked_kernel``).

    The channels are read as weights times values, ``x = w_x x̃`` and ``z = w_z z̃`` (0 where the
    weight is 0: a hole, or a border a taper has faded out). At each shift ``τ`` (``z`` moved by
    ``τ``, as in ``kernel_correlation``) the squared distance is summed over the overlap of the
    two weights only::

        D(τ) = Σ_p w_x(p) w_z(p-τ) Σ_c (x̃_c(p) - z̃_c(p-τ))²,   κ(τ) = exp(-D(τ) / (σ² C H W)).

    The unmasked kernel (``kernel_correlation``) counts a hole as the value 0, the mean of the
    standardised channels, so its distance also holds ``Σ x̃²`` over the frame's pixels that meet
    a keyframe hole at that shift and ``Σ z̃²`` over the keyframe's pixels that meet a frame hole.
    Where those holes move with the camera (its invalid borders, the sensor's hole pattern,
    occlusion shadows), that term is smallest at no motion and pulls the peak towards it; where
    they move with the scene (surfaces without depth), it is a cue to the shift that the masked
    kernel gives up. With full weights the two kernels agree. The distance is not divided by the
    overlap's size: tried on real frame pairs, the mean over the overlap measured the same
    shifts with more frame-to-frame noise. Every term is one correlation through ``rfft2``: two
    extra forward transforms per frame (its weights and weighted energy, in one call), the
    keyframe's kept in its filter.

    Args:
        x: (B, C, H, W) test channels.
        z: (B, C, H, W) keyframe channels.
        sigma: kernel width, a float or a 0-d / (B,) tensor.
        x_mask: (B, 1, H, W) weights of ``x`` in [0, 1].
        z_mask: (B, 1, H, W) weights of ``z``.

    Returns:
        (B, H, W) kernel values at each shift ``τ = (row, col)``.
    """
    dims: dict[str, int] = {}
    _check_images(x, "x", dims)
    _check_images(z, "z", dims)
    _check_mask(x_mask, x, "x_mask")
    _check_mask(z_mask, x, "z_mask")
    z = z.to(x.dtype)
    H, W = x.shape[-2:]
    s = _per_item(sigma, x, "sigma")
    return _masked_kernel_map(
        torch.fft.rfft2(x), torch.fft.rfft2(z), _mask_terms(x, x_mask.to(x.dtype)), _mask_terms(z, z_mask.to(x.dtype)), s, H, W
    )


def _check_mask(mask: Tensor, x: Tensor, name: str) -> None:
    check_shape(mask, f"{x.shape[0]} 1 {x.shape[-2]} {x.shape[-1]}", name)
    check_float(mask, name)


# --------------------------------------------------------------------------------------------
# training and prediction


@dataclass(frozen=True)
class KCCFilter:
    """A KCC trained on keyframes (Eq. (11)).

    Attributes:
        z_hat: (B, C, H, W//2+1) complex rfft2 spectrum of the keyframe channels.
        z_energy: (B,) keyframe energy ``‖z‖²``.
        h_hat: (B, H, W//2+1) complex filter ``ĥ* = ĝ / (κ̂_z(z) + λ)`` with ``ĝ = 1``.
        height: image height H.
        width: image width W.
        mask_terms: (B, 2, H, W//2+1) spectra of the keyframe's mask and weighted energy, when
            trained with a mask (``masked_kernel_map``); frames are then matched with theirs.
    """

    z_hat: Tensor
    z_energy: Tensor
    h_hat: Tensor
    height: int
    width: int
    mask_terms: Tensor | None = None


def kcc_train(z: Tensor, sigma, lam, mask: Tensor | None = None) -> KCCFilter:
    """Train a kernel cross-correlator on keyframe images (NI-SLAM Eq. (9)–(11)).

    The desired output is a delta at ``[0, 0]`` (§6.1), so ``ĝ = 1`` and
    ``ĥ* = 1 / (κ̂_z(z) + λ)``, the element-wise minimiser of Eq. (9).

    Args:
        z: (B, C, H, W) keyframe channels (e.g. from ``kcc_features``).
        sigma: kernel width σ, a float or a 0-d / (B,) tensor (may require grad).
        lam: regulariser λ, a float or a 0-d / (B,) tensor (may require grad).
        mask: optional (B, 1, H, W) weights of ``z``: the kernel is then ``masked_kernel_map``'s,
            here and when frames are matched against the filter (they must pass theirs).

    Returns:
        KCCFilter holding the keyframe spectrum, energy and filter.
    """
    dims: dict[str, int] = {}
    _check_images(z, "z", dims)
    H, W = z.shape[-2:]
    s = _per_item(sigma, z, "sigma")
    lm = _per_item(lam, z, "lam")
    z_hat = torch.fft.rfft2(z)
    ez = _energy(z_hat, W)
    if mask is None:
        kzz_hat = torch.fft.rfft2(_kernel_map(z_hat, z_hat, ez, ez, s, H, W))
        return KCCFilter(z_hat=z_hat, z_energy=ez, h_hat=1.0 / (kzz_hat + lm), height=H, width=W)
    _check_mask(mask, z, "mask")
    mask = mask.to(z.dtype)
    terms = _mask_terms(z, mask)
    kzz_hat = torch.fft.rfft2(_masked_kernel_map(z_hat, z_hat, terms, terms, s, H, W))
    return KCCFilter(z_hat=z_hat, z_energy=ez, h_hat=1.0 / (kzz_hat + lm), height=H, width=W, mask_terms=terms)


def _check_filter(x: Tensor, filt: KCCFilter) -> None:
    dims: dict[str, int] = {}
    _check_images(x, "x", dims)
    check_shape(filt.z_hat, "B C H K", "filt.z_hat", dims)
    if (x.shape[-2], x.shape[-1]) != (filt.height, filt.width):
        raise ShapeError(f"x: expected spatial size ({filt.height}, {filt.width}) of the filter, got {tuple(x.shape)}")


def _response_spectrum(x: Tensor, filt: KCCFilter, sigma, mask: Tensor | None = None) -> Tensor:
    H, W = filt.height, filt.width
    x = x.to(filt.z_energy.dtype)
    x_hat = torch.fft.rfft2(x)
    s = _per_item(sigma, filt.z_energy, "sigma")
    if filt.mask_terms is None:
        if mask is not None:
            raise ConfigError("mask: the filter was trained without a mask; train it with one (kcc_train(..., mask=)) to match masked frames")
        kxz = _kernel_map(x_hat, filt.z_hat, _energy(x_hat, W), filt.z_energy, s, H, W)
    else:
        if mask is None:
            raise ConfigError("mask: the filter was trained with a mask (masked kernel); pass the frame's mask too")
        _check_mask(mask, x, "mask")
        kxz = _masked_kernel_map(x_hat, filt.z_hat, _mask_terms(x, mask.to(x.dtype)), filt.mask_terms, s, H, W)
    return torch.fft.rfft2(kxz) * filt.h_hat  # (B, H, W//2+1)


def kcc_response(x: Tensor, filt: KCCFilter, sigma, mask: Tensor | None = None) -> Tensor:
    """Correlation output ``g(x) = F⁻¹(κ̂_z(x) ⊙ ĥ*)`` of test images against a trained filter (Eq. (17)).

    Args:
        x: (B, C, H, W) test channels, same layout as the keyframe's.
        filt: filter from ``kcc_train``.
        sigma: kernel width used at training.
        mask: (B, 1, H, W) weights of ``x``; required by, and only by, a filter trained with a mask.

    Returns:
        (B, H, W) correlation output; it peaks at the content shift of ``x`` relative to the
        keyframe (see the module convention) with a value near 1 for a perfect match.
    """
    _check_filter(x, filt)
    return torch.fft.irfft2(_response_spectrum(x, filt, sigma, mask), s=(filt.height, filt.width))


# --------------------------------------------------------------------------------------------
# peak finding (the spatial-domain parts are in ``peak``)


# Largest Newton step (pixels) at which the Fourier refinement stops early.
_NEWTON_TOL = 1e-4

_FOURIER_TABLES: FifoCache[tuple[Tensor, Tensor, Tensor, Tensor, Tensor]] = FifoCache(8)


def _fourier_tables(
    H: int, W: int, smoothing: float, dtype: torch.dtype, device
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Tables of the interpolant, cached per size (they depend on nothing else).

    Returns the angular frequencies ``wy`` (H,) and ``wx`` (W//2+1,), the (H, W//2+1)
    Gaussian-smoothing, Parseval and 1/(HW) factor, and the complex derivative weights
    ``(1, i w, -w²)`` of each axis, (3, H) and (3, W//2+1).
    """
    key = (H, W, float(smoothing), dtype, torch.device(device))
    hit = _FOURIER_TABLES.get(key)
    if hit is not None:
        return hit
    fy = torch.fft.fftfreq(H, dtype=dtype, device=device)
    fx = torch.fft.rfftfreq(W, dtype=dtype, device=device)
    damp = torch.exp(-2 * math.pi**2 * smoothing**2 * (fy[:, None].square() + fx[None, :].square()))
    wy, wx = 2 * math.pi * fy, 2 * math.pi * fx

    def orders(w: Tensor) -> Tensor:
        zero = torch.zeros_like(w)
        return torch.complex(torch.stack([torch.ones_like(w), zero, -w.square()]), torch.stack([zero, w, zero]))

    tables = (wy, wx, damp * _half_weights(W, damp)[None, :] / (H * W), orders(wy), orders(wx))
    return _FOURIER_TABLES.put(key, tables)


def _refine_fourier(
    g_hat: Tensor, H: int, W: int, row: Tensor, col: Tensor, smoothing: float, iterations: int
) -> tuple[Tensor, Tensor]:
    """Newton ascent on the Gaussian-smoothed trigonometric interpolant of g around the integer peak."""
    real = g_hat.real.dtype
    wy, wx, factor, dy, dx = _fourier_tables(H, W, smoothing, real, g_hat.device)
    unit_y, unit_x = torch.ones_like(wy), torch.ones_like(wx)
    G = g_hat * factor  # (B, H, W//2+1)
    t0 = torch.stack([row, col], dim=1).to(real)  # (B, 2) (y, x)
    t = t0
    ok = torch.ones(row.shape, dtype=torch.bool, device=row.device)
    step_norm = torch.zeros(row.shape, dtype=real, device=row.device)
    host = is_host(g_hat)
    for _ in range(iterations):
        # e^{i wy ty} (B, H) and e^{i wx tx} (B, Wr).
        a = torch.polar(unit_y, t[:, 0:1] * wy)
        b = torch.polar(unit_x, t[:, 1:2] * wx)
        # The value and derivatives of the interpolant are separable sums
        # Re Σ_y a_y dy[m]_y Σ_x G_yx b_x dx[n]_x for derivative orders (m, n): two small
        # matrix products give all nine, of which five are used (3 x GEMV + 5 reductions before).
        M = torch.matmul(G, (b[:, None, :] * dx).transpose(1, 2))  # (B, H, 3)
        P = torch.matmul(a[:, None, :] * dy, M).real  # (B, 3, 3) [order in y, order in x]
        gy, gx, hyy, hxx, hxy = P[:, 1, 0], P[:, 0, 1], P[:, 2, 0], P[:, 0, 2], P[:, 1, 1]
        det = hyy * hxx - hxy * hxy
        nd = (hyy < 0) & (det > 0)
        # Newton step -H^-1 grad with H = [[hyy, hxy], [hxy, hxx]], only where H is negative definite.
        step = torch.stack([hxy * gx - hxx * gy, hxy * gy - hyy * gx], dim=1) / torch.where(nd, det, 1.0)[:, None]
        step = torch.where(nd[:, None], step, 0.0)
        ok = ok & nd
        t_new = t0 + (t + step - t0).clamp(-1.0, 1.0)
        step_norm = (t_new - t).abs().amax(dim=1)
        t = t_new
        if host and not bool((step_norm > _NEWTON_TOL).any()):
            # Newton converges quadratically: once every step is below _NEWTON_TOL the next one
            # would be ~1e-8 px, under the float32 spacing of t (a few 1e-6 px at tens of pixels),
            # so further iterations only move t by round-off. This usually saves one or two of
            # the iterations it took to reach an exact fixed point. On the host reading the flag
            # is free; on an accelerator it would wait for the device, so all iterations run.
            break
    d = t - t0
    ok = ok & (step_norm < 1e-3) & (d.abs().amax(dim=1) < 1.0)
    off_xy = d.flip(1)  # (B, 2) (x, y)
    return torch.where(ok[:, None], off_xy, torch.zeros_like(off_xy)), ok


def _find_peak(
    g: Tensor, g_hat: Tensor | None, subpixel: Subpixel, smoothing: float, iterations: int
) -> Peak:
    B, H, W = g.shape
    row, col, value = _argmax(g)
    index = torch.stack([_wrap(col, W), _wrap(row, H)], dim=1)  # (B, 2) (x, y)
    if subpixel is Subpixel.NONE:
        return Peak(index, index.to(g.dtype), value, torch.zeros(B, dtype=torch.bool, device=g.device))
    if subpixel is Subpixel.QUADRATIC:
        off, ok = _refine_quadratic(g, row, col)
    else:
        if g_hat is None:
            g_hat = torch.fft.rfft2(g)
        off, ok = _refine_fourier(g_hat, H, W, row, col, smoothing, iterations)
    return Peak(index, index.to(g.dtype) + off, value, ok)


def find_peak(
    g: Tensor,
    subpixel: Subpixel | str = Subpixel.FOURIER,
    smoothing: float = 1.0,
    iterations: int = 5,
) -> Peak:
    """Locate the correlation peak with signed wrap-around and optional sub-pixel refinement (Eq. (17)).

    Args:
        g: (B, H, W) correlation output.
        subpixel: refinement mode (see ``Subpixel``).
        smoothing: Gaussian smoothing in pixels for ``Subpixel.FOURIER``.
        iterations: Newton iterations for ``Subpixel.FOURIER`` (fixed count, batched).

    Returns:
        Peak with ``(col, row)`` = ``(x, y)`` ordering. Where refinement does not converge
        (non-concave neighbourhood, or the maximum lies more than 1 px from the integer peak)
        the integer peak is kept and ``refined`` is False.
    """
    _check_response(g, "g")
    subpixel = parse_choice(Subpixel, subpixel, "subpixel")
    if not smoothing > 0:
        raise ConfigError(f"smoothing: expected a positive number of pixels, got {smoothing!r}")
    return _find_peak(g, None, subpixel, float(smoothing), int(iterations))


@dataclass(frozen=True)
class KCCPrediction:
    """Result of matching frames against a trained KCC.

    Attributes:
        response: (B, H, W) correlation output g(x).
        shift: (B, 2) content shift ``(s_x, s_y)`` in pixels (sub-pixel or soft arg-max).
        index: (B, 2) long integer peak ``(col, row)`` wrapped to signed shifts; use it for
            pixel-exact operations (depth translation, fusion).
        peak: (B,) g at the integer peak.
        psr: (B,) peak-to-sidelobe ratio (Eq. (22)).
        t_xy: (B, 2) ``resolution * shift``: metric content translation in the keyframe
            attitude frame, metres (pixels when no resolution was given) (Eq. (18)).
        variance: (B,) per-axis variance of ``t_xy`` (Eq. (19)), m² (px² without resolution).
        refined: (B,) bool, True where the sub-pixel refinement converged.
    """

    response: Tensor
    shift: Tensor
    index: Tensor
    peak: Tensor
    psr: Tensor
    t_xy: Tensor
    variance: Tensor
    refined: Tensor


def kcc_predict(
    x: Tensor,
    filt: KCCFilter,
    sigma,
    resolution: Tensor | None = None,
    subpixel: Subpixel | str = Subpixel.FOURIER,
    smoothing: float = 1.0,
    iterations: int = 5,
    psr_window: int = 11,
    temperature=None,
    mask: Tensor | None = None,
) -> KCCPrediction:
    """Match test images against a trained KCC: response, shift, PSR and variance (Eq. (17)–(19), (22)).

    Args:
        x: (B, C, H, W) test channels.
        filt: filter from ``kcc_train`` on the keyframes.
        sigma: kernel width used at training (float or 0-d / (B,) tensor).
        resolution: (B,) metres per pixel of the orthographic images, or ``None`` for pixels.
        subpixel: peak refinement mode (ignored when ``temperature`` is given).
        smoothing: Gaussian smoothing in pixels for ``Subpixel.FOURIER``.
        iterations: Newton iterations for ``Subpixel.FOURIER``.
        psr_window: odd side of the square excluded from the PSR sidelobe.
        temperature: if given, the shift is the differentiable ``soft_argmax`` at this temperature.
        mask: (B, 1, H, W) weights of ``x``; required by, and only by, a filter trained with a
            mask (``masked_kernel_map``).

    Returns:
        KCCPrediction.
    """
    _check_filter(x, filt)
    subpixel = parse_choice(Subpixel, subpixel, "subpixel")
    B = x.shape[0]
    if resolution is not None:
        check_shape(resolution, f"{B}", "resolution")
        check_float(resolution, "resolution")
    H, W = filt.height, filt.width
    g_hat = _response_spectrum(x, filt, sigma, mask)
    g = torch.fft.irfft2(g_hat, s=(H, W))
    if temperature is not None:
        peak = _find_peak(g, None, Subpixel.NONE, smoothing, iterations)
        shift = soft_argmax(g, temperature)
        refined = torch.zeros(B, dtype=torch.bool, device=g.device)
    else:
        peak = _find_peak(g, g_hat, subpixel, float(smoothing), int(iterations))
        shift, refined = peak.shift, peak.refined
    psr = peak_to_sidelobe(g, peak.index, psr_window)
    var = shift_variance(g, peak.value, resolution)
    t_xy = shift if resolution is None else shift * resolution.to(g.dtype)[:, None]
    return KCCPrediction(
        response=g, shift=shift, index=peak.index, peak=peak.value, psr=psr, t_xy=t_xy, variance=var, refined=refined
    )


# --------------------------------------------------------------------------------------------
# module


class KernelCorrelator(nn.Module):
    """Thin module over ``kcc_train`` / ``kcc_predict`` holding σ, λ and the soft arg-max temperature.

    ``learnable`` names the ones to learn (any of ``"sigma"``, ``"lam"``, ``"temperature"``). All
    three must stay positive, so a learned one is held in log space as the parameter
    ``log_<name>`` (``torchslam.optim.positive_parameter``, the parametrisation of
    ``torchslam.learn.learnable``): a plain optimiser step can never make it zero or negative.
    The others are buffers named ``sigma``, ``lam``, ``temperature``. Either way the attribute
    ``sigma`` (``lam``, ``temperature``) reads the positive 0-d value. Gradients reach the
    parameters through the kernel, the filter and, with ``cfg.soft_argmax``, the soft arg-max.

    With ``cfg.features == "learned"`` it also holds the network of the learned channels as the
    submodule ``features`` (``torchslam.kcc.features.KCCFeatureNet``, given; ``correlator_for``
    reads it from ``cfg.features_weights`` or the packaged weights), so that ``.to(device)`` moves it too;
    ``channels`` computes a map's or frame's KCC input either way.

    Args:
        cfg: KCC settings.
        learnable: names of the values to learn.
        dtype: dtype of the held values (they are cast to the inputs' dtype at use).
        features: the learned channels' network (only with ``cfg.features == "learned"``).
    """

    LEARNABLE = frozenset({"sigma", "lam", "temperature"})

    def __init__(
        self,
        cfg: KCCConfig | None = None,
        learnable=frozenset(),
        dtype: torch.dtype = torch.float32,
        features: nn.Module | None = None,
    ):
        super().__init__()
        self.cfg = cfg if cfg is not None else KCCConfig()
        if self.cfg.features is FeatureKind.LEARNED:
            if features is None:
                raise ConfigError(
                    "features: cfg.features is 'learned' but no network was given; pass features= "
                    "(torchslam.kcc.load_feature_net) or build the correlator with torchslam.kcc.correlator_for(cfg)"
                )
            self.features = features
        elif features is not None:
            raise ConfigError("features: a feature network was given but cfg.features is 'handcrafted'; set features='learned'")
        else:
            self.features = None
        unknown = set(learnable) - self.LEARNABLE
        if unknown:
            raise ConfigError(f"learnable: unknown names {sorted(unknown)}; valid are {sorted(self.LEARNABLE)}")
        for name in ("sigma", "lam", "temperature"):
            value = float(getattr(self.cfg, name))
            if name in learnable:
                self.register_parameter(f"log_{name}", positive_parameter(value, name, dtype))
            else:
                self.register_buffer(name, torch.tensor(value, dtype=dtype))

    def __getattr__(self, name: str):
        # A learned value has no attribute of its own: it is exp of its log-space parameter.
        if name in KernelCorrelator.LEARNABLE:
            raw = self.__dict__["_parameters"].get(f"log_{name}")
            if raw is not None:
                return positive_value(raw)
        return super().__getattr__(name)

    def channels(self, images, frame: bool = False, mask: bool = False) -> Tensor | tuple[Tensor, Tensor]:
        """(B, C, H, W) KCC input of orthographic images (``OrthoImages`` or ``KeyframeMap``).

        The hand-crafted ``kcc_features`` (C = 2) or the learned network's channels
        (``cfg.features``), then ``cfg.window``; for a frame's images (``frame``, the side that
        is matched, never the side a filter is trained on) also ``cfg.frame_taper``.

        With ``mask`` also the (B, 1, H, W) weights of those channels (``masked_kernel_map``):
        the pixels the channels hold (valid or filled from a valid neighbour) times the window
        and the frame's taper. Learned channels are then set to 0 off those pixels.
        """
        cfg = self.cfg
        if self.features is None:
            z, m = kcc_features_masked(images.grey, images.depth, images.valid, cfg.channel_norm, cfg.fill_holes)
        else:
            z = self.features(images.grey, images.depth, images.valid, cfg.channel_norm, cfg.fill_holes)
            m = _fill_mask(images.valid, cfg.fill_holes, z.dtype) if mask else None
            z = z * m if mask else z
        z = apply_window(z, cfg.window)
        z = taper_frame(z, cfg.frame_taper) if frame else z
        if not mask:
            return z
        H, W = z.shape[-2:]
        for w in (kcc_window(cfg.window, H, W, z.dtype, z.device), frame_taper(H, W, cfg.frame_taper, z.dtype, z.device) if frame else None):
            m = m if w is None else m * w
        return z, m

    def fit(self, z: Tensor, mask: Tensor | None = None) -> KCCFilter:
        """Train on (B, C, H, W) keyframe channels, with their weights for the masked kernel (see ``kcc_train``)."""
        return kcc_train(z, self.sigma.to(z.dtype), self.lam.to(z.dtype), mask)

    def forward(self, x: Tensor, filt: KCCFilter, resolution: Tensor | None = None, mask: Tensor | None = None) -> KCCPrediction:
        """Match (B, C, H, W) frame channels (and their weights, for a masked filter) against ``filt`` (see ``kcc_predict``)."""
        cfg = self.cfg
        return kcc_predict(
            x,
            filt,
            self.sigma.to(x.dtype),
            resolution,
            subpixel=cfg.subpixel,
            smoothing=cfg.subpixel_smoothing,
            iterations=cfg.subpixel_iterations,
            psr_window=cfg.psr_window,
            temperature=self.temperature.to(x.dtype) if cfg.soft_argmax else None,
            mask=mask,
        )
