"""Hamming distances between 256-bit binary descriptors and nearest-neighbour matching.

Three torch kernels compute the full distance matrix, batched over pairs ``(B, K1, K2)``:

- ``swar``: descriptors packed to four int64 words; XOR, then a SWAR popcount (bit-sliced sums
  in 2-, 4-, 8- and 16-bit fields, and a multiply that adds the fields into the top bits).
- ``lut``: XOR of the raw bytes and a 256-entry popcount table.
- ``matmul``: bits as ±1 vectors, so ``a·b = 256 - 2 d`` and the whole matrix is one GEMM
  (``bmm``). Every product and partial sum is a small integer, exact in float16/float32.

Matching (``match_descriptors``) returns each query descriptor's nearest neighbour, optionally
kept only when mutual and/or when it passes a ratio test, and always only within
``max_distance``. GC-SLAM's defaults: nearest neighbour, Hamming threshold 50, no ratio test.
On the CPU the ``auto`` backend is the faster, timed once per process (``cpu_auto_backend``),
of ``int8``, one exact int8 GEMM (``torch._int_mm``) of the ±1 bit vectors per pair, and
``opencv``, OpenCV's brute-force Hamming search (``cv2.batchDistance``); the GEMM is about
1.5 x faster where the CPU has int8 dot-product instructions and 60 x slower where it has only
AVX2. Both are faster on the CPU than the float torch kernels (``scripts/bench_matching.py``);
on other devices the torch path runs. All backends give the same matches (the first index on
ties).
"""

from __future__ import annotations

import enum
import platform
import time
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from ..devices import index_select
from ..environment import cpuinfo_field
from ..errors import ConfigError, DTypeError, ShapeError, check_shape, parse_choice

__all__ = [
    "HammingKernel",
    "MatchBackend",
    "Matches",
    "cpu_auto_backend",
    "BatchedMatches",
    "popcount64",
    "pack_descriptors",
    "pad_descriptors",
    "hamming_distance",
    "hamming_distance_packed",
    "hamming_distance_indexed",
    "match_descriptors",
    "match_descriptors_batched",
]

_M1 = 0x5555555555555555
_M2 = 0x3333333333333333
_M4 = 0x0F0F0F0F0F0F0F0F
_H01 = 0x0101010101010101
_M8 = 0x00FF00FF00FF00FF
_H0001 = 0x0001000100010001
_BITS = 256
# Larger than any Hamming distance between 256-bit strings: marks padded candidates.
_FAR = 1 << 20
# Elements of one (B, rows, K2) int64 block of the SWAR/LUT kernels: small enough to stay in cache
# on a CPU, large enough that kernel launches do not dominate on a GPU.
_BLOCK_CPU = 1 << 19
_BLOCK_GPU = 1 << 25
# Elements of one float block of the GEMM kernel (64 MiB in float32).
_BLOCK_GEMM = 1 << 24
# NumPy's element-wise popcount (NumPy >= 2.0), else None.
_NP_POPCOUNT = getattr(np, "bitwise_count", None)


class HammingKernel(enum.Enum):
    """How torch computes a Hamming distance matrix (see the module docstring)."""

    AUTO = "auto"
    SWAR = "swar"
    LUT = "lut"
    MATMUL = "matmul"


class MatchBackend(enum.Enum):
    """Who runs nearest-neighbour matching: ``auto`` is the faster of ``int8`` and ``opencv`` on
    the CPU (:func:`cpu_auto_backend`) and torch elsewhere."""

    AUTO = "auto"
    TORCH = "torch"
    OPENCV = "opencv"
    INT8 = "int8"


def _int8_gemm_works() -> bool:
    """Whether ``torch._int_mm`` (int8 x int8 -> int32) runs on the CPU and is exact here."""
    try:
        a = torch.tensor([[1, -1, 1, 1], [-1, -1, 1, -1]], dtype=torch.int8)
        return bool(torch.equal(torch._int_mm(a, a.T), a.int() @ a.int().T))
    except (AttributeError, RuntimeError, NotImplementedError):
        return False


