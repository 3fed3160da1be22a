"""A fast path for decoding the PNG images of RGB-D datasets.

Decoding is a large share of a frame's CPU time (docs/results/gcslam.md, "PNG decoding"): a 640x480 colour PNG
of TUM RGB-D takes about 6.6 ms in OpenCV and its 16-bit depth PNG 3.7 ms, nearly all of it in
zlib's inflate. This module inflates with ISA-L (``isal``, about 3x faster) and undoes the PNG
row filters with one running sum per byte lane (torch's scan, or NumPy's), for the simple images
the datasets write: 8-bit RGB, 8- or 16-bit grey, not interlaced, every row filtered with
``None`` or ``Sub`` (the TUM RGB-D and the HoloLens sequences). Anything else (``Up``,
``Average`` or ``Paeth`` rows, palettes, alpha, ancillary chunks that may change the pixels, a
damaged stream) returns None, and the caller decodes with OpenCV as before; so does everything
when ``isal`` is not installed. Where it returns an image, it is the one OpenCV returns, to the
bit (``tests/data/test_png.py``).
"""

from __future__ import annotations

import struct

import numpy as np
import torch

try:  # optional: without it the standard inflate is no faster than OpenCV's, so there is no fast path
    from isal import isal_zlib as _inflate
except ImportError:  # pragma: no cover - exercised where isal is missing
    _inflate = None

__all__ = ["available", "decode_png"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Chunks that never change the decoded pixels (text, time, physical size); any other chunk
# besides IHDR, IDAT and IEND sends the image to OpenCV.
_HARMLESS = frozenset({b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs"})
# (colour type, bit depth) -> (channels, bytes per sample) of the layouts on the fast path.
_LAYOUTS = {(2, 8): (3, 1), (0, 8): (1, 1), (0, 16): (1, 2)}


def available() -> bool:
    """Whether the fast path can run here (``isal`` is installed)."""
    return _inflate is not None


def decode_png(buf: np.ndarray | bytes, colour: bool) -> np.ndarray | None:
    """Decode a simple PNG, or return None for OpenCV to decode it.

    Args:
        buf: the file's bytes.
        colour: True for an 8-bit RGB image, returned as (H, W, 3) uint8 in RGB order (OpenCV's
            ``IMREAD_COLOR`` gives the same in BGR); False for a grey image, returned as (H, W)
            uint8 or uint16 (OpenCV's ``IMREAD_UNCHANGED``).

    Returns:
        The image, or None: not a PNG this path decodes (see the module docstring), a damaged
        one, or no ``isal``. A None never means the file is bad: OpenCV decides that.
    """
    if _inflate is None:
        return None
    data = memoryview(buf if isinstance(buf, bytes) else np.ascontiguousarray(buf, dtype=np.uint8)).cast("B")
    if len(data) < 33 or data[:8] != _SIGNATURE:
        return None
    pos, header, idat = 8, None, []
    while pos + 12 <= len(data):
        (length,) = struct.unpack_from(">I", data, pos)
        kind = bytes(data[pos + 4 : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        if len(body) != length:
            return None
        if kind == b"IHDR":
            if header is not None or length != 13:
                return None
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        elif kind not in _HARMLESS:
            return None
        pos += 12 + length
    else:
        return None  # no IEND
    if header is None or not idat:
        return None
    width, height, depth, colour_type, compression, filtering, interlace = header
    layout = _LAYOUTS.get((colour_type, depth))
    if layout is None or compression or filtering or interlace or width == 0 or height == 0:
        return None
    channels, sample = layout
    if colour != (channels == 3):
        return None
    bpp = channels * sample
    stride = 1 + width * bpp
    try:
        raw = _inflate.decompress(b"".join(idat))
    except Exception:  # a damaged stream: OpenCV names the problem
        return None
    if len(raw) != height * stride:
        return None
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(height, stride)
    filters = rows[:, 0]
    if int(filters.max()) > 1:
        return None  # Up, Average or Paeth rows (or an invalid filter byte)
    pixels = rows[:, 1:].reshape(height, width, bpp)
    if bool(filters.any()):
        # Sub: each byte adds the reconstructed byte bpp to its left, modulo 256, i.e. a running
        # sum along the row of every byte lane (uint8 arithmetic wraps).
        sub = filters.astype(bool)
        if bool(sub.all()):
            pixels = _running_sum(pixels)
        else:
            pixels = pixels.copy()
            pixels[sub] = _running_sum(pixels[sub])
    if sample == 2:
        return pixels.view(">u2").reshape(height, width).astype(np.uint16)
    if channels == 1:
        return np.ascontiguousarray(pixels.reshape(height, width))
    return np.ascontiguousarray(pixels)


def _running_sum(pixels: np.ndarray) -> np.ndarray:
    """(rows, W, bpp) uint8 running sums along W, modulo 256: the ``Sub`` filter undone.

    Torch's scan where it runs on the calling thread alone (one intra-op thread, a run's
    default): about 5 x NumPy's uint8 ``cumsum`` over a 640x480 image (0.4 against 2.0 ms for
    colour). With more intra-op threads the scan would wake torch's pool from the loader's
    thread, which stalls beside a busy process (docs/results/cpu.md, "Threads"), so NumPy's runs there. Sums
    modulo 256 do not depend on the order of the additions: both give the same bytes.
    """
    if torch.get_num_threads() == 1:
        # A copy: the inflated bytes are read-only, which torch warns about once per process.
        return torch.cumsum(torch.from_numpy(np.ascontiguousarray(pixels)), 1, dtype=torch.uint8).numpy()
    return np.cumsum(pixels, axis=1, dtype=np.uint8)
