"""Hamming distances and descriptor matching against NumPy bit counts and OpenCV's BFMatcher."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, DTypeError, ShapeError
from torchslam.features import matching as matching_module
from torchslam.features import (
    HammingKernel,
    hamming_distance,
    hamming_distance_indexed,
    hamming_distance_packed,
    match_descriptors,
    match_descriptors_batched,
    pack_descriptors,
    pad_descriptors,
    popcount64,
)
from torchslam.features.matching import first_argmax_columns

KERNELS = ["swar", "lut", "matmul", "auto"]


def _rand(shape, gen):
    return torch.randint(0, 256, shape, dtype=torch.uint8, generator=gen)


def _ref_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Brute force: unpack both sets to bits and count differing bits for every pair."""
    return np.unpackbits(a[..., :, None, :] ^ b[..., None, :, :], axis=-1).sum(-1)


def _correlated(gen, k1=300, k2=400, flips=30):
    """Sets where many d1 rows are noisy copies of d2 rows, so thresholds and ratios matter."""
    b = _rand((k2, 32), gen)
    src = torch.randint(0, k2, (k1,), generator=gen)
    a = b[src].clone()
    bits = torch.randint(0, 256, (k1, flips), generator=gen)
    nflip = torch.randint(0, flips + 1, (k1,), generator=gen)
    for j in range(flips):
        on = nflip > j
        byte, bit = bits[:, j] // 8, bits[:, j] % 8
        a[on, byte[on]] ^= (1 << bit[on]).to(torch.uint8)
    a[: k1 // 5] = _rand((k1 // 5, 32), gen)  # some queries with no counterpart
    return a, b


def test_popcount64_matches_numpy_including_sign_bit():
    gen = torch.Generator().manual_seed(0)
    x = torch.randint(-(2**63), 2**63 - 1, (5000,), dtype=torch.int64, generator=gen)
    x[:4] = torch.tensor([0, -1, -(2**63), 2**63 - 1])
    ref = np.unpackbits(x.numpy().view(np.uint8).reshape(-1, 8), axis=-1).sum(-1)
    assert np.array_equal(popcount64(x).numpy(), ref)
    assert popcount64(x[:4]).tolist() == [0, 64, 1, 63]


@pytest.mark.parametrize("kernel", KERNELS)
def test_hamming_distance_equals_unpackbits_reference(kernel):
    gen = torch.Generator().manual_seed(1)
    a, b = _rand((257, 32), gen), _rand((130, 32), gen)
    a[0], b[0] = 0, 255  # distance 256 overflows a one-byte total
    a[1], b[1] = 255, 255
    d = hamming_distance(a, b, kernel)
    assert d.dtype == torch.int32 and d.shape == (257, 130)
    ref = _ref_distance(a.numpy(), b.numpy())
    assert np.array_equal(d.numpy(), ref)
    assert d[0, 0] == 256 and d[1, 1] == 0


@pytest.mark.parametrize("kernel", ["swar", "lut", "matmul"])
@pytest.mark.parametrize("lead", [(), (1,), (5,), (2, 3)])
def test_hamming_distance_batch_shapes_equal_per_item(kernel, lead):
    gen = torch.Generator().manual_seed(2)
    a, b = _rand((*lead, 17, 32), gen), _rand((*lead, 9, 32), gen)
    d = hamming_distance(a, b, kernel)
    assert d.shape == (*lead, 17, 9)
    flat_a, flat_b, flat_d = a.reshape(-1, 17, 32), b.reshape(-1, 9, 32), d.reshape(-1, 17, 9)
    for i in range(flat_a.shape[0]):
        assert np.array_equal(flat_d[i].numpy(), _ref_distance(flat_a[i].numpy(), flat_b[i].numpy()))


def test_hamming_distance_empty_sets():
    gen = torch.Generator().manual_seed(3)
    assert hamming_distance(_rand((0, 32), gen), _rand((4, 32), gen)).shape == (0, 4)
    assert hamming_distance(_rand((3, 32), gen), _rand((0, 32), gen)).shape == (3, 0)


def test_packed_distance_and_packing():
    gen = torch.Generator().manual_seed(4)
    a, b = _rand((50, 32), gen), _rand((50, 32), gen)
    wa, wb = pack_descriptors(a), pack_descriptors(b)
    assert wa.shape == (50, 4) and wa.dtype == torch.int64
    ref = np.unpackbits(a.numpy() ^ b.numpy(), axis=-1).sum(-1)
    assert np.array_equal(hamming_distance_packed(wa, wb).numpy(), ref)


def test_indexed_distance_equals_reference_in_any_chunking():
    gen = torch.Generator().manual_seed(11)
    a, b = _rand((70, 32), gen), _rand((90, 32), gen)
    i1 = torch.randint(0, 70, (1000,), generator=gen)
    i2 = torch.randint(0, 90, (1000,), generator=gen)
    ref = np.unpackbits(a.numpy()[i1.numpy()] ^ b.numpy()[i2.numpy()], axis=-1).sum(-1)
    for chunk in (1, 7, 1000, 1 << 15):
        got = hamming_distance_indexed(pack_descriptors(a), i1, pack_descriptors(b), i2, chunk=chunk)
        assert np.array_equal(got.numpy(), ref)
    empty = torch.zeros(0, dtype=torch.int64)
    assert hamming_distance_indexed(pack_descriptors(a), empty, pack_descriptors(b), empty).shape == (0,)


@pytest.mark.parametrize("kernel", ["swar", "lut", "matmul"])
def test_row_blocks_do_not_change_results(kernel, monkeypatch):
    """Distance matrices are computed in row blocks; mutual checks must combine blocks exactly."""
    gen = torch.Generator().manual_seed(12)
    a, b = _correlated(gen, 150, 120)
    a[100:] = a[:50]  # duplicate queries: ties between rows that fall in different blocks
    ref_d = hamming_distance(a, b, kernel)
    ref_m = match_descriptors(a, b, max_distance=80, mutual=True, ratio=0.95, backend="torch", kernel=kernel)
    for name in ("_BLOCK_CPU", "_BLOCK_GEMM"):
        monkeypatch.setattr(matching_module, name, 7 * 120)  # 7 rows per block
    assert torch.equal(hamming_distance(a, b, kernel), ref_d)
    m = match_descriptors(a, b, max_distance=80, mutual=True, ratio=0.95, backend="torch", kernel=kernel)
    assert torch.equal(m.pairs, ref_m.pairs) and torch.equal(m.distances, ref_m.distances)
    assert m.pairs.shape[0] > 10
    assert m.pairs.tolist() == [[i, j] for i, j, _ in _np_match(a.numpy(), b.numpy(), 80, True, 0.95)]


def _bf_nearest(a: np.ndarray, b: np.ndarray):
    m = cv2.BFMatcher(cv2.NORM_HAMMING).match(a, b)
    idx = np.array([x.trainIdx for x in m])
    dist = np.array([x.distance for x in m])
    qidx = np.array([x.queryIdx for x in m])
    order = np.argsort(qidx)
    return idx[order], dist[order]


@pytest.mark.parametrize("backend", ["torch", "opencv", "int8"])
@pytest.mark.parametrize("kernel", ["swar", "matmul"])
def test_nearest_neighbour_equals_opencv_bfmatcher(backend, kernel):
    gen = torch.Generator().manual_seed(5)
    a, b = _correlated(gen)
    ref_idx, ref_dist = _bf_nearest(a.numpy(), b.numpy())
    m = match_descriptors(a, b, max_distance=256, backend=backend, kernel=kernel)
    assert m.pairs.shape == (a.shape[0], 2)
    assert np.array_equal(m.pairs[:, 0].numpy(), np.arange(a.shape[0]))
    assert np.array_equal(m.distances.numpy(), ref_dist.astype(np.int32))
    # Where the nearest neighbour is unique, the index must agree too.
    full = _ref_distance(a.numpy(), b.numpy())
    unique = (full == full.min(1, keepdims=True)).sum(1) == 1
    assert unique.sum() > 0.5 * a.shape[0]
    assert np.array_equal(m.pairs[unique, 1].numpy(), ref_idx[unique])


def test_nearest_neighbour_on_real_orb_descriptors(shared_data):
    from torchslam.features import ORBConfig, extract_orb

    names = sorted((shared_data / "tum_fr1_xyz" / "rgb").iterdir())[:2]
    imgs = [cv2.imread(str(p))[..., ::-1].copy() for p in names]
    rgb = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).float() / 255.0
    f1, f2 = extract_orb(rgb, ORBConfig(n_features=1000))
    ref_idx, ref_dist = _bf_nearest(f1.descriptors.numpy(), f2.descriptors.numpy())
    for backend in ("torch", "opencv", "int8"):
        m = match_descriptors(f1.descriptors, f2.descriptors, max_distance=256, backend=backend)
        assert np.array_equal(m.distances.numpy(), ref_dist.astype(np.int32))
    # GC-SLAM default threshold keeps a large share between consecutive frames.
    m = match_descriptors(f1.descriptors, f2.descriptors)
    assert m.pairs.shape[0] > 0.4 * len(f1)
    assert int(m.distances.max()) <= 50