_INT8_GEMM = _int8_gemm_works()
# Descriptors per side of the two timings that pick the CPU's ``auto`` backend. The first is
# cheap everywhere and settles a CPU without an int8 kernel (there the GEMM is tens of times
# slower); the second is near GC-SLAM's 2,000 features, where the GEMM's speed, not the call's
# fixed cost, decides (at 384 the two backends can come out even where the GEMM is 3x faster at
# 2,000).
_PROBE_DESCRIPTORS = 384
_PROBE_DESCRIPTORS_LARGE = 1024
# An int8 GEMM this many times OpenCV's CPU time at the small size is not timed at the large one.
_PROBE_HOPELESS = 4.0
# The CPU backend that ``auto`` resolved to in this process (measured on first use), or None.
_cpu_auto: MatchBackend | None = None


def _best_ms(fn, repeats: int = 3, clock=time.perf_counter) -> float:
    """Fastest of ``repeats`` timed calls of ``fn`` after one warm-up call, milliseconds of ``clock``."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = clock()
        fn()
        best = min(best, clock() - start)
    return best * 1e3


def _probe_cpu_ms(n: int) -> tuple[float, float]:
    """CPU milliseconds (every thread of the process) of one int8 and one OpenCV match of n x n random descriptors."""
    gen = torch.Generator().manual_seed(0)
    d1, d2 = torch.randint(0, 256, (2, n, 32), dtype=torch.uint8, generator=gen)
    int8_ms = _best_ms(lambda: _match_int8(d1, d2, 50, False, None), clock=time.process_time)
    opencv_ms = _best_ms(lambda: _match_opencv(d1, d2, 50, False, None), clock=time.process_time)
    return int8_ms, opencv_ms


# x86 feature flags of CPUs whose int8 GEMM may beat OpenCV (AVX-512 VNNI implies AVX-512F;
# AVX-VNNI and AMX on CPUs without AVX-512). Without any of them (an AVX2-only CPU) oneDNN's int8
# GEMM took 60 x OpenCV's time, and the first of the probe's timings alone cost about 0.1 s of a
# run's start, only to find it hopeless.
_FAST_INT8_FLAGS = frozenset({"avx512f", "avx_vnni", "amx_int8"})


def _cpu_flags() -> frozenset[str] | None:
    """This x86 CPU's feature flags from ``/proc/cpuinfo`` (Linux), or None where they cannot be read."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    flags = cpuinfo_field("flags")
    return None if flags is None else frozenset(flags.split())


def _int8_may_be_fast() -> bool:
    """False on an x86 CPU known to lack every int8 dot-product extension, else True (timed)."""
    flags = _cpu_flags()
    return flags is None or bool(flags & _FAST_INT8_FLAGS)


def cpu_auto_backend() -> MatchBackend:
    """The backend ``auto`` runs on the CPU in this process: ``int8`` or ``opencv``.

    ``torch._int_mm`` is exact wherever it runs, but only fast where oneDNN has an int8 kernel
    for the CPU (int8 dot-product instructions, AVX-512 VNNI or AMX): there it matches 2,000 x
    2,000 ORB descriptors in about 0.3 x OpenCV's CPU time, while on an AVX2-only CPU the same
    call took 60 x OpenCV's (720 against 11 ms, which made GC-SLAM's sparse front-end 2.5 x
    slower end to end). So the first call times both backends (best of 3 after a warm-up) on the
    same random descriptors and keeps the cheaper for the rest of the process: first 384 x 384,
    and where int8 is not hopeless there, 1,024 x 1,024, whose figures decide. The clock is the
    process's CPU time, so OpenCV's worker threads count: a run has other work for the cores
    they take (another thread's work during a timed call counts too, in proportion to each
    call's length; the best of three keeps the cheaper). An x86 CPU whose flags show no AVX-512,
    AVX-VNNI or AMX is not timed: OpenCV (``_int8_may_be_fast``). Both give the same matches, so
    the choice changes speed only.
    """
    global _cpu_auto
    if _cpu_auto is None:
        if not _INT8_GEMM or not _int8_may_be_fast():
            _cpu_auto = MatchBackend.OPENCV
        else:
            int8_ms, opencv_ms = _probe_cpu_ms(_PROBE_DESCRIPTORS)
            if int8_ms < _PROBE_HOPELESS * opencv_ms:
                int8_ms, opencv_ms = _probe_cpu_ms(_PROBE_DESCRIPTORS_LARGE)
            _cpu_auto = MatchBackend.INT8 if int8_ms < opencv_ms else MatchBackend.OPENCV
    return _cpu_auto


class Matches(NamedTuple):
    """Matches of one descriptor pair, sorted by the first index.

    Attributes:
        pairs: (M, 2) int64 ``(index into d1, index into d2)``.
        distances: (M,) int32 Hamming distances in bits.
    """

    pairs: Tensor
    distances: Tensor


