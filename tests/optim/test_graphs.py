"""torchslam.optim.graphs against SciPy's sparse graph routines, which it replaces."""

import subprocess
import sys

import numpy as np
import pytest

from torchslam.optim import graphs as G


def _random_graph(rng, trial):
    n = int(rng.integers(1, 120))
    kind = trial % 4
    if kind == 0:  # a chain with loops, as a pose graph along a route
        r, c = np.arange(n - 1), np.arange(1, n)
        m = int(rng.integers(0, n))
        a = rng.integers(0, n, m)
        r, c = np.r_[r, a], np.r_[c, np.clip(a + rng.integers(-20, 20, m), 0, n - 1)]
    elif kind == 1:  # dense-ish random
        m = int(rng.integers(0, 3 * n))
        r, c = rng.integers(0, n, m), rng.integers(0, n, m)
    elif kind == 2:  # broken chains: several components
        r, c = np.arange(n - 1), np.arange(1, n)
        keep = rng.random(n - 1) < 0.8
        r, c = r[keep], c[keep]
    else:  # sparse random, isolated nodes, self-loops
        m = int(rng.integers(0, n))
        r, c = rng.integers(0, n, m), rng.integers(0, n, m)
    return n, r, c


def _scipy_csr(n, r, c):
    sp = pytest.importorskip("scipy.sparse")
    A = sp.csr_matrix((np.ones(2 * r.size), (np.r_[r, c].astype(np.int32), np.r_[c, r].astype(np.int32))), shape=(n, n))
    A.sum_duplicates()
    A.data[:] = 1.0
    return A


def test_routines_give_scipys_answers_on_random_graphs():
    csgraph = pytest.importorskip("scipy.sparse.csgraph")
    rng = np.random.default_rng(0)
    for trial in range(600):
        n, r, c = _random_graph(rng, trial)
        A = _scipy_csr(n, r, c)
        g = G.adjacency(n, r, c)
        np.testing.assert_array_equal(g.indptr, A.indptr)
        np.testing.assert_array_equal(g.indices, A.indices)
        k, labels = G.connected_components(g)
        k_ref, labels_ref = csgraph.connected_components(A, directed=False)
        assert k == k_ref
        np.testing.assert_array_equal(labels, labels_ref)
        np.testing.assert_array_equal(G.reverse_cuthill_mckee(g), csgraph.reverse_cuthill_mckee(A, symmetric_mode=True))
        s = int(rng.integers(0, n))
        assert G.bfs_last(g, s) == int(csgraph.breadth_first_order(A, s, directed=False, return_predecessors=False)[-1])
        d = csgraph.shortest_path(A, method="D", unweighted=True, directed=False, indices=s)
        np.testing.assert_array_equal(G.bfs_distances(g, s), np.where(np.isinf(d), -1, d).astype(np.int64))
        x = rng.random(n)
        np.testing.assert_allclose(g.neighbour_sum(x), A @ x, rtol=1e-12, atol=0)


def test_long_route_and_induced_subgraph():
    csgraph = pytest.importorskip("scipy.sparse.csgraph")
    rng = np.random.default_rng(1)
    n = 1500  # a long route with loops to nearby keyframes
    a = rng.integers(0, n, 800)
    r, c = np.r_[np.arange(n - 1), a], np.r_[np.arange(1, n), np.clip(a + rng.integers(-25, 25, 800), 0, n - 1)]
    off = r != c
    A, g = _scipy_csr(n, r[off], c[off]), G.adjacency(n, r[off], c[off])
    np.testing.assert_array_equal(G.reverse_cuthill_mckee(g), csgraph.reverse_cuthill_mckee(A, symmetric_mode=True))
    assert G.connected_components(g)[0] == 1
    nodes = np.sort(rng.choice(n, 400, replace=False))
    scratch = np.full(n, -1, dtype=np.int64)
    sub = G.induced(g, nodes, scratch)
    assert (scratch == -1).all()
    ref = A[nodes][:, nodes]
    ref.sort_indices()
    np.testing.assert_array_equal(sub.indptr, ref.indptr)
    np.testing.assert_array_equal(sub.indices, ref.indices)


def test_empty_and_single_node_graphs():
    g = G.adjacency(0, np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert G.connected_components(g)[0] == 0 and G.reverse_cuthill_mckee(g).size == 0
    g = G.adjacency(1, np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert G.connected_components(g)[0] == 1
    np.testing.assert_array_equal(G.reverse_cuthill_mckee(g), [0])
    assert G.bfs_last(g, 0) == 0


def test_fastgo_and_pose_graph_solves_import_no_scipy():
    # SciPy's sparse graphs took about 0.25 s to import in every GC-SLAM run and at NI-SLAM's
    # first loop test.
    code = """
import sys, torch
from torchslam.optim.blocksparse import analyze
sym = analyze(50, torch.arange(49), torch.arange(1, 50), ordering="band")
sym = analyze(50, torch.arange(49), torch.arange(1, 50), ordering="nested", leaf_size=4)
from torchslam.fastgo import optimize
from torchslam.fastgo.synthetic import loop_route_problem
P = loop_route_problem(40, lap_length=20, loops_per_keyframe=1, noise=0.0, seed=1)
assert optimize(P.T_init, P.pairs, P.stats).converged
from torchslam.backend import chi2_quantile
chi2_quantile(0.999, 6)
print(sorted(m for m in sys.modules if m == "scipy" or m.startswith("scipy.")))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
