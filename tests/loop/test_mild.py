"""MILD loop detection: real places, planted revisits, and the multi-index lookup against brute force."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchslam.errors import ConfigError, DTypeError, ShapeError
from torchslam.features import ORBConfig, extract_orb
from torchslam.loop import MILDConfig, MILDDatabase, MILDError, substring_keys
from torchslam.loop import mild as mild_module


def _rand(n, gen):
    return torch.randint(0, 256, (n, 32), dtype=torch.uint8, generator=gen)


def _flip_bits(desc: torch.Tensor, max_flips: int, gen: torch.Generator) -> torch.Tensor:
    """Flip between 0 and ``max_flips`` distinct random bits of every descriptor."""
    k = desc.shape[0]
    out = desc.clone()
    n_flip = torch.randint(0, max_flips + 1, (k,), generator=gen)
    order = torch.argsort(torch.rand(k, 256, generator=gen), dim=1)[:, :max_flips]  # distinct bit indices
    for j in range(max_flips):
        on = n_flip > j
        byte, bit = order[on, j] // 8, order[on, j] % 8
        out[on.nonzero().squeeze(-1), byte] ^= (1 << bit).to(torch.uint8)
    return out


def _ref_keys(desc: np.ndarray, bits: int) -> np.ndarray:
    """Substring values by plain integer arithmetic, (K, tables)."""
    nb = bits // 8
    grouped = desc.reshape(desc.shape[0], -1, nb).astype(np.int64)
    return sum(grouped[:, :, j] << (8 * j) for j in range(nb))


def _ref_candidates(query: np.ndarray, sets: list[np.ndarray], bits: int):
    """Brute force: every (query, keyframe, descriptor) whose substrings agree on some table."""
    qk = _ref_keys(query, bits)
    out = set()
    for kf, desc in enumerate(sets):
        if len(desc) == 0:
            continue
        eq = (qk[:, None, :] == _ref_keys(desc, bits)[None, :, :]).any(-1)
        out |= {(int(i), kf, int(j)) for i, j in zip(*np.nonzero(eq))}
    return out


def _ref_scores(query: np.ndarray, sets: list[np.ndarray], cfg: MILDConfig) -> np.ndarray:
    """Brute-force scores: candidates by substring equality, best weighted vote per keyframe."""
    qk = _ref_keys(query, cfg.bits)
    scores = np.zeros(len(sets))
    for kf, desc in enumerate(sets):
        if len(desc) == 0 or len(query) == 0:
            continue
        eq = (qk[:, None, :] == _ref_keys(desc, cfg.bits)[None, :, :]).any(-1)
        dist = np.unpackbits(query[:, None, :] ^ desc[None, :, :], axis=-1).sum(-1).astype(np.float64)
        ok = eq & (dist <= cfg.max_distance)
        w = np.where(ok, np.exp(-((dist / cfg.sigma) ** 2)), 0.0)
        scores[kf] = w.max(1).sum() / np.sqrt(len(query) * len(desc))
    return scores


def test_substring_keys_match_integer_reference():
    gen = torch.Generator().manual_seed(0)
    d = _rand(40, gen)
    for tables in (16, 32, 8):
        keys = substring_keys(d, tables)
        assert keys.shape == (tables, 40)
        assert np.array_equal(keys.T.numpy(), _ref_keys(d.numpy(), 256 // tables))
    assert substring_keys(d, 16).max() < 2**16


@pytest.mark.parametrize("bits,scale", [(16, 1), (8, 1), (16, 12)])
def test_multi_index_lookup_equals_substring_scan(bits, scale):
    gen = torch.Generator().manual_seed(1)
    cfg = MILDConfig(tables=256 // bits, bits=bits)
    db = MILDDatabase(cfg)
    sizes = [300, 0, 1, 257, 40, 512, 3, 128, 90, 300, 7, 600] * scale
    sets = [_rand(k, gen) for k in sizes]
    query = torch.cat([_flip_bits(sets[3][:60], 40, gen), _flip_bits(sets[9][:60], 25, gen), _rand(80, gen)])
    for i, s in enumerate(sets):
        db.add(100 + i, s)
    # Small runs are searched by bisection, large ones through CSR bucket offsets: cover both.
    with_offsets = [lvl.offsets is not None for lvl in db._levels]
    assert any(with_offsets) == (bits == 8 or scale > 1)
    assert not all(with_offsets) or bits == 8
    q_idx, kf_ids, d_idx = db.candidates(query)
    got = list(zip(q_idx.tolist(), (kf_ids - 100).tolist(), d_idx.tolist()))
    ref = _ref_candidates(query.numpy(), [s.numpy() for s in sets], bits)
    assert len(got) == len(set(got))  # each pair once
    assert set(got) == ref
    assert len(ref) > 50


def test_host_row_search_equals_torch_searchsorted(monkeypatch):
    """The host's row-by-row NumPy search (values in ascending order, sorted runs or queries by
    their argsort) gives torch.searchsorted's positions, ties and out-of-range values included;
    the database built and queried either way yields the same candidates."""
    gen = torch.Generator().manual_seed(5)
    keys = torch.sort(torch.randint(0, 50, (4, 300), dtype=torch.int32, generator=gen), dim=1).values  # many ties
    values = torch.randint(-5, 60, (4, 120), dtype=torch.int32, generator=gen)
    ascending = mild_module._ascending(values)
    run = torch.sort(values, dim=1).values
    for right in (False, True):
        assert torch.equal(mild_module._search_rows(keys, values, right, ascending), torch.searchsorted(keys, values, right=right))
        assert torch.equal(mild_module._search_rows(keys, run, right), torch.searchsorted(keys, run, right=right))
    sets = [_rand(k, gen) for k in (300, 40, 512, 3, 128, 90, 300)]
    query = torch.cat([_flip_bits(sets[2][:60], 30, gen), _rand(50, gen)])
    found = []
    for host in (True, False):
        if not host:
            monkeypatch.setattr(mild_module, "numpy_viewable", lambda x: False)
        db = MILDDatabase()
        for i, d in enumerate(sets):
            db.add(i, d)
        found.append([t.tolist() for t in db.candidates(query)] + [db.similarity(query)[1].tolist()])
    assert found[0] == found[1] and len(found[0][0]) > 50


def test_levels_stay_sorted_and_geometric():
    gen = torch.Generator().manual_seed(2)
    db = MILDDatabase()
    total = 0
    for i in range(40):
        k = int(torch.randint(0, 400, (1,), generator=gen))
        db.add(i, _rand(k, gen))
        total += k
    assert len(db) == 40 and db.num_descriptors == total
    sizes = [lvl.size for lvl in db._levels]
    assert sum(sizes) == total
    assert all(a > 2 * b for a, b in zip(sizes, sizes[1:]))
    assert db.num_levels <= int(np.log2(total)) + 1
    for lvl in db._levels:
        keys, ids = lvl.keys.long(), lvl.ids.long()
        order = keys * total + ids  # (key, id) must be strictly increasing along each table
        assert (order[:, 1:] > order[:, :-1]).all()
    all_ids = torch.cat([lvl.ids.long() for lvl in db._levels], dim=1)
    assert torch.equal(all_ids.sort(dim=1).values, torch.arange(total).expand(16, total))


def test_scores_equal_brute_force_reference(monkeypatch):
    gen = torch.Generator().manual_seed(3)
    cfg = MILDConfig(max_distance=40, sigma=20.0)
    db = MILDDatabase(cfg)
    sets = [_rand(k, gen) for k in (200, 150, 0, 300, 120)]
    sets[3][:100] = _flip_bits(sets[0][:100], 30, gen)  # keyframes sharing part of a view
    for i, s in enumerate(sets):
        db.add(i, s)
    query = torch.cat([_flip_bits(sets[0][50:150], 35, gen), _flip_bits(sets[4][:40], 12, gen), _rand(60, gen)])
    ids, scores = db.similarity(query)
    assert ids.tolist() == [0, 1, 2, 3, 4] and scores.dtype == torch.float64
    ref = _ref_scores(query.numpy(), [s.numpy() for s in sets], cfg)
    assert np.allclose(scores.numpy(), ref, rtol=1e-12, atol=1e-15)
    assert ref[0] > 0.1 and ref[4] > 0.05 and ref[2] == 0.0
    # Candidate pairs are processed in chunks: tiny chunks must give the same scores and candidates.
    monkeypatch.setattr(mild_module, "_HIT_CHUNK", 7)
    assert np.allclose(db.similarity(query)[1].numpy(), ref, rtol=1e-12, atol=1e-15)
    got = set(zip(*(t.tolist() for t in db.candidates(query))))
    assert got == _ref_candidates(query.numpy(), [s.numpy() for s in sets], cfg.bits)


def test_planted_revisit_is_top1_and_random_query_scores_zero():
    gen = torch.Generator().manual_seed(4)
    db = MILDDatabase(MILDConfig(exclude_recent=0))
    sets = [_rand(300, gen) for _ in range(50)]
    for i, s in enumerate(sets):
        db.add(1000 + i, s)
    for target in (0, 17, 49):
        query = _flip_bits(sets[target], 10, gen)
        ids, scores = db.query(query)
        assert int(ids[0]) == 1000 + target
        assert float(scores[0]) > 0.8  # <= 10 flips: every descriptor found (pigeonhole), weight >= exp(-0.16)
        assert len(ids) == 1 or float(scores[1]) < 0.05 * float(scores[0])
    _, all_scores = db.similarity(_rand(300, gen))
    assert all_scores.shape == (50,) and float(all_scores.max()) < 1e-3
    ids, scores = db.query(_rand(300, gen))
    assert ids.numel() == 0 and scores.numel() == 0  # nothing above min_score


def test_exclude_recent_top_k_and_min_score():
    gen = torch.Generator().manual_seed(5)
    base = _rand(400, gen)
    db = MILDDatabase(MILDConfig(top_k=3, exclude_recent=2, min_score=0.05))
    # Keyframe i shares the first 50 * (i + 1) descriptors of ``base`` (noisy), so later ones score higher.
    for i in range(8):
        k = 50 * (i + 1)
        db.add(i, torch.cat([_flip_bits(base[:k], 8, gen), _rand(400 - k, gen)]))
    ids, scores = db.query(base)
    assert ids.tolist() == [5, 4, 3]  # 7 and 6 are the two most recent, excluded
    assert (scores[:-1] >= scores[1:]).all()
    # min_score keeps exactly the keyframes scoring above it, even with room for more.
    db3 = MILDDatabase(MILDConfig(top_k=8, exclude_recent=0, min_score=0.3))
    for i in range(8):
        k = 50 * (i + 1)
        db3.add(i, torch.cat([base[:k], _rand(400 - k, gen)]))
    _, s_all = db3.similarity(base)
    expected = [i for i in range(8) if float(s_all[i]) > 0.3]
    ids3, s3 = db3.query(base)
    assert 0 < len(expected) < 8
    assert sorted(ids3.tolist()) == expected and (s3 > 0.3).all()


def test_empty_database_and_empty_query():
    gen = torch.Generator().manual_seed(6)
    db = MILDDatabase()
    ids, scores = db.query(_rand(10, gen))
    assert ids.numel() == 0 and scores.numel() == 0
    db.add(3, _rand(0, gen))  # a keyframe without features
    db.add(4, _rand(50, gen))
    assert len(db) == 2
    ids, scores = db.similarity(_rand(0, gen))
    assert ids.tolist() == [3, 4] and (scores == 0).all()
    q, k, j = db.candidates(_rand(0, gen))
    assert q.numel() == k.numel() == j.numel() == 0


def test_bad_input_raises():
    gen = torch.Generator().manual_seed(7)
    db = MILDDatabase()
    db.add(0, _rand(5, gen))
    with pytest.raises(MILDError, match="keyframe_id: 0 is already"):
        db.add(0, _rand(5, gen))
    with pytest.raises(ShapeError, match=r"descriptors: expected \(K, 32\)"):
        db.add(1, _rand(5, gen)[:, :8])
    with pytest.raises(DTypeError, match="descriptors: expected uint8"):
        db.query(_rand(5, gen).int())
    with pytest.raises(MILDError, match="database is on cpu"):
        db.query(torch.empty(5, 32, dtype=torch.uint8, device="meta"))
    with pytest.raises(ConfigError, match="tables/bits"):
        MILDConfig(tables=16, bits=8)
    with pytest.raises(ConfigError, match="bits: expected an integer >= 8 and <= 32"):
        MILDConfig(tables=4, bits=64)
    with pytest.raises(ConfigError, match="top_k"):
        MILDConfig(top_k=0)
    with pytest.raises(ConfigError, match="exclude_recent"):
        MILDConfig(exclude_recent=-1)
    with pytest.raises(ConfigError, match="tables: must divide"):
        substring_keys(_rand(3, gen), 5)


def _load_rgb(path: Path) -> torch.Tensor:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return torch.from_numpy(bgr[..., ::-1].copy()).permute(2, 0, 1).float() / 255.0


def _frames(root: Path, name: str, indices):
    names = sorted((root / name / "rgb").iterdir())
    return [_load_rgb(names[i]) for i in indices]


def test_real_frames_rank_the_nearby_keyframe_first(shared_data):
    tum_kf = [0, 40, 80, 120, 160, 200]
    places = {
        "tum": _frames(shared_data, "tum_fr1_xyz", tum_kf),
        "kitchen": _frames(shared_data, "7scenes_redkitchen", [0, 100, 200, 299]),
        "hololens": _frames(shared_data, "hololens_dvmvs", [0, 25, 49]),
    }
    orb = ORBConfig()
    db = MILDDatabase(MILDConfig(exclude_recent=0))
    owner = {}
    for place, frames in places.items():
        for i, img in enumerate(frames):
            kf = len(db)
            db.add(kf, extract_orb(img, orb).descriptors)
            owner[kf] = (place, i)
    queries = _frames(shared_data, "tum_fr1_xyz", [83, 123])
    for query_img, expect in zip(queries, (2, 3)):  # frames 83 and 123: next to keyframes 80 and 120
        desc = extract_orb(query_img, orb).descriptors
        ids, scores = db.query(desc)
        assert owner[int(ids[0])] == ("tum", expect)
        assert len(ids) == 5 and all(owner[int(i)][0] == "tum" for i in ids[:3])
        all_ids, all_scores = db.similarity(desc)
        other = max(float(s) for i, s in zip(all_ids, all_scores) if owner[int(i)][0] != "tum")
        assert other < 0.1 * float(scores[0])
        assert float(scores[0]) > 0.15
