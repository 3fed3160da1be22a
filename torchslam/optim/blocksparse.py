"""Symmetric block-sparse matrices and their solves (normal equations of pose problems).

A :class:`BlockSparseMatrix` holds a symmetric positive (semi-)definite matrix made of
``b x b`` blocks: one block per node on the diagonal and a list of off-diagonal blocks, each
standing for the ``(rows[e], cols[e])`` block and, transposed, for ``(cols[e], rows[e])``. This
is the shape of every Gauss-Newton system in torchslam (FastGO, pose graphs, registration with
several frames): ``6 x 6`` blocks, one per pose, one off-diagonal block per constraint.

Independent problems of different sizes are solved together by concatenating their nodes
(:meth:`BlockSparseMatrix.cat`): the matrix is then block-diagonal over problems and the
factorisation never mixes them.

Solvers (:class:`SolverMethod`):

* ``CHOLESKY`` — block-sparse supernodal Cholesky. A fill-reducing order (reverse
  Cuthill-McKee band or nested dissection) is computed once per sparsity pattern on the host
  (:func:`analyze`); the numeric factorisation is multifrontal, one dense ``torch.linalg.cholesky_ex``
  per supernode, so it runs on any device and is differentiable by autograd.
* ``DENSE`` — assemble the full ``bN x bN`` matrix and factor it (small systems, reference).
* ``PCG`` — block-Jacobi preconditioned conjugate gradients, matrix-free (accelerators, large
  systems, when an approximate step is enough).

Convention:
    Nodes marked ``fixed`` take no update: their rows and columns are removed, their solution is
    zero. This is how a gauge (the first keyframe) is fixed.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError, DTypeError, InvalidValueError, ShapeError, check_float, check_shape, parse_choice
from .graphs import Csr, adjacency, bfs_distances, bfs_last, connected_components, induced, reverse_cuthill_mckee

__all__ = [
    "BlockSparseMatrix",
    "Ordering",
    "BlockCholeskySymbolic",
    "BlockCholeskyFactor",
    "Schedule",
    "SolverMethod",
    "analyze",
    "block_cholesky",
    "solve_block_sparse",
    "pcg_block_jacobi",
]


class SolverMethod(enum.Enum):
    """How a block-sparse system is solved."""

    AUTO = "auto"
    CHOLESKY = "cholesky"
    DENSE = "dense"
    PCG = "pcg"

    @classmethod
    def parse(cls, value: "SolverMethod | str") -> "SolverMethod":
        """Return the member for ``value``; a bad name lists the valid ones."""
        return parse_choice(cls, value, "solver method")


class Ordering(str, enum.Enum):
    """Fill-reducing order of the sparse Cholesky: reverse Cuthill-McKee band, or nested dissection."""

    BAND = "band"
    NESTED = "nested"


class Schedule(str, enum.Enum):
    """How the numeric factorisation and the solves walk the elimination tree.

    ``FRONT``: one supernode (front) at a time, in elimination order: dense calls per front,
    in-place assembly without autograd. ``LEVEL``: the fronts of one level of the elimination
    tree at once, batched by size class and padded to a common size: the number of calls
    grows with the tree's depth (times a few size classes) rather than with the number of
    fronts, for accelerators, where each call costs a launch. Only nested-dissection orders
    have shallow trees; a band order's tree is a chain (depth = fronts). Both schedules give
    the same factor up to round-off; on the CPU ``FRONT`` is faster
    (``scripts/bench_cholesky_schedule.py``).
    """

    FRONT = "front"
    LEVEL = "level"


@dataclass(frozen=True)
class BlockSparseMatrix:
    """A symmetric matrix of ``b x b`` blocks.

    Attributes:
        diag: (N, b, b) diagonal blocks.
        off: (E, b, b) off-diagonal blocks; ``off[e]`` is block ``(rows[e], cols[e])`` and its
            transpose is block ``(cols[e], rows[e])``. Repeated ``(row, col)`` entries add up.
        rows: (E,) int64 block-row index of each off-diagonal block.
        cols: (E,) int64 block-column index, ``cols[e] != rows[e]``.
    """

    diag: Tensor
    off: Tensor
    rows: Tensor
    cols: Tensor

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        check_shape(self.diag, "N b b", "diag", dims)
        check_shape(self.off, "E b b", "off", dims)
        check_shape(self.rows, "E", "rows", dims)
        check_shape(self.cols, "E", "cols", dims)
        check_float(self.diag, "diag")
        if self.off.dtype != self.diag.dtype:
            raise DTypeError(f"off: expected dtype {self.diag.dtype} like diag, got {self.off.dtype}")
        if self.rows.dtype != torch.int64 or self.cols.dtype != torch.int64:
            raise DTypeError(f"rows/cols: expected int64, got {self.rows.dtype}/{self.cols.dtype}")

    @property
    def num_nodes(self) -> int:
        """Number of block rows N."""
        return self.diag.shape[0]

    @property
    def block_size(self) -> int:
        """Block size b."""
        return self.diag.shape[-1]

    @staticmethod
    def cat(matrices: Sequence["BlockSparseMatrix"]) -> tuple["BlockSparseMatrix", Tensor]:
        """Concatenate independent systems into one block-diagonal system.

        Args:
            matrices: B systems of possibly different sizes ``N_b``.

        Returns:
            The combined system over ``sum N_b`` nodes and ``(B + 1,)`` int64 node offsets.
        """
        if len(matrices) == 0:
            raise ShapeError("matrices: expected at least one system, got none")
        sizes = torch.tensor([m.num_nodes for m in matrices], dtype=torch.int64)
        offsets = torch.cat([sizes.new_zeros(1), sizes.cumsum(0)])
        dev = matrices[0].diag.device
        shift = [int(o) for o in offsets[:-1]]
        return (
            BlockSparseMatrix(
                torch.cat([m.diag for m in matrices]),
                torch.cat([m.off for m in matrices]),
                torch.cat([m.rows + s for m, s in zip(matrices, shift)]),
                torch.cat([m.cols + s for m, s in zip(matrices, shift)]),
            ),
            offsets.to(dev),
        )

    def matvec(self, x: Tensor) -> Tensor:
        """Return ``A x``.

        Args:
            x: (N, b) block vector.

        Returns:
            (N, b) product.
        """
        check_shape(x, f"{self.num_nodes} {self.block_size}", "x")
        y = (self.diag @ x[..., None])[..., 0]
        y = y.index_add(0, self.rows, (self.off @ x[self.cols][..., None])[..., 0])
        return y.index_add(0, self.cols, (self.off.transpose(-1, -2) @ x[self.rows][..., None])[..., 0])

    def to_dense(self) -> Tensor:
        """Return the full ``(bN, bN)`` matrix (tests, small systems)."""
        n, b = self.num_nodes, self.block_size
        A = self.diag.new_zeros(n, n, b, b)
        idx = torch.arange(n, device=self.diag.device)
        A = A.index_put((idx, idx), self.diag, accumulate=True)
        A = A.index_put((self.rows, self.cols), self.off, accumulate=True)
        A = A.index_put((self.cols, self.rows), self.off.transpose(-1, -2), accumulate=True)
        return A.permute(0, 2, 1, 3).reshape(n * b, n * b)

    def add_to_diagonal(self, values: Tensor) -> "BlockSparseMatrix":
        """Return the matrix with ``values`` added to the scalar diagonal (damping).

        Args:
            values: (N, b) amounts added to the diagonal entries of each diagonal block.
        """
        check_shape(values, f"{self.num_nodes} {self.block_size}", "values")
        return BlockSparseMatrix(self.diag + torch.diag_embed(values), self.off, self.rows, self.cols)


# ----------------------------------------------------------------------------------------------
# Symbolic analysis: nested dissection order and supernodal structure (host, NumPy: torchslam.optim.graphs).
# ----------------------------------------------------------------------------------------------


@dataclass
class BlockCholeskySymbolic:
    """Fill-reducing order and supernodal structure of one sparsity pattern.

    Built by :func:`analyze` on the host and reusable for every matrix with the same pattern
    (every Gauss-Newton iteration of one problem). Index tensors are moved to a device on first
    use and cached there.

    Attributes:
        num_nodes: N, block rows of the full matrix (fixed nodes included).
        block_size: b.
        free: (N,) bool numpy mask of nodes that take an update.
        num_fronts: number of supernodes.
        front_sizes: list of (|S_t|, |U_t|) per supernode, in elimination order.
        factor_nnz: scalar entries stored by the factor (sum of ``b|S| * b(|S|+|U|)``).
    """

    num_nodes: int
    block_size: int
    free: np.ndarray
    num_fronts: int
    front_sizes: list
    factor_nnz: int
    # Per front t, in elimination order: supernode dofs, update dofs, children, element maps.
    _s_dofs: list = field(repr=False)
    _u_dofs: list = field(repr=False)
    _children: list = field(repr=False)
    _parent: np.ndarray = field(repr=False)
    _entry_src: list = field(repr=False)
    _entry_dst: list = field(repr=False)
    _entry_lower: list = field(repr=False)
    _child_ud: list = field(repr=False)
    _direct: list = field(repr=False)
    _node_front: np.ndarray = field(repr=False)
    _front_root: np.ndarray = field(repr=False)
    _num_edges: int = field(repr=False)
    _edge_keep: np.ndarray = field(repr=False)
    _device_cache: dict = field(default_factory=dict, repr=False)

    def tensors(self, device: torch.device) -> dict:
        """Return the index tensors of the front-by-front schedule on ``device`` (cached)."""
        key = str(device)
        if key not in self._device_cache:
            empty = np.zeros(0, dtype=np.int64)
            self._device_cache[key] = _upload({
                "s": self._s_dofs,
                "u": self._u_dofs,
                "src_all": self._untransposed(np.concatenate(self._entry_src)) if self._entry_src else empty,
                "src_bounds": np.cumsum([0] + [a.size for a in self._entry_src]).tolist(),
                # lower-triangle entries only: what the factorisation reads (fast path)
                "lo_all": self._untransposed(np.concatenate([a[lo] for a, lo in zip(self._entry_src, self._entry_lower)]))
                if self._entry_src else empty,
                "lo_bounds": np.cumsum([0] + [int(lo.sum()) for lo in self._entry_lower]).tolist(),
                "dst_lo": [a[lo] for a, lo in zip(self._entry_dst, self._entry_lower)],
                "dst": self._entry_dst,
                # scatter maps of the children's updates into each front; updates written in
                # place into the next front (``_direct``) need none on the no-autograd path
                "child": [
                    [None if self._direct[c] >= 0 else _square_map(*ud) for c, ud in zip(kids, lst)]
                    for kids, lst in zip(self._children, self._child_ud)
                ],
                # elimination-tree root of each front, and of each node's front (fixed nodes:
                # the spare slot F, never bad)
                "front_root": self._front_root,
                "node_root": self._node_root(),
            }, device)
        return self._device_cache[key]

    def _node_root(self) -> np.ndarray:
        """(N,) elimination-tree root of each node's front; ``num_fronts`` for fixed nodes."""
        return np.append(self._front_root, self.num_fronts)[self._node_front]

    @property
    def depth(self) -> int:
        """Height of the tallest elimination tree: its number of levels."""
        return self._plan()["depth"]

    @property
    def num_groups(self) -> int:
        """Batched calls per pass of the ``level`` schedule: size classes summed over the levels."""
        return len(self._plan()["fronts"])

    def _plan(self) -> dict:
        """The level schedule on the host (cached): fronts grouped by height and size.

        Level ``h`` holds the fronts whose longest path down to a leaf has ``h`` edges, so all
        their children lie in lower levels and the fronts of one level are independent. A
        level's fronts are split into size classes (pivot and update blocks rounded up to
        :data:`_LEVEL_SIZE_CLASS` nodes), so that padding costs little; a group is stored
        padded to its largest pivot block ``ms`` and update block ``mu`` (dofs): a front of
        pivot size ``m`` and update size ``nu`` occupies rows/columns ``[0, m)`` and
        ``[ms, ms + nu)`` of an ``n = ms + mu`` square; its padding is an identity pivot and
        zero couplings, so the padded factor is ``diag(L, I)`` and the padded update is zero
        outside the real one. Children's updates live in one flat pool, group by group,
        ``(P, mu, mu)`` each.
        """
        if "plan" in self._device_cache:
            return self._device_cache["plan"]
        b, nf = self.block_size, self.num_fronts
        height = np.zeros(nf, dtype=np.int64)
        for k in range(nf):  # children come before their parents
            if self._parent[k] >= 0:
                height[self._parent[k]] = max(height[self._parent[k]], height[k] + 1)
        depth = int(height.max()) + 1 if nf else 0
        sizes = np.array(self.front_sizes, dtype=np.int64).reshape(-1, 2)
        cls = -(-sizes // _LEVEL_SIZE_CLASS)  # size class of the pivot and update blocks
        order = np.lexsort((cls[:, 1], cls[:, 0], height))
        key = np.stack([height, cls[:, 0], cls[:, 1]], -1)[order]
        cut = np.nonzero(np.any(key[1:] != key[:-1], axis=1))[0] + 1
        fronts = [np.sort(g) for g in np.split(order, cut)] if nf else []
        group = np.zeros(nf, dtype=np.int64)
        slot = np.zeros(nf, dtype=np.int64)
        for gi, ks in enumerate(fronts):
            group[ks] = gi
            slot[ks] = np.arange(ks.size)
        m = sizes[:, 0] * b
        nu = sizes[:, 1] * b
        ms = [int(m[ks].max()) for ks in fronts]
        mu = [int(nu[ks].max()) for ks in fronts]
        pool_off = np.cumsum([0] + [ks.size * u * u for ks, u in zip(fronts, mu)])
        zero, sink = self.num_nodes * b, self.num_nodes * b + 1  # padding reads / writes
        groups = []
        for h, ks in enumerate(fronts):
            n = ms[h] + mu[h]
            src, dst, pad, csrc, cdst, s_r, s_w, u_r, u_w = ([] for _ in range(9))
            for k in ks:
                base = slot[k] * n * n
                R = np.concatenate([np.arange(m[k]), ms[h] + np.arange(nu[k])])  # local -> padded
                row, col = np.divmod(self._entry_dst[k], m[k] + nu[k])
                src.append(self._untransposed(self._entry_src[k]))
                dst.append(base + R[row] * n + R[col])
                d = np.arange(m[k], ms[h])
                pad.append(base + d * (n + 1))
                for c, (ud, _) in zip(self._children[k], self._child_ud[k]):
                    hc, uc = group[c], nu[c]
                    i = np.arange(uc)
                    csrc.append((pool_off[hc] + slot[c] * mu[hc] ** 2 + i[:, None] * mu[hc] + i[None, :]).ravel())
                    r = R[ud]
                    cdst.append((base + r[:, None] * n + r[None, :]).ravel())
                fill_s, fill_u = ms[h] - m[k], mu[h] - nu[k]
                s_r.append(np.concatenate([self._s_dofs[k], np.full(fill_s, zero)]))
                s_w.append(np.concatenate([self._s_dofs[k], np.full(fill_s, sink)]))
                u_r.append(np.concatenate([self._u_dofs[k], np.full(fill_u, zero)]))
                u_w.append(np.concatenate([self._u_dofs[k], np.full(fill_u, sink)]))
            cat = np.concatenate
            groups.append({
                "src": cat(src), "dst": cat(dst), "pad": cat(pad),
                "child_src": cat(csrc) if csrc else np.zeros(0, dtype=np.int64),
                "child_dst": cat(cdst) if cdst else np.zeros(0, dtype=np.int64),
                "s_read": cat(s_r), "s_write": cat(s_w), "u_read": cat(u_r), "u_write": cat(u_w),
            })
        order = np.concatenate(fronts) if fronts else np.zeros(0, dtype=np.int64)
        plan = {
            "fronts": fronts, "slot": slot, "group": group, "depth": depth, "ms": ms, "mu": mu,
            "pool_off": pool_off.tolist(), "groups": groups,
            # roots of the fronts in group order (the order of the factorisation's infos)
            "front_root": self._front_root[order],
        }
        self._device_cache["plan"] = plan
        return plan

    def level_tensors(self, device: torch.device) -> dict:
        """Return the index tensors of the level schedule on ``device`` (cached)."""
        key = "level:" + str(device)
        if key not in self._device_cache:
            plan = self._plan()
            self._device_cache[key] = _upload(
                {"groups": plan["groups"], "front_root": plan["front_root"], "node_root": self._node_root()}, device
            )
        return self._device_cache[key]

    def _untransposed(self, src: np.ndarray) -> np.ndarray:
        """Map entries of the transposed off-diagonal blocks onto the blocks themselves.

        Entry maps index ``[diag (N), off (E), off^T (E)]``; the factorisation gathers from
        ``[diag, off]`` only, so entry ``(i, j)`` of ``off^T[e]`` becomes ``(j, i)`` of ``off[e]``.
        """
        b2 = self.block_size ** 2
        first = (self.num_nodes + self._num_edges) * b2
        tr = src >= first
        e, r = np.divmod(src[tr] - first, b2)
        i, j = np.divmod(r, self.block_size)
        src = src.copy()
        src[tr] = (self.num_nodes + e) * b2 + j * self.block_size + i
        return src

    def child_maps(self, device: torch.device) -> list:
        """Scatter maps of every child's update into its parent front (autograd path, cached)."""
        key = "all:" + str(device)
        if key not in self._device_cache:
            self._device_cache[key] = _upload([[_square_map(*ud) for ud in lst] for lst in self._child_ud], device)
        return self._device_cache[key]


# Fronts of one level are batched by size class: pivot and update blocks rounded up to this
# many nodes (padding then adds about 20 % to the flops of FastGO's nested-dissection fronts,
# against 2.5-4x for one padded batch per level).
_LEVEL_SIZE_CLASS = 4


def _upload(tree, device: torch.device):
    """Copy the int numpy arrays of a nested structure (dicts, lists) to ``device`` in one transfer.

    Other leaves are kept as they are. The arrays become views of one int64 tensor.
    """
    flat: list[np.ndarray] = []

    def collect(x) -> None:
        if isinstance(x, np.ndarray):
            flat.append(x.astype(np.int64, copy=False).ravel())
        elif isinstance(x, dict):
            for v in x.values():
                collect(v)
        elif isinstance(x, list):
            for v in x:
                collect(v)

    collect(tree)
    whole = torch.as_tensor(np.concatenate(flat) if flat else np.zeros(0, dtype=np.int64), device=device)
    parts = iter(torch.split(whole, [a.size for a in flat]))

    def build(x):
        if isinstance(x, np.ndarray):
            return next(parts).view(x.shape)
        if isinstance(x, dict):
            return {k: build(v) for k, v in x.items()}
        if isinstance(x, list):
            return [build(v) for v in x]
        return x

    return build(tree)


def _square_map(ud: np.ndarray, nb: int) -> np.ndarray:
    """Flat positions in an ``nb x nb`` front of the ``ud x ud`` sub-matrix."""
    return (ud[:, None] * nb + ud[None, :]).ravel()


def _bisect(A_sub: Csr) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Split a connected graph by a breadth-first level set; ``None`` when it has too few levels."""
    start = bfs_last(A_sub, 0)  # a far node: repeat from it for a pseudo-peripheral start
    dist = bfs_distances(A_sub, start)
    nlev = int(dist.max()) + 1
    if nlev < 3:
        return None
    counts = np.bincount(dist, minlength=nlev)
    cum = np.cumsum(counts)
    n = cum[-1]
    # Candidate separator levels keep both sides between 30 % and 70 % of the nodes; the
    # smallest such level is the separator (ties go to the middle).
    lo = np.searchsorted(cum, 0.3 * n)
    hi = np.searchsorted(cum, 0.7 * n)
    cand = np.arange(max(lo, 1), min(hi, nlev - 2) + 1)
    if cand.size == 0:
        cand = np.array([min(max(int(np.searchsorted(cum, 0.5 * n)), 1), nlev - 2)])
    mid = np.searchsorted(cum, 0.5 * n)
    lev = int(cand[np.lexsort((np.abs(cand - mid), counts[cand]))[0]])
    in_lev = dist == lev
    # Keep in the separator only level nodes that touch the next level; the rest join side A.
    nxt = (dist == lev + 1).astype(np.float64)
    touches = A_sub.neighbour_sum(nxt) > 0
    sep = in_lev & touches
    side_a = (dist < lev) | (in_lev & ~touches)
    side_b = dist > lev
    return np.nonzero(sep)[0], np.nonzero(side_a)[0], np.nonzero(side_b)[0]


def _band_supernodes(A: Csr, size: int) -> tuple[list[np.ndarray], list[int], list[np.ndarray]]:
    """Supernodes of ``size`` consecutive nodes of a reverse Cuthill-McKee (band) order.

    Pose graphs that follow a route have a narrow profile in this order, so a run of
    consecutive nodes shares almost all of its update set and the fronts stay small without
    treating large sparse leaves as dense. The parent of a supernode is the one holding the
    first node of its update set (the elimination tree of the chunked order); connected
    components never share a supernode.

    Returns:
        Supernode node lists, parent supernode (-1 for roots) and update sets ``U_t`` (node ids
        sorted by elimination rank).
    """
    nf = A.n
    if nf == 0:
        return [], [], []
    perm = reverse_cuthill_mckee(A)
    ncomp, labels = connected_components(A)
    perm = perm[np.argsort(labels[perm], kind="stable")]
    comp_bounds = np.searchsorted(labels[perm], np.arange(ncomp + 1))
    sizes = np.diff(comp_bounds)
    counts = -(-sizes // size)
    # chunk boundaries: every component split into runs of at most `size` nodes
    starts = np.repeat(comp_bounds[:-1], counts) + size * (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))
    bounds = np.append(starts, nf)
    nsn = starts.size
    rank = np.empty(nf, dtype=np.int64)
    rank[perm] = np.arange(nf)
    chunk_of = np.repeat(np.arange(nsn), np.diff(bounds))
    # off-diagonal pattern in rank space, grouped by the chunk of the row and cut to later ranks
    ri, ci = rank[A.rows], rank[A.indices]
    later = ci >= bounds[chunk_of[ri] + 1]
    own_c, own_r = chunk_of[ri[later]], ci[later]
    order = np.argsort(own_c, kind="stable")
    own_c, own_r = own_c[order], own_r[order]
    ob = np.searchsorted(own_c, np.arange(nsn + 1))
    kids: list[list[int]] = [[] for _ in range(nsn)]
    parent = [-1] * nsn
    U_rank: list[np.ndarray] = [None] * nsn  # type: ignore[list-item]
    for t in range(nsn):
        end = bounds[t + 1]
        parts = [own_r[ob[t]:ob[t + 1]]] + [U_rank[c][U_rank[c] >= end] for c in kids[t]]
        u = np.unique(np.concatenate(parts))
        U_rank[t] = u
        if u.size:
            p = int(chunk_of[u[0]])
            parent[t] = p
            kids[p].append(t)
    sn_nodes = [perm[bounds[t]:bounds[t + 1]] for t in range(nsn)]
    return sn_nodes, parent, [perm[u] for u in U_rank]


def _dissect(A: Csr, leaf_size: int) -> tuple[list[np.ndarray], list[int]]:
    """Nested dissection of the adjacency ``A`` into supernodes and their parents."""
    nf = A.n
    # --- nested dissection into a forest of supernodes --------------------------------------
    sn_nodes: list[np.ndarray] = []
    sn_parent: list[int] = []
    stack: list[tuple[np.ndarray, int]] = [(np.arange(nf), -1)]
    scratch = np.full(nf, -1, dtype=np.int64)
    while stack:
        nodes, parent = stack.pop()
        if nodes.size == 0:
            continue
        sub = induced(A, nodes, scratch)
        ncomp, labels = connected_components(sub)
        order = np.argsort(labels, kind="stable")
        bounds = np.searchsorted(labels[order], np.arange(ncomp + 1))
        for c in range(ncomp):
            comp = nodes[order[bounds[c]:bounds[c + 1]]]
            # Separate components never share a supernode, so a failed factorisation of one
            # (e.g. one problem of a batch) cannot spoil another.
            if comp.size <= leaf_size:
                sn_nodes.append(comp)
                sn_parent.append(parent)
                continue
            split = _bisect(sub if ncomp == 1 else induced(A, comp, scratch))
            if split is None or split[0].size >= comp.size // 2:
                sn_nodes.append(comp)  # dense-ish part: no useful separator
                sn_parent.append(parent)
                continue
            sep, side_a, side_b = split
            sn_nodes.append(comp[sep])
            sn_parent.append(parent)
            me = len(sn_nodes) - 1
            stack.append((comp[side_a], me))
            stack.append((comp[side_b], me))

    return sn_nodes, sn_parent


def analyze(
    num_nodes: int,
    rows: Tensor | np.ndarray,
    cols: Tensor | np.ndarray,
    fixed: Tensor | np.ndarray | None = None,
    block_size: int = 6,
    leaf_size: int = 16,
    ordering: Ordering | str = Ordering.BAND,
) -> BlockCholeskySymbolic:
    """Compute a fill-reducing order and the supernodal structure of a block pattern.

    ``"band"`` (default): reverse Cuthill-McKee order cut into supernodes of ``leaf_size``
    consecutive nodes. Pose graphs along a route (odometry chain plus loops to nearby
    keyframes) keep a narrow profile in this order, so its factor has little fill and its
    analysis is cheaper than nested dissection's.
    ``"nested"``: nested dissection; each connected part larger than ``leaf_size`` nodes is
    split by a breadth-first level set from a pseudo-peripheral node; the separator becomes a
    supernode eliminated after both halves. Connected parts of at most ``leaf_size`` nodes are
    dense leaf supernodes (suits mesh-like graphs with a wide profile).
    Separate components never share a supernode in either order.

    Args:
        num_nodes: N, block rows.
        rows: (E,) block-row indices of the off-diagonal blocks.
        cols: (E,) block-column indices.
        fixed: optional (N,) bool mask of nodes removed from the system.
        block_size: b.
        leaf_size: supernode size in nodes (``"band"``), or the largest part left without
            dissection (``"nested"``).
        ordering: ``"band"`` or ``"nested"``.

    Returns:
        The symbolic structure, reusable while the pattern stays the same.
    """
    rows_np = np.asarray(rows.detach().cpu() if isinstance(rows, Tensor) else rows, dtype=np.int64)
    cols_np = np.asarray(cols.detach().cpu() if isinstance(cols, Tensor) else cols, dtype=np.int64)
    if rows_np.shape != cols_np.shape or rows_np.ndim != 1:
        raise ShapeError(f"rows/cols: expected two (E,) arrays, got {rows_np.shape} and {cols_np.shape}")
    if rows_np.size and (min(rows_np.min(), cols_np.min()) < 0 or max(rows_np.max(), cols_np.max()) >= num_nodes):
        raise InvalidValueError(f"rows/cols: block indices must lie in [0, {num_nodes})")
    ordering = parse_choice(Ordering, ordering, "ordering")
    if leaf_size < 1:
        raise ConfigError(f"leaf_size: expected >= 1 nodes, got {leaf_size}")
    free = np.ones(num_nodes, dtype=bool)
    if fixed is not None:
        f = np.asarray(fixed.detach().cpu() if isinstance(fixed, Tensor) else fixed, dtype=bool)
        if f.shape != (num_nodes,):
            raise ShapeError(f"fixed: expected ({num_nodes},), got {f.shape}")
        free &= ~f
    b = block_size
    free_ids = np.nonzero(free)[0]
    nf = free_ids.size
    new_id = np.full(num_nodes, -1, dtype=np.int64)
    new_id[free_ids] = np.arange(nf)
    edge_keep = free[rows_np] & free[cols_np] & (rows_np != cols_np)
    er, ec = new_id[rows_np[edge_keep]], new_id[cols_np[edge_keep]]
    A = adjacency(nf, er, ec)

    if ordering == "band":
        sn_nodes, sn_parent, U_band = _band_supernodes(A, leaf_size)
    else:
        sn_nodes, sn_parent = _dissect(A, leaf_size)
        U_band = None
    ns = len(sn_nodes)
    children: list[list[int]] = [[] for _ in range(ns)]
    for t, p in enumerate(sn_parent):
        if p >= 0:
            children[p].append(t)
    # Postorder: children before their parent.
    post: list[int] = []
    roots = [t for t in range(ns) if sn_parent[t] < 0]
    work = [(r, False) for r in reversed(roots)]
    while work:
        t, done = work.pop()
        if done:
            post.append(t)
            continue
        work.append((t, True))
        work.extend((c, False) for c in reversed(children[t]))
    pos_of = np.empty(ns, dtype=np.int64)
    pos_of[post] = np.arange(ns)

    rank = np.empty(nf, dtype=np.int64)
    node_front = np.empty(nf, dtype=np.int64)
    r = 0
    for k, t in enumerate(post):
        rank[sn_nodes[t]] = np.arange(r, r + sn_nodes[t].size)
        node_front[sn_nodes[t]] = k
        r += sn_nodes[t].size

    # --- supernodal structure: U_t = (adj(S_t) U children's U) with rank beyond S_t ----------
    indptr, indices = A.indptr, A.indices
    if U_band is not None:
        U = U_band
    else:
        U = [np.empty(0, dtype=np.int64)] * ns
        for t in post:
            S = sn_nodes[t]
            nbr = np.concatenate([indices[indptr[v]:indptr[v + 1]] for v in S] + [U[c] for c in children[t]])
            nbr = np.unique(nbr)
            last = rank[S].max()
            Ut = nbr[rank[nbr] > last]
            U[t] = Ut[np.argsort(rank[Ut])]

    # --- element maps: original entries and children's updates into each front --------------
    # Original entries are the concatenation [diag blocks (N), off (E), off^T (E)], flattened
    # to scalars; entry (a, c) is assembled in the front that eliminates the earlier of a, c.
    e_all = rows_np.size
    src_row = np.concatenate([new_id, new_id[rows_np], new_id[cols_np]])
    src_col = np.concatenate([new_id, new_id[cols_np], new_id[rows_np]])
    valid = (src_row >= 0) & (src_col >= 0)
    valid[num_nodes:num_nodes + e_all] &= edge_keep
    valid[num_nodes + e_all:] &= edge_keep
    blk = np.nonzero(valid)[0]
    br, bc = src_row[blk], src_col[blk]
    owner_node = np.where(rank[br] <= rank[bc], br, bc)
    owner = node_front[owner_node]
    order_b = np.argsort(owner, kind="stable")
    blk, br, bc, owner = blk[order_b], br[order_b], bc[order_b], owner[order_b]
    obounds = np.searchsorted(owner, np.arange(ns + 1))

    local = np.full(nf, -1, dtype=np.int64)
    bi = np.arange(b)
    s_dofs, u_dofs, child_ud, kids, sizes = [], [], [], [], []
    lr_all = np.empty(blk.size, dtype=np.int64)
    lc_all = np.empty(blk.size, dtype=np.int64)
    nb_all = np.empty(blk.size, dtype=np.int64)
    direct = [-1] * ns
    nnz = 0
    for k, t in enumerate(post):
        S, Ut = sn_nodes[t], U[t]
        idx = np.concatenate([S, Ut])
        n_loc = idx.size
        local[idx] = np.arange(n_loc)
        nb = n_loc * b
        # block positions of the original blocks owned by this front
        sl = slice(obounds[k], obounds[k + 1])
        lr_all[sl], lc_all[sl], nb_all[sl] = local[br[sl]], local[bc[sl]], nb
        cd = []
        for c in children[t]:
            uc = local[U[c]] * b
            if pos_of[c] == k - 1 and uc.size and uc[-1] - uc[0] == (uc.size - 1) * b:
                # the front just before lands on one diagonal block of this one (band orders)
                direct[k - 1] = int(uc[0])
            cd.append(((uc[:, None] + bi[None, :]).ravel(), nb))
        child_ud.append(cd)
        kids.append([int(pos_of[c]) for c in children[t]])
        s_dofs.append((free_ids[S][:, None] * b + bi[None, :]).ravel())
        u_dofs.append((free_ids[Ut][:, None] * b + bi[None, :]).ravel())
        sizes.append((int(S.size), int(Ut.size)))
        nnz += S.size * b * (S.size + Ut.size) * b
        local[idx] = -1
    # scalar entries of all owned blocks at once, split per front below
    src = (blk[:, None, None] * (b * b) + bi[None, :, None] * b + bi[None, None, :]).ravel()
    row = (lr_all[:, None, None] * b + bi[None, :, None] + 0 * bi[None, None, :]).ravel()
    col = (lc_all[:, None, None] * b + 0 * bi[None, :, None] + bi[None, None, :]).ravel()
    dst = row * np.repeat(nb_all, b * b) + col
    cut = obounds[1:-1] * (b * b)
    entry_src, entry_dst, entry_lower = np.split(src, cut), np.split(dst, cut), np.split(row >= col, cut)
    parent_pos = np.array([pos_of[sn_parent[t]] if sn_parent[t] >= 0 else -1 for t in post], dtype=np.int64)
    nf_full = np.full(num_nodes, -1, dtype=np.int64)
    nf_full[free_ids] = node_front
    # root of each front's elimination tree: parents come after their children
    root = np.arange(ns, dtype=np.int64)
    for k in range(ns - 1, -1, -1):
        if parent_pos[k] >= 0:
            root[k] = root[parent_pos[k]]
    return BlockCholeskySymbolic(
        num_nodes=num_nodes,
        block_size=b,
        free=free,
        num_fronts=ns,
        front_sizes=sizes,
        factor_nnz=int(nnz),
        _s_dofs=s_dofs,
        _u_dofs=u_dofs,
        _children=kids,
        _parent=parent_pos,
        _entry_src=entry_src,
        _entry_dst=entry_dst,
        _entry_lower=entry_lower,
        _child_ud=child_ud,
        _direct=direct,
        _node_front=nf_full,
        _front_root=root,
        _num_edges=e_all,
        _edge_keep=edge_keep,
    )


# ----------------------------------------------------------------------------------------------
# Numeric factorisation and solve (torch, any device, differentiable).
# ----------------------------------------------------------------------------------------------


@dataclass
class BlockCholeskyFactor:
    """Numeric supernodal Cholesky factor ``P A P^T = L L^T`` of a block-sparse matrix.

    Attributes:
        symbolic: the structure it was computed with.
        ok: (N,) bool, False for nodes in an elimination tree where a pivot block was not
            positive definite; the solution there is meaningless and callers must reject it.
    """

    symbolic: BlockCholeskySymbolic
    ok: Tensor
    _L_ss: list = field(repr=False)
    _L_us: list = field(repr=False)
    schedule: Schedule = Schedule.FRONT

    def solve(self, rhs: Tensor) -> Tensor:
        """Solve ``A x = rhs`` with fixed nodes' solution zero.

        Args:
            rhs: (N, b) right-hand side.

        Returns:
            (N, b) solution.
        """
        sym = self.symbolic
        check_shape(rhs, f"{sym.num_nodes} {sym.block_size}", "rhs")
        if self.schedule is Schedule.LEVEL:
            return self._solve_levels(rhs)
        idx = sym.tensors(rhs.device)
        y = rhs.reshape(-1).clone()
        z: list[Tensor] = []
        for k in range(sym.num_fronts):  # forward substitution, children first
            zs = torch.linalg.solve_triangular(self._L_ss[k], y[idx["s"][k]][:, None], upper=False)
            z.append(zs)
            if idx["u"][k].numel():
                y.index_add_(0, idx["u"][k], (self._L_us[k] @ zs)[:, 0], alpha=-1)
        x = torch.zeros_like(y)
        for k in reversed(range(sym.num_fronts)):  # back substitution, parents first
            v = z[k]
            if idx["u"][k].numel():
                v = torch.addmm(v, self._L_us[k].transpose(0, 1), x[idx["u"][k]][:, None], alpha=-1)
            xs = torch.linalg.solve_triangular(self._L_ss[k].transpose(0, 1), v, upper=True)
            x.index_copy_(0, idx["s"][k], xs[:, 0])
        return x.reshape(rhs.shape)

    def _solve_levels(self, rhs: Tensor) -> Tensor:
        """Forward and back substitution one group of fronts at a time (batched over the group).

        The right-hand side gets two spare entries: one that stays zero (what padding reads)
        and one that collects what padding writes, so padding never touches real entries.
        """
        sym = self.symbolic
        lv = sym.level_tensors(rhs.device)["groups"]
        y = torch.cat([rhs.reshape(-1), rhs.new_zeros(2)])
        z: list[Tensor] = []
        for h, (L, Lu) in enumerate(zip(self._L_ss, self._L_us)):  # lowest level first
            zs = torch.linalg.solve_triangular(L, y[lv[h]["s_read"]].view(L.shape[0], -1, 1), upper=False)
            z.append(zs)
            if Lu.shape[1]:
                y.index_add_(0, lv[h]["u_write"], torch.bmm(Lu, zs).reshape(-1), alpha=-1)
        x = torch.zeros_like(y)
        for h in reversed(range(len(z))):  # highest level first
            L, Lu, v = self._L_ss[h], self._L_us[h], z[h]
            if Lu.shape[1]:
                v = torch.baddbmm(v, Lu.transpose(1, 2), x[lv[h]["u_read"]].view(L.shape[0], -1, 1), alpha=-1)
            xs = torch.linalg.solve_triangular(L.transpose(1, 2), v, upper=True)
            x.index_copy_(0, lv[h]["s_write"], xs.reshape(-1))
        return x[: rhs.numel()].reshape(rhs.shape)

    def fronts(self) -> list[tuple[Tensor, Tensor]]:
        """The factor's blocks ``(L_SS, L_US)`` of every front, in elimination order (inspection, tests).

        Returns:
            Per front, its (b|S|, b|S|) lower-triangular pivot factor and (b|U|, b|S|) coupling.
        """
        if self.schedule is Schedule.FRONT:
            return list(zip(self._L_ss, self._L_us))
        sym = self.symbolic
        plan = sym._plan()
        b = sym.block_size
        out = []
        for k, (ns, nu) in enumerate(sym.front_sizes):
            h, p = plan["group"][k], plan["slot"][k]
            out.append((self._L_ss[h][p, : ns * b, : ns * b], self._L_us[h][p, : nu * b, : ns * b]))
        return out


def _tree_ok(infos: list[Tensor], idx: dict, sym: BlockCholeskySymbolic) -> Tensor:
    """(N,) bool: the node's elimination tree factored without a failed pivot (fixed nodes True).

    Args:
        infos: ``cholesky_ex`` infos of all fronts, () or (P,) each, in the order of
            ``idx["front_root"]`` (elimination order, or group by group).
        idx: the schedule's index tensors.
    """
    if not infos:
        return torch.ones(sym.num_nodes, dtype=torch.bool, device=idx["node_root"].device)
    info = torch.cat([i.reshape(-1) for i in infos])
    bad = torch.zeros(sym.num_fronts + 1, dtype=torch.int32, device=info.device)
    bad.index_add_(0, idx["front_root"], (info != 0).to(torch.int32))
    return bad[idx["node_root"]] == 0


def block_cholesky(
    matrix: BlockSparseMatrix, symbolic: BlockCholeskySymbolic, schedule: Schedule | str = Schedule.FRONT
) -> BlockCholeskyFactor:
    """Factor a block-sparse SPD matrix with a precomputed symbolic structure (multifrontal).

    Each supernode assembles a dense front from the original blocks it owns and the update
    matrices of its children, factors its pivot block with ``torch.linalg.cholesky_ex`` and
    passes the Schur complement to its parent. Failure (a non-positive pivot) is reported in
    :attr:`BlockCholeskyFactor.ok` instead of raising.

    Args:
        matrix: the system; same pattern as the one ``symbolic`` was built from.
        symbolic: from :func:`analyze`.
        schedule: ``"front"`` (one front at a time) or ``"level"`` (batched calls per level of
            the elimination tree and size class, :class:`Schedule`); the factor's
            :meth:`~BlockCholeskyFactor.solve` follows the same schedule.

    Returns:
        The factor.
    """
    sym = symbolic
    schedule = parse_choice(Schedule, schedule, "schedule")
    if matrix.num_nodes != sym.num_nodes or matrix.block_size != sym.block_size:
        raise ShapeError(
            f"matrix: expected {sym.num_nodes} nodes of {sym.block_size}x{sym.block_size} blocks "
            f"like the symbolic analysis, got {matrix.num_nodes} of {matrix.block_size}"
        )
    if matrix.rows.shape[0] != sym._num_edges:
        raise ShapeError(f"matrix: expected {sym._num_edges} off-diagonal blocks like the analysis, got {matrix.rows.shape[0]}")
    if schedule is Schedule.LEVEL:
        return _factor_levels(matrix, sym)
    dev = matrix.diag.device
    idx = sym.tensors(dev)
    b = sym.block_size
    values = torch.cat([matrix.diag.reshape(-1), matrix.off.reshape(-1)])
    # Without autograd, fronts are assembled in one reused workspace (no fresh pages per front)
    # and only their lower triangles are filled and updated: Cholesky, the off-diagonal solve
    # and the parents read nothing else. With autograd, whole fronts are built out of place so
    # that every entry (both triangles) receives its gradient.
    grad = torch.is_grad_enabled() and (matrix.diag.requires_grad or matrix.off.requires_grad)
    child = sym.child_maps(dev) if grad else idx["child"]
    if grad:
        values = values[idx["src_all"]]  # one gather of every front's entries, sliced below
        vb, dsts = idx["src_bounds"], idx["dst"]
    else:
        values = values[idx["lo_all"]]
        vb, dsts = idx["lo_bounds"], idx["dst_lo"]
        # two buffers: a front whose update lands on one diagonal block of the next front
        # (``_direct``, the usual case in band orders) writes it there in place
        size = max([(s + u) * b for s, u in sym.front_sizes], default=0) ** 2
        buffers = (values.new_empty(size), values.new_empty(size))
    L_ss: list[Tensor] = []
    L_us: list[Tensor] = []
    infos: list[Tensor] = []
    updates: list[Tensor | None] = [None] * sym.num_fronts
    started = False
    for k in range(sym.num_fronts):
        ns, nu = sym.front_sizes[k]
        n = (ns + nu) * b
        if grad:
            F = values.new_zeros(n * n)
        elif started:
            F = buffers[k % 2][:n * n]  # already holds the previous front's update
        else:
            F = buffers[k % 2][:n * n].zero_()
        F.index_add_(0, dsts[k], values[vb[k]:vb[k + 1]])
        for c, dst in zip(sym._children[k], child[k]):
            if updates[c] is not None:
                F.index_add_(0, dst, updates[c].reshape(-1))
                updates[c] = None
        F = F.reshape(n, n)
        m = ns * b
        L, info = torch.linalg.cholesky_ex(F[:m, :m])
        L_ss.append(L)
        infos.append(info)
        started = False
        if nu:
            Lu = torch.linalg.solve_triangular(L.transpose(0, 1), F[m:, :m], upper=True, left=False)  # X L^T = F_US
            L_us.append(Lu)
            if grad:
                updates[k] = torch.addmm(F[m:, m:], Lu, Lu.transpose(0, 1), alpha=-1)
                continue
            p0 = sym._direct[k]
            if p0 >= 0:
                n_p = sum(sym.front_sizes[k + 1]) * b
                upd = buffers[(k + 1) % 2][:n_p * n_p].zero_().view(n_p, n_p)[p0:p0 + nu * b, p0:p0 + nu * b]
                upd.copy_(F[m:, m:])
                started = True
            else:
                upd = F[m:, m:].clone()
                updates[k] = upd
            # Schur complement, lower triangle by row bands: 3/4 of the full product's flops
            h = nu * b // 2
            upd[:h, :h].addmm_(Lu[:h], Lu[:h].transpose(0, 1), alpha=-1)
            upd[h:].addmm_(Lu[h:], Lu.transpose(0, 1), alpha=-1)
        else:
            L_us.append(F.new_zeros(0, m))
    # A failed pivot (not positive definite) spoils its whole elimination tree: upwards through
    # the Schur complements, downwards through back substitution. Garbage stays inside that
    # tree because trees share nothing. Decided on the device: no synchronisation.
    ok = _tree_ok(infos, idx, sym)
    return BlockCholeskyFactor(sym, ok, L_ss, L_us)


def _factor_levels(matrix: BlockSparseMatrix, sym: BlockCholeskySymbolic) -> BlockCholeskyFactor:
    """:func:`block_cholesky` one level of the elimination tree at a time (``Schedule.LEVEL``).

    The P fronts of one group (a level's fronts of one size class, ``BlockCholeskySymbolic._plan``)
    are assembled into one (P, n, n) padded workspace by two scatters (original entries,
    children's updates from the pool), then factored by one batched Cholesky, one batched
    triangular solve and one batched Schur complement, which is written to the group's part
    of the update pool. Whole fronts (both triangles) are built, so autograd reaches every entry.
    """
    plan = sym._plan()
    lv = sym.level_tensors(matrix.diag.device)
    values = torch.cat([matrix.diag.reshape(-1), matrix.off.reshape(-1)])
    # every pool entry a parent reads was written by its child before: no need to clear it
    pool = values.new_empty(plan["pool_off"][-1] if plan["fronts"] else 0)
    sizes = [ks.size * (ms + mu) ** 2 for ks, ms, mu in zip(plan["fronts"], plan["ms"], plan["mu"])]
    # Without autograd every level is assembled in one reused workspace (no fresh pages per
    # level) and its update is written straight into the pool.
    grad = torch.is_grad_enabled() and (matrix.diag.requires_grad or matrix.off.requires_grad)
    work = None if grad else values.new_empty(max(sizes, default=0))
    L_ss: list[Tensor] = []
    L_us: list[Tensor] = []
    infos: list[Tensor] = []
    for h, ks in enumerate(plan["fronts"]):
        P, ms, mu = ks.size, plan["ms"][h], plan["mu"][h]
        n = ms + mu
        idx = lv["groups"][h]
        W = values.new_zeros(sizes[h]) if grad else work[: sizes[h]].zero_()
        W.index_fill_(0, idx["pad"], 1.0)  # identity pivots of the padding
        W.index_add_(0, idx["dst"], values[idx["src"]])
        if idx["child_src"].numel():
            W.index_add_(0, idx["child_dst"], pool[idx["child_src"]])
        W = W.view(P, n, n)
        L, info = torch.linalg.cholesky_ex(W[:, :ms, :ms])
        L_ss.append(L)
        infos.append(info)
        if mu:
            Lu = torch.linalg.solve_triangular(L.transpose(1, 2), W[:, ms:, :ms], upper=True, left=False)  # X L^T = F_US
            L_us.append(Lu)
            a = plan["pool_off"][h]
            if grad:
                pool[a : a + P * mu * mu] = torch.baddbmm(W[:, ms:, ms:], Lu, Lu.transpose(1, 2), alpha=-1).reshape(-1)
            else:
                torch.baddbmm(W[:, ms:, ms:], Lu, Lu.transpose(1, 2), alpha=-1, out=pool[a : a + P * mu * mu].view(P, mu, mu))
        else:
            L_us.append(W.new_zeros(P, 0, ms))
    ok = _tree_ok(infos, lv, sym)
    return BlockCholeskyFactor(sym, ok, L_ss, L_us, Schedule.LEVEL)


# ----------------------------------------------------------------------------------------------
# Dense and iterative solvers, and the front door.
# ----------------------------------------------------------------------------------------------


def _dense_solve(matrix: BlockSparseMatrix, rhs: Tensor, free: Tensor) -> tuple[Tensor, Tensor]:
    b = matrix.block_size
    A = matrix.to_dense()
    dof = free.repeat_interleave(b)
    A = A[dof][:, dof]
    L, info = torch.linalg.cholesky_ex(A)
    ok_all = info == 0
    L = torch.where(ok_all, L, torch.eye(L.shape[0], dtype=L.dtype, device=L.device))
    xs = torch.cholesky_solve(rhs.reshape(-1)[dof][:, None], L)[:, 0]
    x = rhs.new_zeros(rhs.numel()).index_copy(0, torch.nonzero(dof)[:, 0], xs)
    ok = ok_all.expand(matrix.num_nodes).clone()
    return x.reshape(rhs.shape), ok


def pcg_block_jacobi(
    matrix: BlockSparseMatrix,
    rhs: Tensor,
    fixed: Tensor | None = None,
    tol: float = 1e-10,
    max_iter: int = 2000,
) -> tuple[Tensor, Tensor, int]:
    """Solve ``A x = rhs`` by conjugate gradients with a block-Jacobi preconditioner.

    Matrix-free (one block mat-vec per iteration), so it suits accelerators and very large
    systems; chain-like graphs need many iterations (they are poorly conditioned).

    Args:
        matrix: SPD system.
        rhs: (N, b) right-hand side.
        fixed: optional (N,) bool mask of nodes whose solution is zero.
        tol: stop when ``||r|| <= tol * ||rhs||``.
        max_iter: iteration cap.

    Returns:
        ``(x (N, b), converged () bool, iterations)``.
    """
    check_shape(rhs, f"{matrix.num_nodes} {matrix.block_size}", "rhs")
    free = torch.ones(matrix.num_nodes, dtype=torch.bool, device=rhs.device) if fixed is None else ~fixed
    mask = free[:, None].to(rhs.dtype)
    eye = torch.eye(matrix.block_size, dtype=rhs.dtype, device=rhs.device)
    # Fixed nodes get an identity diagonal block and a zero rhs; masking keeps them at zero.
    Dinv = torch.linalg.inv(torch.where(free[:, None, None], matrix.diag, eye))

    def A(v: Tensor) -> Tensor:
        return matrix.matvec(v * mask) * mask

    x = torch.zeros_like(rhs)
    r = rhs * mask
    z = (Dinv @ r[..., None])[..., 0]
    p = z
    rz = (r * z).sum()
    stop = tol * r.norm()
    it = 0
    for it in range(1, max_iter + 1):
        Ap = A(p)
        alpha = rz / (p * Ap).sum()
        x = x + alpha * p
        r = r - alpha * Ap
        if bool(r.norm() <= stop):
            break
        z = (Dinv @ r[..., None])[..., 0]
        rz_new = (r * z).sum()
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, r.norm() <= stop, it


def solve_block_sparse(
    matrix: BlockSparseMatrix,
    rhs: Tensor,
    fixed: Tensor | None = None,
    method: SolverMethod | str = SolverMethod.AUTO,
    symbolic: BlockCholeskySymbolic | None = None,
    pcg_tol: float = 1e-10,
    pcg_max_iter: int = 2000,
    schedule: Schedule | str = Schedule.FRONT,
) -> tuple[Tensor, Tensor]:
    """Solve the symmetric block system ``A x = rhs`` with fixed nodes held at zero.

    ``AUTO`` picks the supernodal Cholesky on every device: it is exact, differentiable and
    its cost follows the fill of the factor rather than ``(bN)^3`` (see
    ``scripts/bench_fastgo.py`` for the dense / sparse / PCG comparison).

    Args:
        matrix: SPD (on the free nodes) block-sparse system.
        rhs: (N, b) right-hand side.
        fixed: optional (N,) bool mask; those nodes' rows/columns are removed, their x is 0.
        method: a :class:`SolverMethod` or its name.
        symbolic: a reusable analysis of this pattern (Cholesky only); computed when missing.
        pcg_tol: relative residual tolerance of ``PCG``.
        pcg_max_iter: iteration cap of ``PCG``.
        schedule: how the Cholesky walks the elimination tree (:class:`Schedule`).

    Returns:
        ``(x (N, b), ok (N,) bool)``; ``ok`` is False where the factorisation failed (not
        positive definite) or PCG did not converge.
    """
    check_shape(rhs, f"{matrix.num_nodes} {matrix.block_size}", "rhs")
    if fixed is not None:
        check_shape(fixed, f"{matrix.num_nodes}", "fixed")
        if fixed.dtype != torch.bool:
            raise DTypeError(f"fixed: expected a bool mask, got {fixed.dtype}")
    method = SolverMethod.parse(method)
    if method in (SolverMethod.AUTO, SolverMethod.CHOLESKY):
        if symbolic is None:
            symbolic = analyze(matrix.num_nodes, matrix.rows, matrix.cols, fixed, matrix.block_size)
        factor = block_cholesky(matrix, symbolic, schedule)
        return factor.solve(rhs), factor.ok
    free = torch.ones(matrix.num_nodes, dtype=torch.bool, device=rhs.device) if fixed is None else ~fixed
    if method is SolverMethod.DENSE:
        return _dense_solve(matrix, rhs, free)
    x, conv, _ = pcg_block_jacobi(matrix, rhs, ~free, pcg_tol, pcg_max_iter)
    return x, conv.expand(matrix.num_nodes).clone()