def _np_match(a, b, max_distance, mutual, ratio):
    """Loop reference for the matching rules (first index on ties)."""
    full = _ref_distance(a, b)
    out = []
    for i in range(a.shape[0]):
        j = int(np.argmin(full[i]))
        d = int(full[i, j])
        if d > max_distance:
            continue
        if ratio is not None and b.shape[0] >= 2:
            second = np.sort(full[i])[1]
            if not d < ratio * second:
                continue
        if mutual and int(np.argmin(full[:, j])) != i:
            continue
        out.append((i, j, d))
    return out


@pytest.mark.parametrize("backend", ["torch", "opencv", "int8"])
@pytest.mark.parametrize("mutual,ratio,max_distance", [(False, None, 50), (True, None, 60), (False, 0.8, 256), (True, 0.7, 40)])
def test_match_rules_equal_loop_reference(backend, mutual, ratio, max_distance):
    gen = torch.Generator().manual_seed(6)
    a, b = _correlated(gen, 120, 150)
    ref = _np_match(a.numpy(), b.numpy(), max_distance, mutual, ratio)
    m = match_descriptors(a, b, max_distance=max_distance, mutual=mutual, ratio=ratio, backend=backend)
    got = [(int(i), int(j), int(d)) for (i, j), d in zip(m.pairs.tolist(), m.distances.tolist())]
    assert got == ref
    assert len(ref) > 10  # the rules are exercised, not vacuous