class BatchedMatches(NamedTuple):
    """Matches of B descriptor pairs, one entry per query descriptor.

    Attributes:
        index: (B, K1) int64 index into ``d2`` of the accepted match, -1 where there is none.
        distance: (B, K1) int32 distance to the nearest valid ``d2`` descriptor (also where the
            match was rejected), -1 for padded queries or when ``d2`` has no valid descriptor.
    """

    index: Tensor
    distance: Tensor


def _check_descriptors(d: Tensor, spec: str, name: str, dims: dict) -> None:
    check_shape(d, spec, name, dims)
    if d.dtype != torch.uint8:
        raise DTypeError(f"{name}: expected uint8 descriptors, got {d.dtype}")


def _popcount64_(x: Tensor) -> Tensor:
    # In place: fewer temporaries matter more than operation count on large tensors.
    t = x >> 1
    t &= _M1  # the mask also clears the sign bits an arithmetic shift brings in
    x -= t  # 2-bit field sums
    t = x >> 2
    t &= _M2
    x &= _M2
    x += t  # 4-bit field sums
    t = x >> 4
    x += t
    x &= _M4  # byte sums
    x *= _H01  # wrapping multiply: the top byte collects the sum of all bytes
    x >>= 56
    return x


def popcount64(x: Tensor) -> Tensor:
    """Count the set bits of every int64 element (SWAR, no lookup table).

    Args:
        x: (...) int64 tensor; negative values count their two's-complement bits.

    Returns:
        (...) int64 bit counts in [0, 64].
    """
    if x.dtype != torch.int64:
        raise DTypeError(f"x: expected int64, got {x.dtype}")
    return _popcount64_(x.clone())


def pack_descriptors(descriptors: Tensor) -> Tensor:
    """Reinterpret 32-byte descriptors as four int64 words (no copy when contiguous).

    Args:
        descriptors: (..., K, 32) uint8.

    Returns:
        (..., K, 4) int64 words holding the same 256 bits.
    """
    _check_descriptors(descriptors, "... K 32", "descriptors", {})
    return descriptors.contiguous().view(torch.int64)


def _signs(descriptors: Tensor, dtype: torch.dtype) -> Tensor:
    # (..., K, 32) uint8 -> (..., K, 256) of +1 (bit set) / -1 (bit clear).
    shifts = torch.arange(8, dtype=torch.uint8, device=descriptors.device)
    bits = (descriptors.unsqueeze(-1) >> shifts) & 1
    return bits.flatten(-2).to(dtype).mul_(2).sub_(1)


def _popcount_block(a: Tensor, bt: Tensor) -> Tensor:
    """SWAR distances of a block: a (B, R, 4) int64, bt (B, 4, K2) int64 -> (B, R, K2) int64.

    Same arithmetic as :func:`popcount64`, but words are added while their field sums still fit
    (two words per 4-bit field, four per byte), so the later folds run on fewer tensors.
    """

    def nibbles(x: Tensor) -> Tensor:
        t = x >> 1
        t &= _M1
        x -= t
        t = x >> 2
        t &= _M2
        x &= _M2
        x += t
        return x

    x0 = nibbles(a[:, :, 0:1] ^ bt[:, 0:1, :])
    x0 += nibbles(a[:, :, 1:2] ^ bt[:, 1:2, :])
    x1 = nibbles(a[:, :, 2:3] ^ bt[:, 2:3, :])
    x1 += nibbles(a[:, :, 3:4] ^ bt[:, 3:4, :])
    for x in (x0, x1):
        t = x >> 4
        t &= _M4
        x &= _M4
        x += t  # byte sums <= 16
    x0 += x1  # byte sums <= 32
    # Fold bytes into 16-bit fields (<= 64), then one multiply adds the four fields into the top
    # 16 bits. The total (<= 256) does not fit the top byte a 64-bit popcount would use.
    t = x0 >> 8
    t &= _M8
    x0 &= _M8
    x0 += t
    x0 *= _H0001
    x0 >>= 48
    return x0


def _lut(device: torch.device) -> Tensor:
    v = torch.arange(256, device=device)
    return ((v.unsqueeze(-1) >> torch.arange(8, device=device)) & 1).sum(-1).to(torch.int32)


