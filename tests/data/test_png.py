"""The PNG fast path (``torchslam.data.png``) against OpenCV's decoder, bit for bit."""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import torch
import pytest

from torchslam.data import png
from torchslam.data.png import decode_png
from torchslam.data.tum import TUMSequence, _read_image

pytestmark = pytest.mark.skipif(not png.available(), reason="isal is not installed: no PNG fast path to test")


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def _filter_row(row: np.ndarray, prev: np.ndarray, kind: int, bpp: int) -> np.ndarray:
    """PNG filter ``kind`` of one row of bytes (``prev``: the row above, unfiltered)."""
    x = row.astype(np.int32)
    left = np.concatenate([np.zeros(bpp, np.int32), x[:-bpp]])
    up = prev.astype(np.int32)
    if kind == 0:
        out = x
    elif kind == 1:
        out = x - left
    elif kind == 2:
        out = x - up
    elif kind == 3:
        out = x - (left + up) // 2
    else:  # Paeth
        upleft = np.concatenate([np.zeros(bpp, np.int32), up[:-bpp]])
        p = left + up - upleft
        pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - upleft)
        pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
        out = x - pred
    return (out % 256).astype(np.uint8)


def _encode(img: np.ndarray, filters: list[int], extra: list[tuple[bytes, bytes]] = (), interlace: int = 0) -> bytes:
    """A PNG of ``img`` ((H, W, 3) uint8 RGB, (H, W) uint8 or uint16 grey) with the given row filters."""
    h, w = img.shape[:2]
    colour_type, depth = (2, 8) if img.ndim == 3 else (0, 16 if img.dtype == np.uint16 else 8)
    data = img.astype(">u2") if img.dtype == np.uint16 else img
    rows = np.frombuffer(np.ascontiguousarray(data).tobytes(), np.uint8).reshape(h, -1)
    bpp = (3 if img.ndim == 3 else 1) * (2 if img.dtype == np.uint16 else 1)
    prev = np.zeros(rows.shape[1], np.uint8)
    out = bytearray()
    for k, row in enumerate(rows):
        f = filters[k % len(filters)]
        out.append(f)
        out += _filter_row(row, prev, f, bpp).tobytes()
        prev = row
    header = struct.pack(">IIBBBBB", w, h, depth, colour_type, 0, 0, interlace)
    chunks = [_chunk(b"IHDR", header)] + [_chunk(k, b) for k, b in extra]
    z = zlib.compress(bytes(out), 6)
    # Two IDAT chunks: the stream may be split anywhere.
    chunks += [_chunk(b"IDAT", z[: len(z) // 2]), _chunk(b"IDAT", z[len(z) // 2 :]), _chunk(b"IEND", b"")]
    return b"\x89PNG\r\n\x1a\n" + b"".join(chunks)


def _opencv(buf: bytes, colour: bool) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_COLOR if colour else cv2.IMREAD_UNCHANGED)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if colour else img


def _images(rng: np.random.Generator) -> list[np.ndarray]:
    return [
        rng.integers(0, 256, (13, 17, 3), dtype=np.uint8),
        rng.integers(0, 256, (9, 11), dtype=np.uint8),
        rng.integers(0, 65536, (12, 7), dtype=np.uint16),
        # a depth-like image: smooth, with holes (0) and the invalid marker 65535
        np.where(rng.random((10, 16)) < 0.1, 0, 5000 + np.arange(160).reshape(10, 16) * 37).astype(np.uint16),
    ]


@pytest.fixture(params=[1, 2], ids=["torch-scan", "numpy-scan"])
def intra_op_threads(request):
    """Torch's intra-op threads: one takes the ``Sub`` rows' torch scan, two NumPy's."""
    before = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(before)


@pytest.mark.parametrize("filters", [[0], [1], [0, 1, 1], [1, 0]])
def test_none_and_sub_rows_decode_as_opencv_does(filters, intra_op_threads):
    rng = np.random.default_rng(0)
    for img in _images(rng):
        colour = img.ndim == 3
        buf = _encode(img, filters)
        fast = decode_png(np.frombuffer(buf, np.uint8), colour)
        assert fast is not None, "the fast path declined a None/Sub PNG"
        ref = _opencv(buf, colour)
        assert fast.dtype == ref.dtype and fast.shape == ref.shape
        np.testing.assert_array_equal(fast, ref)
        np.testing.assert_array_equal(fast, img)
        assert fast.flags.c_contiguous


@pytest.mark.parametrize("filters", [[2], [1, 2], [3], [4], [1, 4]])
def test_other_filters_are_left_to_opencv(filters):
    img = _images(np.random.default_rng(1))[0]
    buf = _encode(img, filters)
    assert decode_png(buf, True) is None
    np.testing.assert_array_equal(_opencv(buf, True), img)  # the encoder is right: OpenCV reads it


def test_layouts_and_chunks_off_the_path_return_none():
    rng = np.random.default_rng(2)
    rgb, grey = _images(rng)[0], _images(rng)[1]
    assert decode_png(_encode(rgb, [1]), colour=False) is None  # colour asked as grey
    assert decode_png(_encode(grey, [1]), colour=True) is None  # grey asked as colour
    assert decode_png(_encode(rgb, [1], extra=[(b"gAMA", struct.pack(">I", 45455))]), True) is None
    assert decode_png(_encode(rgb, [1], extra=[(b"tEXt", b"Software\x00test")]), True) is not None
    assert decode_png(b"\xff\xd8\xff" + bytes(64), True) is None  # a JPEG
    rgba = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", 4, 4, 8, 6, 0, 0, 0))
    assert decode_png(rgba + _chunk(b"IEND", b""), True) is None


def test_damaged_streams_return_none_and_opencv_decides():
    img = _images(np.random.default_rng(3))[0]
    buf = bytearray(_encode(img, [1]))
    truncated = bytes(buf[: len(buf) - 30])
    assert decode_png(truncated, True) is None
    # A flipped byte inside the compressed data: inflate or its checksum fails.
    idat = buf.index(b"IDAT") + 10
    buf[idat] ^= 0xFF
    assert decode_png(bytes(buf), True) is None


def test_without_isal_there_is_no_fast_path(monkeypatch):
    monkeypatch.setattr(png, "_inflate", None)
    assert not png.available()
    assert decode_png(_encode(_images(np.random.default_rng(4))[0], [1]), True) is None


def test_read_image_stops_trying_a_stream_the_fast_path_declines(tmp_path: Path):
    rng = np.random.default_rng(5)
    img = _images(rng)[0]
    sub, paeth = tmp_path / "sub.png", tmp_path / "paeth.png"
    sub.write_bytes(_encode(img, [1]))
    paeth.write_bytes(_encode(img, [4]))
    fast = {"colour": True, "other": True}
    np.testing.assert_array_equal(_read_image(sub, cv2.IMREAD_COLOR, "x", fast), img)
    assert fast == {"colour": True, "other": True}
    np.testing.assert_array_equal(_read_image(paeth, cv2.IMREAD_COLOR, "x", fast), img)
    assert fast == {"colour": False, "other": True}
    np.testing.assert_array_equal(_read_image(sub, cv2.IMREAD_COLOR, "x", fast), img)  # OpenCV from now on


def _data_root() -> Path:
    return Path(os.environ.get("TORCHSLAM_DATA", Path(__file__).resolve().parents[2].parent / "shared" / "data"))


def test_shipped_sequences_frames_equal_with_and_without_the_fast_path():
    root = _data_root()
    names = [n for n in ("tum_fr1_xyz", "hololens_dvmvs", "7scenes_redkitchen") if (root / n / "rgb.txt").exists()]
    if not names:
        pytest.skip(f"no shipped sequence under {root} (set TORCHSLAM_DATA)")
    for name in names:
        fast_seq, slow_seq = TUMSequence(root / name), TUMSequence(root / name, fast_png=False)
        assert not any(slow_seq.fast_png_streams.values())
        for i in (0, len(fast_seq.timestamps) // 2):
            a, b = fast_seq[i], slow_seq[i]
            assert a.rgb.dtype == b.rgb.dtype and a.depth.dtype == b.depth.dtype
            assert bool((a.rgb == b.rgb).all()) and bool((a.depth == b.depth).all()), name
        if name != "7scenes_redkitchen":  # JPEG colour and Paeth-filtered depth: both declined
            assert all(fast_seq.fast_png_streams.values()), name
