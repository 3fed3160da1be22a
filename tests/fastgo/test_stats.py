"""PairStats: segment sums against per-pair float64 loops, merging, indexing, serialisation."""

from __future__ import annotations

import pytest
import torch

from torchslam.errors import ShapeError
from torchslam.fastgo import PairStats


def ragged(g: torch.Generator, sizes, dtype=torch.float64):
    pi = [torch.randn(k, 3, generator=g, dtype=dtype) + 2 for k in sizes]
    pj = [torch.randn(k, 3, generator=g, dtype=dtype) for k in sizes]
    w = [torch.rand(k, generator=g, dtype=dtype) for k in sizes]
    return pi, pj, w


def brute(pi, pj, w):
    """The 28 statistics by explicit per-pair sums (oracle)."""
    out = []
    for a, b, c in zip(pi, pj, w):
        out.append(
            (c.sum(), (c[:, None] * a).sum(0), (c[:, None] * b).sum(0),
             sum(ck * torch.outer(x, x) for ck, x in zip(c, a)),
             sum(ck * torch.outer(x, y) for ck, x, y in zip(c, a, b)),
             sum(ck * torch.outer(y, y) for ck, y in zip(c, b)))
        )
    return out


@pytest.mark.parametrize("weighted", [False, True])
def test_ragged_statistics_match_brute_force(weighted):
    g = torch.Generator().manual_seed(0)
    sizes = [3, 17, 1, 40]
    pi, pj, w = ragged(g, sizes)
    st = PairStats.from_correspondences(pi, pj, w if weighted else None)
    ref = brute(pi, pj, w if weighted else [torch.ones(k, dtype=torch.float64) for k in sizes])
    assert st.count.tolist() == sizes
    for m, (n, si, sj, Sii, Sij, Sjj) in enumerate(ref):
        assert torch.allclose(st.n[m], n)
        assert torch.allclose(st.s_i[m], si) and torch.allclose(st.s_j[m], sj)
        assert torch.allclose(st.S_ii[m], Sii) and torch.allclose(st.S_ij[m], Sij) and torch.allclose(st.S_jj[m], Sjj)


def test_padded_masked_equals_ragged():
    g = torch.Generator().manual_seed(1)
    sizes = [5, 9, 2]
    pi, pj, w = ragged(g, sizes)
    P_i = torch.full((3, 9, 3), float("nan"), dtype=torch.float64)
    P_j = torch.full((3, 9, 3), float("nan"), dtype=torch.float64)
    W = torch.zeros(3, 9, dtype=torch.float64)
    mask = torch.zeros(3, 9, dtype=torch.bool)
    for m, k in enumerate(sizes):
        P_i[m, :k], P_j[m, :k], W[m, :k], mask[m, :k] = pi[m], pj[m], w[m], True
    a = PairStats.from_padded(P_i, P_j, mask=mask, weights=W)
    b = PairStats.from_correspondences(pi, pj, w)
    assert torch.allclose(a.as_vector(), b.as_vector())
    assert a.count.tolist() == sizes
    c = PairStats.from_correspondences(P_i[:1, :5], P_j[:1, :5])
    assert torch.allclose(c.as_vector(), PairStats.from_correspondences(pi[:1], pj[:1]).as_vector())


def test_gram_of_weighted_rows_equals_ragged():
    g = torch.Generator().manual_seed(4)
    sizes = [6, 11]
    pi, pj, w = ragged(g, sizes)
    G = torch.stack([
        (torch.cat([torch.ones(k, 1, dtype=torch.float64), a, b], 1) * c[:, None]).T @ torch.cat([torch.ones(k, 1, dtype=torch.float64), a, b], 1)
        for k, a, b, c in zip(sizes, pi, pj, w)
    ])
    st = PairStats.from_gram(G, torch.tensor(sizes))
    ref = PairStats.from_correspondences(pi, pj, w)
    torch.testing.assert_close(st.as_vector(), ref.as_vector(), rtol=1e-12, atol=1e-12)
    assert st.count.tolist() == sizes
    with pytest.raises(ShapeError, match="G"):
        PairStats.from_gram(G[:, :6], torch.tensor(sizes))


