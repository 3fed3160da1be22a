"""Small undirected graphs in compressed sparse rows, in NumPy: what the sparse Cholesky's
analysis (:mod:`torchslam.optim.blocksparse`) and FastGO's connectivity check need.

SciPy's sparse graph routines did this before; importing them took about 0.25 s per process
(``scipy.sparse`` pulls in SciPy's array-API layer, ``scipy.sparse.csgraph`` its iterative
solvers), paid by every GC-SLAM run at start and by NI-SLAM at its first loop test. Graphs here
have keyframes as nodes (hundreds to a few thousand), so level-synchronous NumPy passes are
quick. Each routine gives SciPy's answer (``tests/optim/test_graphs.py`` compares them on
random graphs), so the orderings, and with them every factorisation, stay as they were.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = ["Csr", "adjacency", "bfs_distances", "bfs_last", "connected_components", "induced", "reverse_cuthill_mckee"]


@dataclass(frozen=True)
class Csr:
    """An undirected graph's adjacency: the neighbours of node ``v`` are
    ``indices[indptr[v]:indptr[v + 1]]``, each edge stored in both of its rows."""

    indptr: np.ndarray   # (n + 1,) int64
    indices: np.ndarray  # (nnz,) int64

    @property
    def n(self) -> int:
        return self.indptr.size - 1

    @functools.cached_property
    def rows(self) -> np.ndarray:
        """(nnz,) the row of each stored entry."""
        return np.repeat(np.arange(self.n), np.diff(self.indptr))

    def neighbour_sum(self, x: np.ndarray) -> np.ndarray:
        """(n,) per node the sum of ``x`` over its neighbours (the adjacency times ``x``)."""
        return np.bincount(self.rows, weights=x[self.indices], minlength=self.n)

    def entries_of(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions in ``indices`` of the rows of ``nodes``, row after row in stored order, and
        each row's count."""
        starts = self.indptr[nodes]
        counts = self.indptr[nodes + 1] - starts
        return np.repeat(starts - (np.cumsum(counts) - counts), counts) + np.arange(int(counts.sum())), counts


def adjacency(n: int, rows: np.ndarray, cols: np.ndarray) -> Csr:
    """The symmetric adjacency of the edges ``(rows[e], cols[e])`` on ``n`` nodes: each row's
    neighbours sorted and unique (SciPy's canonical CSR of the same pattern)."""
    r = np.concatenate([rows, cols]).astype(np.int64)
    c = np.concatenate([cols, rows]).astype(np.int64)
    row, col = np.divmod(np.unique(r * n + c), max(n, 1))
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(row, minlength=n), out=indptr[1:])
    return Csr(indptr, col)


def induced(graph: Csr, nodes: np.ndarray, local: np.ndarray) -> Csr:
    """The subgraph induced by ``nodes`` (in their order; ``local`` is scratch of size n, all -1,
    returned so)."""
    k = nodes.size
    local[nodes] = np.arange(k)
    flat, counts = graph.entries_of(nodes)
    nb = local[graph.indices[flat]]
    keep = nb >= 0
    rows = np.repeat(np.arange(k), counts)[keep]
    indptr = np.zeros(k + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=k), out=indptr[1:])
    local[nodes] = -1
    return Csr(indptr, nb[keep])


def connected_components(graph: Csr) -> tuple[int, np.ndarray]:
    """``(count, labels)``: components numbered in the order of their lowest node (as SciPy's
    ``connected_components(directed=False)``).

    Every node takes the lowest label among itself and its neighbours, then the label of its
    label (pointer jumping), until nothing changes: the labels settle on each component's lowest
    node in a few rounds even along a long chain.
    """
    n = graph.n
    if n == 0:
        return 0, np.zeros(0, dtype=np.int64)
    rows, cols = graph.rows, graph.indices
    label = np.arange(n)
    while True:
        new = label.copy()
        np.minimum.at(new, rows, label[cols])
        while True:
            jumped = new[new]
            if np.array_equal(jumped, new):
                break
            new = jumped
        if np.array_equal(new, label):
            break
        label = new
    roots, labels = np.unique(label, return_inverse=True)
    return roots.size, labels.astype(np.int64)


def _levels(graph: Csr, start: int, seen: np.ndarray, sort_key: np.ndarray | None = None):
    """Breadth-first levels from ``start`` in queue order (marking ``seen``): each level holds the
    unseen neighbours of the level before, parent by parent in queue order and each parent's in
    stored order; with ``sort_key``, each parent's new children are stably sorted by it."""
    level = np.array([start], dtype=np.int64)
    seen[start] = True
    while level.size:
        yield level
        flat, counts = graph.entries_of(level)
        cand = graph.indices[flat]
        parent = np.repeat(np.arange(level.size), counts)
        fresh = ~seen[cand]
        cand, parent = cand[fresh], parent[fresh]
        # A node reached from several parents belongs to the first (the queue's order).
        _, first = np.unique(cand, return_index=True)
        first.sort()
        cand, parent = cand[first], parent[first]
        if sort_key is not None and cand.size:
            o = np.lexsort((sort_key[cand], parent))  # stable: ties keep the stored order
            cand = cand[o]
        seen[cand] = True
        level = cand


def bfs_last(graph: Csr, start: int) -> int:
    """The last node a breadth-first search from ``start`` reaches (SciPy's
    ``breadth_first_order(...)[-1]``): a far node."""
    seen = np.zeros(graph.n, dtype=bool)
    last = start
    for level in _levels(graph, start, seen):
        last = int(level[-1])
    return last


def bfs_distances(graph: Csr, start: int) -> np.ndarray:
    """(n,) int64 hops from ``start`` (-1 where unreachable)."""
    dist = np.full(graph.n, -1, dtype=np.int64)
    seen = np.zeros(graph.n, dtype=bool)
    for d, level in enumerate(_levels(graph, start, seen)):
        dist[level] = d
    return dist


def reverse_cuthill_mckee(graph: Csr) -> np.ndarray:
    """(n,) int64 reverse Cuthill-McKee order (SciPy's ``reverse_cuthill_mckee`` of a symmetric
    pattern): each component from its lowest-degree node (lowest-degree first over the nodes,
    by NumPy's ``argsort`` of the int32 degrees, as SciPy's), breadth-first, each node's unvisited
    neighbours by increasing degree (ties in stored order), the whole order reversed."""
    n = graph.n
    degree = np.diff(graph.indptr).astype(np.int32)
    diag = np.zeros(n, dtype=bool)
    rows = graph.rows
    diag[rows[graph.indices == rows]] = True
    degree += diag  # a diagonal entry counts twice, as in SciPy
    seeds = np.argsort(degree)
    seen = np.zeros(n, dtype=bool)
    order: list[np.ndarray] = []
    done = 0
    for seed in seeds:
        if done == n:
            break
        if seen[seed]:
            continue
        for level in _levels(graph, int(seed), seen, sort_key=degree):
            order.append(level)
            done += level.size
    out = np.concatenate(order) if order else np.zeros(0, dtype=np.int64)
    return out[::-1].astype(np.int64)