def _rows_per_block(b: int, k2: int, cols: int, device: torch.device) -> int:
    budget = _BLOCK_GPU if device.type != "cpu" else _BLOCK_CPU
    return max(1, budget // max(1, b * k2 * cols))


def _distance_blocks(d1: Tensor, d2: Tensor, kernel: HammingKernel):
    """Yield ``(row_start, (B, R, K2) int32 distances)`` blocks of the (B, K1, K2) matrix."""
    b, k1, k2 = d1.shape[0], d1.shape[1], d2.shape[1]
    dev = d1.device
    if kernel is HammingKernel.AUTO:
        kernel = HammingKernel.MATMUL
    if kernel is HammingKernel.MATMUL:
        dtype = torch.float32 if dev.type == "cpu" else torch.float16
        s1, s2t = _signs(d1, dtype), _signs(d2, dtype).transpose(1, 2)
        rows = max(1, _BLOCK_GEMM // max(1, b * k2))
        for r0 in range(0, k1, rows):
            dot = torch.bmm(s1[:, r0 : r0 + rows], s2t)  # (B, R, K2) = 256 - 2 d, exact
            yield r0, ((_BITS - dot.float()) * 0.5).round_().to(torch.int32)
        return
    if kernel is HammingKernel.SWAR:
        w1 = d1.contiguous().view(torch.int64)
        w2t = d2.contiguous().view(torch.int64).transpose(1, 2).contiguous()  # (B, 4, K2)
        rows = _rows_per_block(b, k2, 1, dev)
        for r0 in range(0, k1, rows):
            yield r0, _popcount_block(w1[:, r0 : r0 + rows], w2t).to(torch.int32)
        return
    lut = _lut(dev)
    rows = _rows_per_block(b, k2, 32, dev)
    for r0 in range(0, k1, rows):
        x = d1[:, r0 : r0 + rows, None, :] ^ d2[:, None, :, :]  # (B, R, K2, 32) uint8
        yield r0, lut[x.int()].sum(-1, dtype=torch.int32)


def hamming_distance(d1: Tensor, d2: Tensor, kernel: HammingKernel | str = HammingKernel.AUTO) -> Tensor:
    """Compute all Hamming distances between two descriptor sets.

    Args:
        d1: (..., K1, 32) uint8 descriptors.
        d2: (..., K2, 32) uint8 descriptors with the same leading dimensions as ``d1``.
        kernel: torch kernel; ``auto`` is ``matmul``, the fastest torch kernel measured on the CPU
            (``scripts/bench_matching.py``); on an accelerator it runs as a float16 GEMM.

    Returns:
        (..., K1, K2) int32 distances in bits, in [0, 256].
    """
    kernel = parse_choice(HammingKernel, kernel, "kernel")
    _check_descriptors(d1, "... K1 32", "d1", {})
    _check_descriptors(d2, "... K2 32", "d2", {})
    if d1.shape[:-2] != d2.shape[:-2]:
        raise ShapeError(f"d2: expected leading dimensions {tuple(d1.shape[:-2])} as d1, got {tuple(d2.shape)}")
    if d1.device != d2.device:
        raise ShapeError(f"d2: expected device {d1.device} as d1, got {d2.device}")
    lead = d1.shape[:-2]
    nb = int(np.prod(lead)) if lead else 1
    a = d1.reshape(nb, d1.shape[-2], 32)
    b = d2.reshape(nb, d2.shape[-2], 32)
    out = torch.empty(a.shape[0], a.shape[1], b.shape[1], dtype=torch.int32, device=d1.device)
    if out.numel():
        for r0, block in _distance_blocks(a, b, kernel):
            out[:, r0 : r0 + block.shape[1]] = block
    return out.reshape(*lead, a.shape[1], b.shape[1])


def hamming_distance_packed(w1: Tensor, w2: Tensor) -> Tensor:
    """Hamming distances between corresponding packed descriptors (element-wise, not all pairs).

    Args:
        w1: (..., 4) int64 packed descriptors (:func:`pack_descriptors`).
        w2: (..., 4) int64, broadcastable against ``w1``.

    Returns:
        (...) int64 distances in bits.
    """
    check_shape(w1, "... 4", "w1")
    check_shape(w2, "... 4", "w2")
    return _popcount64_(w1 ^ w2).sum(-1)


def hamming_distance_indexed(w1: Tensor, idx1: Tensor, w2: Tensor, idx2: Tensor, chunk: int = 1 << 15) -> Tensor:
    """Hamming distances between ``w1[idx1[h]]`` and ``w2[idx2[h]]`` for a long list of pairs.

    The pairs are processed in chunks that fit in cache, which on a CPU is several times faster
    than gathering all rows first (candidate lists of a hash lookup hold millions of pairs).

    Args:
        w1: (N1, 4) int64 packed descriptors.
        idx1: (H,) int64 row indices into ``w1``.
        w2: (N2, 4) int64 packed descriptors.
        idx2: (H,) int64 row indices into ``w2``.
        chunk: pairs per chunk.

    Returns:
        (H,) int64 distances in bits.
    """
    dims: dict[str, int] = {}
    check_shape(w1, "N1 4", "w1")
    check_shape(w2, "N2 4", "w2")
    check_shape(idx1, "H", "idx1", dims)
    check_shape(idx2, "H", "idx2", dims)
    h = idx1.shape[0]
    out = torch.empty(h, dtype=torch.int64, device=w1.device)
    cpu = w1.device.type == "cpu"
    step = h if not cpu else max(1, chunk)
    for s in range(0, h, max(step, 1)):
        x = index_select(w1, 0, idx1[s : s + step])
        x ^= index_select(w2, 0, idx2[s : s + step])
        if cpu and _NP_POPCOUNT is not None:
            # NumPy >= 2 counts bits with the CPU's popcount instruction (of the unsigned words: it
            # counts a signed integer's absolute value): one call, not the SWAR steps.
            # The four words' counts are added column by column: NumPy's reduction over a last
            # axis of four is several times slower than three additions.
            c = _NP_POPCOUNT(x.numpy().view(np.uint64))  # (chunk, 4) uint8
            o = out[s : s + step].numpy()
            np.add(c[:, 0], c[:, 1], out=o, dtype=np.int64, casting="unsafe")
            o += c[:, 2]
            o += c[:, 3]
        else:
            torch.sum(_popcount64_(x), -1, out=out[s : s + step])
    return out


def pad_descriptors(descriptors: list[Tensor]) -> tuple[Tensor, Tensor]:
    """Stack ragged descriptor sets into one padded batch.

    Args:
        descriptors: B tensors of shape (K_b, 32) uint8, on one device.

    Returns:
        padded: (B, K_max, 32) uint8, zeros past each set's end.
        valid: (B, K_max) bool, True for real descriptors.
    """
    if len(descriptors) == 0:
        raise ShapeError("descriptors: expected at least one (K, 32) tensor, got an empty list")
    for i, d in enumerate(descriptors):
        _check_descriptors(d, "K 32", f"descriptors[{i}]", {})
    dev = descriptors[0].device
    counts = torch.tensor([d.shape[0] for d in descriptors], device=dev)
    k_max = int(counts.max())
    padded = torch.zeros(len(descriptors), k_max, 32, dtype=torch.uint8, device=dev)
    valid = torch.arange(k_max, device=dev) < counts[:, None]
    if k_max:
        padded[valid] = torch.cat(descriptors, 0)
    return padded, valid


def _match_torch(d1, d2, valid1, valid2, max_distance, mutual, ratio, kernel) -> BatchedMatches:
    b, k1, k2 = d1.shape[0], d1.shape[1], d2.shape[1]
    dev = d1.device
    best = torch.full((b, k1), _FAR, dtype=torch.int32, device=dev)
    best_idx = torch.zeros((b, k1), dtype=torch.int64, device=dev)
    second = torch.full((b, k1), _FAR, dtype=torch.int32, device=dev)
    col_best = torch.full((b, k2), _FAR, dtype=torch.int32, device=dev)
    col_idx = torch.full((b, k2), -1, dtype=torch.int64, device=dev)
    if k1 and k2:
        pad_cols = ~valid2[:, None, :]
        for r0, dist in _distance_blocks(d1, d2, kernel):
            r1 = r0 + dist.shape[1]
            dist.masked_fill_(pad_cols, _FAR)
            dist.masked_fill_(~valid1[:, r0:r1, None], _FAR)
            best[:, r0:r1], best_idx[:, r0:r1] = dist.min(-1)  # first index on ties
            if ratio is not None and k2 >= 2:
                second[:, r0:r1] = dist.topk(2, dim=-1, largest=False).values[..., 1]
            if mutual:
                cb, ci = dist.min(1)  # (B, K2) best row of this block, first on ties
                better = cb < col_best  # strict: an earlier block keeps a tie
                col_best = torch.where(better, cb, col_best)
                col_idx = torch.where(better, ci + r0, col_idx)
    has = valid1 & (best < _FAR)
    keep = has & (best <= max_distance)
    if ratio is not None:
        keep &= (best.double() < ratio * second.double()) | (second >= _FAR)
    if mutual and k2:
        rows = torch.arange(k1, device=dev).expand(b, k1)
        keep &= torch.gather(col_idx, 1, best_idx) == rows
    index = torch.where(keep, best_idx, torch.full_like(best_idx, -1))
    distance = torch.where(has, best, torch.full_like(best, -1))
    return BatchedMatches(index, distance)


def _match_opencv(d1: Tensor, d2: Tensor, max_distance, mutual, ratio) -> BatchedMatches:
    a = np.ascontiguousarray(d1.cpu().numpy())
    b = np.ascontiguousarray(d2.cpu().numpy())
    k1, k2 = a.shape[0], b.shape[0]
    if k1 == 0 or k2 == 0:
        empty = torch.full((1, k1), -1, dtype=torch.int64)
        return BatchedMatches(empty, empty.to(torch.int32))
    want = 2 if (ratio is not None and k2 >= 2) else 1
    dist, idx = cv2.batchDistance(a, b, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=want)
    best, best_idx = dist[:, 0], idx[:, 0].astype(np.int64)
    keep = best <= max_distance
    if want == 2:
        keep &= best.astype(np.float64) < ratio * dist[:, 1].astype(np.float64)
    if mutual:
        _, ridx = cv2.batchDistance(b, a, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)
        keep &= ridx[best_idx, 0] == np.arange(k1)
    index = np.where(keep, best_idx, -1)
    return BatchedMatches(torch.from_numpy(index)[None], torch.from_numpy(best.astype(np.int32))[None])


def _match_int8(d1: Tensor, d2: Tensor, max_distance, mutual, ratio) -> BatchedMatches:
    """:func:`_match_opencv`'s result from one exact int8 GEMM of the ±1 bit vectors (CPU).

    ``a·b = 256 - 2 d`` for ±1 vectors, so the nearest neighbour is the largest product; the
    products are small integers, exact in int32. ``max`` takes the first index on ties, as
    OpenCV and the torch kernels do. On a CPU with int8 dot-product instructions this is about
    2 x OpenCV's brute force for 2,000 x 2,000 descriptors (``scripts/bench_matching.py``).
    """
    k1, k2 = d1.shape[0], d2.shape[0]
    if k1 == 0 or k2 == 0:
        empty = torch.full((1, k1), -1, dtype=torch.int64)
        return BatchedMatches(empty, empty.to(torch.int32))
    dot = torch._int_mm(_signs(d1.cpu(), torch.int8), _signs(d2.cpu(), torch.int8).T)  # (K1, K2) int32
    # The reductions in NumPy: its row argmax and column max are vectorised where torch's CPU
    # max-with-indices is not (2,000 x 2,000: 0.3 ms against 4 ms by rows, 11 ms by columns).
    d = dot.numpy()
    best_idx = d.argmax(1)  # the first index on ties
    best_dot = np.take_along_axis(d, best_idx[:, None], 1)[:, 0]
    best = (_BITS - best_dot) // 2
    keep = best <= max_distance
    if ratio is not None and k2 >= 2:
        second = (_BITS - dot.topk(2, dim=1).values[:, 1].numpy()) // 2
        keep &= best.astype(np.float64) < ratio * second.astype(np.float64)
    if mutual:
        keep &= first_argmax_columns(d)[best_idx] == np.arange(k1)
    index = np.where(keep, best_idx, -1).astype(np.int64)
    return BatchedMatches(torch.from_numpy(index)[None], torch.from_numpy(best.astype(np.int32))[None])


# Rows per block of first_argmax_columns: a block's column maxima are one vectorised reduction,
# and a column's first maximum inside its block is one short contiguous row.
_ARGMAX_BLOCK = 64


def first_argmax_columns(d: np.ndarray) -> np.ndarray:
    """(K2,) int64 row index of each column's maximum of a (K1, K2) array, the first on ties.

    Equals ``d.argmax(0)`` (and torch's ``max(0).indices``), which walk the columns with a
    stride and are slow on a large array: here the maxima of blocks of rows are taken along
    contiguous rows, the first block that attains each column's maximum
    is found among the few block maxima, and the first row within that block from one gather.
    """
    k1, k2 = d.shape
    if k1 == 0:
        raise ValueError("first_argmax_columns: no rows")
    b = _ARGMAX_BLOCK
    full = k1 // b
    parts = [d[: full * b].reshape(full, b, k2).max(1)] if full else []  # a view: no copy
    if k1 > full * b:
        parts.append(d[full * b :].max(0, keepdims=True))
    block = np.concatenate(parts).argmax(0)  # the first block holding each column's maximum
    rows = np.minimum(block[:, None] * b + np.arange(b), k1 - 1)  # (K2, b); clipped repeats come last
    cols = np.arange(k2)[:, None]
    within = np.take(d.reshape(-1), rows * k2 + cols).argmax(1)
    return np.take_along_axis(rows, within[:, None], 1)[:, 0].astype(np.int64)


def _match_per_pair(d1, d2, valid1, valid2, max_distance, mutual, ratio, one) -> BatchedMatches:
    """:func:`_match_torch`'s result from ``one`` (:func:`_match_opencv` or :func:`_match_int8`),
    one pair per call over its valid descriptors."""
    b, k1 = d1.shape[:2]
    index = torch.full((b, k1), -1, dtype=torch.int64)
    distance = torch.full((b, k1), -1, dtype=torch.int32)
    for i in range(b):  # both match one descriptor pair per call
        rows1 = torch.nonzero(valid1[i].cpu()).squeeze(-1)
        rows2 = torch.nonzero(valid2[i].cpu()).squeeze(-1)
        if rows1.numel() == 0 or rows2.numel() == 0:
            continue
        m = one(d1[i][rows1.to(d1.device)], d2[i][rows2.to(d2.device)], max_distance, mutual, ratio)
        idx = m.index[0]
        ok = idx >= 0
        index[i, rows1[ok]] = rows2[idx[ok]]
        distance[i, rows1] = m.distance[0]
    return BatchedMatches(index.to(d1.device), distance.to(d1.device))


# The backends that match one pair per call on the host, and their matcher.
_PER_PAIR = {MatchBackend.OPENCV: _match_opencv, MatchBackend.INT8: _match_int8}


def _check_match_args(max_distance, ratio) -> None:
    if max_distance < 0:
        raise ConfigError(f"max_distance: must be >= 0, got {max_distance}")
    if ratio is not None and not 0.0 < ratio <= 1.0:
        raise ConfigError(f"ratio: must be in (0, 1] or None, got {ratio}")


def match_descriptors_batched(
    d1: Tensor,
    d2: Tensor,
    valid1: Tensor | None = None,
    valid2: Tensor | None = None,
    max_distance: int = 50,
    mutual: bool = False,
    ratio: float | None = None,
    kernel: HammingKernel | str = HammingKernel.AUTO,
    backend: MatchBackend | str = MatchBackend.TORCH,
) -> BatchedMatches:
    """Match B descriptor pairs at once in torch (the path that runs on accelerators).

    For every valid query ``d1[b, i]`` the nearest valid ``d2[b, j]`` (the first on ties) is
    accepted when its distance is at most ``max_distance``; with ``mutual`` also only when
    ``d1[b, i]`` is in turn the nearest of ``d2[b, j]``; with ``ratio`` also only when
    ``best < ratio * second_best`` (a single candidate always passes).

    Args:
        d1: (B, K1, 32) uint8 query descriptors (padded, see :func:`pad_descriptors`).
        d2: (B, K2, 32) uint8 reference descriptors.
        valid1: (B, K1) bool, True for real descriptors; None means all.
        valid2: (B, K2) bool; None means all.
        max_distance: largest accepted Hamming distance in bits (GC-SLAM: 50).
        mutual: require mutual nearest neighbours.
        ratio: Lowe ratio threshold in (0, 1], or None for no ratio test (GC-SLAM).
        kernel: torch Hamming kernel.
        backend: ``torch`` (default: all pairs in one computation), ``opencv`` (one OpenCV call
            per pair, same result; several times faster on a CPU), ``int8`` (one int8 GEMM per
            pair on the CPU, same result, about 2 x ``opencv``) or ``auto`` (``int8`` on the CPU,
            ``opencv`` where torch has no int8 GEMM, torch elsewhere).

    Returns:
        ``BatchedMatches(index (B, K1), distance (B, K1))``.
    """
    dims: dict[str, int] = {}
    _check_descriptors(d1, "B K1 32", "d1", dims)
    _check_descriptors(d2, "B K2 32", "d2", dims)
    if d1.device != d2.device:
        raise ShapeError(f"d2: expected device {d1.device} as d1, got {d2.device}")
    _check_match_args(max_distance, ratio)
    kernel = parse_choice(HammingKernel, kernel, "kernel")
    if valid1 is None:
        valid1 = torch.ones(d1.shape[:2], dtype=torch.bool, device=d1.device)
    if valid2 is None:
        valid2 = torch.ones(d2.shape[:2], dtype=torch.bool, device=d2.device)
    check_shape(valid1, "B K1", "valid1", dims)
    check_shape(valid2, "B K2", "valid2", dims)
    one = _PER_PAIR.get(_resolve_backend(backend, d1.device))
    if one is not None:
        return _match_per_pair(d1, d2, valid1.bool(), valid2.bool(), max_distance, mutual, ratio, one)
    return _match_torch(d1, d2, valid1.bool(), valid2.bool(), max_distance, mutual, ratio, kernel)


def _resolve_backend(backend: MatchBackend | str, device: torch.device) -> MatchBackend:
    """``auto`` is the int8 GEMM on the CPU (OpenCV where torch has none), torch elsewhere.

    Raises:
        ConfigError: for ``int8`` where torch has no int8 GEMM on the CPU.
    """
    backend = parse_choice(MatchBackend, backend, "backend")
    if backend is MatchBackend.AUTO:
        if device.type != "cpu":
            return MatchBackend.TORCH
        return cpu_auto_backend()
    if backend is MatchBackend.INT8 and not _INT8_GEMM:
        raise ConfigError("backend: 'int8' needs torch._int_mm on the CPU, which this torch build lacks; use 'opencv'")
    return backend


def match_descriptors(
    d1: Tensor,
    d2: Tensor,
    max_distance: int = 50,
    mutual: bool = False,
    ratio: float | None = None,
    backend: MatchBackend | str = MatchBackend.AUTO,
    kernel: HammingKernel | str = HammingKernel.AUTO,
) -> Matches:
    """Match two descriptor sets by nearest Hamming neighbour.

    Semantics as :func:`match_descriptors_batched`. GC-SLAM's defaults are the nearest neighbour
    within 50 bits, neither mutual nor ratio-tested. Both backends give the same nearest
    distances and, where the nearest neighbour is unique, the same indices (both take the first
    index on ties).

    Args:
        d1: (K1, 32) uint8 query descriptors.
        d2: (K2, 32) uint8 reference descriptors, on the same device.
        max_distance: largest accepted Hamming distance in bits.
        mutual: require mutual nearest neighbours.
        ratio: Lowe ratio threshold in (0, 1], or None.
        backend: ``auto`` (``int8`` on the CPU, see :func:`match_descriptors_batched`; torch
            elsewhere), ``torch``, ``opencv`` or ``int8``.
        kernel: torch Hamming kernel when torch runs.

    Returns:
        ``Matches(pairs (M, 2) int64, distances (M,) int32)`` on ``d1.device``, sorted by the
        index into ``d1``.
    """
    dims: dict[str, int] = {}
    _check_descriptors(d1, "K1 32", "d1", dims)
    _check_descriptors(d2, "K2 32", "d2", dims)
    if d1.device != d2.device:
        raise ShapeError(f"d2: expected device {d1.device} as d1, got {d2.device}")
    _check_match_args(max_distance, ratio)
    backend = _resolve_backend(backend, d1.device)
    kernel = parse_choice(HammingKernel, kernel, "kernel")
    if backend in _PER_PAIR:
        res = _PER_PAIR[backend](d1, d2, max_distance, mutual, ratio)
    else:
        ones1 = torch.ones(1, d1.shape[0], dtype=torch.bool, device=d1.device)
        ones2 = torch.ones(1, d2.shape[0], dtype=torch.bool, device=d1.device)
        res = _match_torch(d1[None], d2[None], ones1, ones2, max_distance, mutual, ratio, kernel)
    index, distance = res.index[0].to(d1.device), res.distance[0].to(d1.device)
    rows = torch.nonzero(index >= 0).squeeze(-1)
    pairs = torch.stack([rows, index[rows]], dim=-1)
    return Matches(pairs, distance[rows])