@pytest.mark.parametrize("backend", ["torch", "opencv", "int8"])
def test_mutual_matching_takes_the_first_index_on_ties(backend):
    # Repeated queries tie for a reference's nearest and repeated references for a query's;
    # 340 queries span several row blocks of the int8 path's column argmax.
    gen = torch.Generator().manual_seed(11)
    a, b = _correlated(gen, 300, 170)
    a, b = torch.cat([a, a[100:140]]), torch.cat([b, b[:30]])
    ref = _np_match(a.numpy(), b.numpy(), 60, True, None)
    m = match_descriptors(a, b, max_distance=60, mutual=True, backend=backend)
    got = [(int(i), int(j), int(d)) for (i, j), d in zip(m.pairs.tolist(), m.distances.tolist())]
    assert got == ref
    assert len(ref) > 50


@pytest.mark.parametrize("k1,k2", [(1, 5), (63, 7), (64, 64), (65, 3), (130, 200), (1000, 1)])
@pytest.mark.parametrize("spread", [0, 1, 50])
def test_first_argmax_columns_equals_argmax(k1, k2, spread):
    d = np.random.default_rng(k1 + k2 + spread).integers(-spread, spread + 1, (k1, k2)).astype(np.int32)
    np.testing.assert_array_equal(first_argmax_columns(d), d.argmax(0))