def test_merge_is_union_and_swap_reverses():
    g = torch.Generator().manual_seed(2)
    pi, pj, w = ragged(g, [6, 4])
    qi, qj, v = ragged(g, [3, 8])
    merged = PairStats.from_correspondences(pi, pj, w).merge(PairStats.from_correspondences(qi, qj, v))
    union = PairStats.from_correspondences(
        [torch.cat([a, b]) for a, b in zip(pi, qi)], [torch.cat([a, b]) for a, b in zip(pj, qj)],
        [torch.cat([a, b]) for a, b in zip(w, v)],
    )
    assert torch.allclose(merged.as_vector(), union.as_vector())
    assert merged.count.tolist() == [9, 12]
    sw = PairStats.from_correspondences(pi, pj, w).swapped()
    assert torch.allclose(sw.as_vector(), PairStats.from_correspondences(pj, pi, w).as_vector())
    with pytest.raises(ShapeError, match="other"):
        merged.merge(merged[0])


def test_indexing_cat_weighting_and_vector_round_trip():
    g = torch.Generator().manual_seed(3)
    pi, pj, w = ragged(g, [4, 5, 6])
    st = PairStats.from_correspondences(pi, pj, w)
    assert len(st) == 3 and len(st[1]) == 1 and len(st[-1]) == 1
    assert torch.allclose(st[torch.tensor([2, 0])].n, st.n[[2, 0]])
    assert torch.allclose(st[torch.tensor([True, False, True])].S_ij, st.S_ij[[0, 2]])
    assert torch.allclose(PairStats.cat([st[:1], st[1:]]).as_vector(), st.as_vector())
    k = torch.tensor([2.0, 0.5, 0.0], dtype=torch.float64)
    scaled = PairStats.from_correspondences(pi, pj, [wi * ki for wi, ki in zip(w, k)])
    assert torch.allclose(st.weighted(k).as_vector(), scaled.as_vector())
    back = PairStats.from_vector(st.as_vector(), st.count)
    assert torch.allclose(back.S_ii, st.S_ii) and torch.allclose(back.S_jj, st.S_jj)
    assert st.as_vector().shape == (3, 28)


def test_state_dict_save_load_round_trip(tmp_path):
    g = torch.Generator().manual_seed(4)
    st = PairStats.from_correspondences(*ragged(g, [3, 7]))
    path = tmp_path / "stats.pt"
    torch.save(st.state_dict(), path)
    back = PairStats.from_state_dict(torch.load(path))
    for f in ("n", "count", "s_i", "s_j", "S_ii", "S_ij", "S_jj"):
        assert torch.equal(getattr(back, f), getattr(st, f))
    with pytest.raises(ShapeError, match="missing"):
        PairStats.from_state_dict({"n": st.n})


def test_nan_point_spoils_only_its_pair_and_bad_shapes_raise():
    g = torch.Generator().manual_seed(5)
    pi, pj, _ = ragged(g, [4, 4])
    pi[1][2, 0] = float("nan")
    st = PairStats.from_correspondences(pi, pj)
    assert torch.isfinite(st[0].as_vector()).all() and not torch.isfinite(st[1].as_vector()).all()
    with pytest.raises(ShapeError, match=r"points_j\[0\]"):
        PairStats.from_correspondences([pi[0]], [pj[0][:3]])
    with pytest.raises(ShapeError, match="points_j"):
        PairStats.from_correspondences(pi, pj[:1])
    with pytest.raises(ShapeError, match=r"points_i\[0\]"):
        PairStats.from_correspondences([pi[0][:, :2]], [pj[0][:, :2]])


def test_gradients_flow_to_points_and_weights():
    g = torch.Generator().manual_seed(6)
    pi = torch.randn(2, 4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    pj = torch.randn(2, 4, 3, generator=g, dtype=torch.float64)
    w = torch.rand(2, 4, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: PairStats.from_padded(a, pj, weights=b).as_vector(), (pi, w))