@pytest.mark.parametrize("kernel,backend", [("swar", "torch"), ("lut", "torch"), ("matmul", "torch"), ("swar", "opencv"), ("swar", "int8"), ("swar", "auto")])
def test_batched_matching_with_padding_equals_per_pair(kernel, backend):
    gen = torch.Generator().manual_seed(7)
    sets1, sets2 = [], []
    for k1, k2 in [(40, 60), (0, 10), (25, 1), (60, 33), (10, 0)]:
        a, b = _correlated(gen, max(k1, 1), max(k2, 1))
        sets1.append(a[:k1])
        sets2.append(b[:k2])
    p1, v1 = pad_descriptors(sets1)
    p2, v2 = pad_descriptors(sets2)
    # Garbage in the padding must not matter.
    p2 = torch.where(v2[..., None], p2, torch.zeros_like(p2))
    for mutual, ratio in [(False, None), (True, 0.9)]:
        res = match_descriptors_batched(p1, p2, v1, v2, max_distance=60, mutual=mutual, ratio=ratio, kernel=kernel,
                                        backend=backend)
        assert res.index.shape == p1.shape[:2]
        for b in range(len(sets1)):
            ref = _np_match(sets1[b].numpy(), sets2[b].numpy(), 60, mutual, ratio) if len(sets2[b]) else []
            k1 = len(sets1[b])
            got = [(i, int(res.index[b, i]), int(res.distance[b, i])) for i in range(k1) if res.index[b, i] >= 0]
            assert got == ref
            assert (res.index[b, k1:] == -1).all() and (res.distance[b, k1:] == -1).all()
            if len(sets2[b]) == 0:
                assert (res.distance[b] == -1).all()


def test_empty_inputs_give_empty_matches():
    gen = torch.Generator().manual_seed(8)
    for backend in ("torch", "opencv", "int8"):
        m = match_descriptors(_rand((0, 32), gen), _rand((5, 32), gen), backend=backend)
        assert m.pairs.shape == (0, 2) and m.distances.shape == (0,)
        m = match_descriptors(_rand((5, 32), gen), _rand((0, 32), gen), backend=backend)
        assert m.pairs.shape == (0, 2)


def test_bad_inputs_raise():
    gen = torch.Generator().manual_seed(9)
    a = _rand((5, 32), gen)
    with pytest.raises(ShapeError, match=r"d1: expected \(K1, 32\)"):
        match_descriptors(a[:, :16], a)
    with pytest.raises(DTypeError, match="d2: expected uint8"):
        match_descriptors(a, a.int())
    with pytest.raises(ConfigError, match="backend: 'gpu' is not one of"):
        match_descriptors(a, a, backend="gpu")
    with pytest.raises(ConfigError, match="kernel"):
        hamming_distance(a, a, kernel="popcnt")
    with pytest.raises(ConfigError, match="ratio"):
        match_descriptors(a, a, ratio=1.5)
    with pytest.raises(ConfigError, match="max_distance"):
        match_descriptors(a, a, max_distance=-1)
    with pytest.raises(ShapeError, match="d2: expected leading dimensions"):
        hamming_distance(a[None].expand(2, 5, 32), a[None])
    with pytest.raises(ShapeError, match="valid2"):
        match_descriptors_batched(a[None], a[None], valid2=torch.ones(1, 4, dtype=torch.bool))
    with pytest.raises(DTypeError, match="x: expected int64"):
        popcount64(torch.zeros(3, dtype=torch.int32))
    with pytest.raises(ShapeError, match="descriptors: expected at least one"):
        pad_descriptors([])
    assert HammingKernel("swar") is HammingKernel.SWAR


@pytest.mark.cuda
def test_cuda_kernels_equal_cpu():
    gen = torch.Generator().manual_seed(10)
    a, b = _correlated(gen, 500, 700)
    ref = hamming_distance(a, b, "swar")
    for kernel in ("swar", "lut", "matmul"):
        assert torch.equal(hamming_distance(a.cuda(), b.cuda(), kernel).cpu(), ref)
    m_gpu = match_descriptors(a.cuda(), b.cuda(), mutual=True)
    m_cpu = match_descriptors(a, b, mutual=True, backend="torch")
    assert torch.equal(m_gpu.pairs.cpu(), m_cpu.pairs) and torch.equal(m_gpu.distances.cpu(), m_cpu.distances)


def _spin(seconds):
    """Burn ``seconds`` of this process's CPU time (the clock the backend probe reads)."""
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def _slowed(fn, seconds):
    def slow(*args):
        _spin(seconds)
        return fn(*args)

    return slow


def _sized(fn, seconds_per_million):
    """``fn`` that burns CPU in proportion to K1 x K2 (a brute force's cost)."""
    def slow(d1, d2, *args):
        _spin(seconds_per_million * d1.shape[0] * d2.shape[0] / 1e6)
        return fn(d1, d2, *args)

    return slow


def _probe_args():
    gen = torch.Generator().manual_seed(0)
    d1, d2 = torch.randint(0, 256, (2, 64, 32), dtype=torch.uint8, generator=gen)
    return d1, d2, 50, False, None


@pytest.mark.parametrize("slow", ["int8", "opencv"])
def test_auto_backend_on_the_cpu_is_the_faster_one_timed_once(monkeypatch, slow):
    # An int8 GEMM 60 x slower than OpenCV (an AVX2-only CPU) must not be picked.
    from torchslam.features import matching

    if not matching._INT8_GEMM:
        pytest.skip("this torch build has no int8 GEMM on the CPU")
    cpu = torch.device("cpu")
    originals = {name: getattr(matching, name) for name in ("_match_int8", "_match_opencv")}
    monkeypatch.setattr(matching, "_cpu_auto", None)
    monkeypatch.setattr(matching, "_int8_may_be_fast", lambda: True)  # timed whatever this CPU is
    for name, fn in originals.items():
        # The slow one sleeps; the other returns a result computed beforehand, in no time.
        done = fn(*_probe_args())
        monkeypatch.setattr(matching, name, _slowed(fn, 0.005) if name.endswith(slow) else (lambda *args, done=done: done))
    fast = matching.MatchBackend.OPENCV if slow == "int8" else matching.MatchBackend.INT8
    assert matching._resolve_backend("auto", cpu) is fast
    # Measured once per process: a later change of speed does not move the choice.
    for name, fn in originals.items():
        monkeypatch.setattr(matching, name, _slowed(fn, 0.05))
    start = time.perf_counter()
    assert matching.cpu_auto_backend() is fast
    assert time.perf_counter() - start < 0.05
    for name, fn in originals.items():
        monkeypatch.setattr(matching, name, fn)
    # Whatever it picks, auto gives the explicit backends' matches.
    gen = torch.Generator().manual_seed(3)
    a, b = _correlated(gen, 300, 400)
    ref = match_descriptors(a, b, mutual=True, backend="torch")
    got = match_descriptors(a, b, mutual=True)
    assert torch.equal(got.pairs, ref.pairs) and torch.equal(got.distances, ref.distances)


def test_auto_backend_is_decided_at_the_large_probe_and_skips_it_when_hopeless(monkeypatch):
    # A GEMM with a fixed cost per call but a cheaper brute force: dearer at 384 x 384, cheaper
    # at GC-SLAM's sizes, so the large probe must decide (the small one alone picked OpenCV on a
    # CPU where int8 is 3 x faster at 2,000 x 2,000).
    from torchslam.features import matching

    if not matching._INT8_GEMM:
        pytest.skip("this torch build has no int8 GEMM on the CPU")
    # The fakes burn only the modelled CPU time and match nothing (the probe discards the
    # matches): the real kernels' own time, 60 x apart on an AVX2-only CPU, is not the model's.
    sizes = []

    def int8_fixed(d1, d2, *args):
        sizes.append(d1.shape[0])
        _spin(0.002 + 0.0005 * d1.shape[0] * d2.shape[0] / 1e6)

    monkeypatch.setattr(matching, "_cpu_auto", None)
    monkeypatch.setattr(matching, "_int8_may_be_fast", lambda: True)  # timed whatever this CPU is
    monkeypatch.setattr(matching, "_match_int8", int8_fixed)
    monkeypatch.setattr(matching, "_match_opencv", _sized(lambda *args: None, 0.005))
    assert matching.cpu_auto_backend() is matching.MatchBackend.INT8
    assert sorted(set(sizes)) == [matching._PROBE_DESCRIPTORS, matching._PROBE_DESCRIPTORS_LARGE]
    # Far slower at the small size (an AVX2-only CPU): never timed at the large one.
    sizes.clear()
    monkeypatch.setattr(matching, "_cpu_auto", None)
    monkeypatch.setattr(matching, "_match_int8", _sized(lambda *a: sizes.append(a[0].shape[0]), 0.5))
    assert matching.cpu_auto_backend() is matching.MatchBackend.OPENCV
    assert set(sizes) == {matching._PROBE_DESCRIPTORS}


def test_auto_backend_probe_reads_the_process_cpu_time(monkeypatch):
    # OpenCV matches on worker threads, and a run has other work for the cores they take: the
    # probe compares the CPU time of every thread of the process. Here int8 works 1 ms and waits
    # 10 (cheap by that clock, slow by the wall clock) and OpenCV works 3 ms on a worker thread
    # (invisible to the calling thread's clock), so only the process's CPU time picks int8.
    import threading

    from torchslam.features import matching

    if not matching._INT8_GEMM:
        pytest.skip("this torch build has no int8 GEMM on the CPU")
    done = matching._match_opencv(*_probe_args())  # a result for both fakes: no real work in the timings

    def waiting(*args):
        _spin(0.001)
        time.sleep(0.01)
        return done

    def on_a_worker(*args):
        worker = threading.Thread(target=_spin, args=(0.003,))
        worker.start()
        worker.join()
        return done

    monkeypatch.setattr(matching, "_cpu_auto", None)
    monkeypatch.setattr(matching, "_int8_may_be_fast", lambda: True)  # timed whatever this CPU is
    monkeypatch.setattr(matching, "_match_int8", waiting)
    monkeypatch.setattr(matching, "_match_opencv", on_a_worker)
    assert matching.cpu_auto_backend() is matching.MatchBackend.INT8


@pytest.mark.parametrize(
    "flags, timed",
    [
        ({"avx2", "fma", "popcnt"}, False),  # AVX2 only: not timed, OpenCV
        ({"avx2", "avx512f", "avx512bw"}, True),  # AVX-512 without VNNI: timed
        ({"avx2", "avx512f", "avx512_vnni"}, True),
        ({"avx2", "avx_vnni"}, True),  # AVX-VNNI without AVX-512
        ({"avx2", "amx_int8"}, True),
        (None, True),  # flags unknown (not Linux, not x86): timed
    ],
)
def test_auto_backend_skips_the_probe_on_a_cpu_without_int8_dot_products(monkeypatch, flags, timed):
    from torchslam.features import matching

    if not matching._INT8_GEMM:
        pytest.skip("this torch build has no int8 GEMM on the CPU")
    probed = []
    monkeypatch.setattr(matching, "_cpu_auto", None)
    monkeypatch.setattr(matching, "_cpu_flags", lambda: None if flags is None else frozenset(flags))
    monkeypatch.setattr(matching, "_probe_cpu_ms", lambda n: probed.append(n) or (1.0, 2.0))  # int8 cheaper
    backend = matching.cpu_auto_backend()
    assert bool(probed) is timed
    assert backend is (matching.MatchBackend.INT8 if timed else matching.MatchBackend.OPENCV)


def test_cpu_flags_are_read_here():
    # On an x86 Linux machine the flags are read (every x86-64 CPU has sse2); elsewhere None.
    import platform

    from torchslam.features import matching

    flags = matching._cpu_flags()
    if platform.system() == "Linux" and platform.machine().lower() in ("x86_64", "amd64"):
        assert flags is not None and "sse2" in flags
    else:
        assert flags is None


def test_auto_backend_is_opencv_without_an_int8_gemm(monkeypatch):
    from torchslam.features import matching

    cpu = torch.device("cpu")
    monkeypatch.setattr(matching, "_INT8_GEMM", False)
    monkeypatch.setattr(matching, "_cpu_auto", None)
    monkeypatch.setattr(matching, "_match_int8", None)  # never timed: it would fail
    assert matching._resolve_backend("auto", cpu) is matching.MatchBackend.OPENCV
    assert matching._resolve_backend("auto", torch.device("meta")) is matching.MatchBackend.TORCH
    with pytest.raises(ConfigError, match="backend: 'int8' needs torch._int_mm"):
        matching._resolve_backend("int8", cpu)
