"""Per-pair second-order statistics of correspondences (FastGO, paper §III-B).

For the correspondences ``(p_i^k, p_j^k)`` of one frame pair, with optional weights ``w_k``,
FastGO keeps 28 numbers: ``n = sum w``, ``s_i = sum w p_i``, ``s_j = sum w p_j`` and the
moments ``S_ii = sum w p_i p_i^T`` (6 distinct entries), ``S_ij = sum w p_i p_j^T`` (9) and
``S_jj = sum w p_j p_j^T`` (6). Every Gauss-Newton quantity of the pair is linear in them
(FastGO Eqs. (18)-(20)), so one linearisation costs O(#pairs) instead of O(#correspondences).

:class:`PairStats` holds these for M pairs as tensors, plus the unweighted correspondence
count used to flag degenerate pairs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..errors import ShapeError, check_float, check_shape

__all__ = ["PairStats"]

_FIELDS = ("n", "count", "s_i", "s_j", "S_ii", "S_ij", "S_jj")
# Upper-triangle indices of a symmetric 3x3 matrix (the 6 distinct entries).
_TRIU = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass(frozen=True)
class PairStats:
    """Second-order statistics of M correspondence sets, in the frames of their two keyframes.

    Attributes:
        n: (M,) sum of weights (the number of correspondences when unweighted).
        count: (M,) int64 number of correspondences (unweighted; for degeneracy checks).
        s_i: (M, 3) ``sum w p_i``, metres (points in frame i).
        s_j: (M, 3) ``sum w p_j``, metres (points in frame j).
        S_ii: (M, 3, 3) ``sum w p_i p_i^T``, square metres.
        S_ij: (M, 3, 3) ``sum w p_i p_j^T``.
        S_jj: (M, 3, 3) ``sum w p_j p_j^T``.
    """

    n: Tensor
    count: Tensor
    s_i: Tensor
    s_j: Tensor
    S_ii: Tensor
    S_ij: Tensor
    S_jj: Tensor

    def __post_init__(self) -> None:
        d: dict[str, int] = {}
        check_shape(self.n, "M", "n", d)
        check_shape(self.count, "M", "count", d)
        check_shape(self.s_i, "M 3", "s_i", d)
        check_shape(self.s_j, "M 3", "s_j", d)
        check_shape(self.S_ii, "M 3 3", "S_ii", d)
        check_shape(self.S_ij, "M 3 3", "S_ij", d)
        check_shape(self.S_jj, "M 3 3", "S_jj", d)
        check_float(self.n, "n")
        for f in ("s_i", "s_j", "S_ii", "S_ij", "S_jj"):
            if getattr(self, f).dtype != self.n.dtype:
                raise ShapeError(f"{f}: expected dtype {self.n.dtype} like n, got {getattr(self, f).dtype}")
        if self.count.dtype != torch.int64:
            raise ShapeError(f"count: expected int64, got {self.count.dtype}")

    # ------------------------------------------------------------------ constructors
    @staticmethod
    def empty(num_pairs: int = 0, dtype: torch.dtype = torch.float64, device=None) -> "PairStats":
        """Return ``num_pairs`` pairs without correspondences (all zeros)."""
        z = lambda *s: torch.zeros(num_pairs, *s, dtype=dtype, device=device)  # noqa: E731
        return PairStats(z(), torch.zeros(num_pairs, dtype=torch.int64, device=device), z(3), z(3), z(3, 3), z(3, 3), z(3, 3))

    @staticmethod
    def from_correspondences(
        points_i: Sequence[Tensor] | Tensor,
        points_j: Sequence[Tensor] | Tensor,
        weights: Sequence[Tensor] | Tensor | None = None,
    ) -> "PairStats":
        """Summarise ragged correspondence sets in one call.

        The sets are concatenated and reduced by segment sums (``index_add``), so there is no
        per-pair arithmetic in Python. Differentiable with respect to points and weights.

        Args:
            points_i: M tensors (K_m, 3) of points in frame i (metres), or one (M, K, 3) tensor.
            points_j: M tensors (K_m, 3) of the matching points in frame j.
            weights: optional M tensors (K_m,) of non-negative weights (or (M, K)).

        Returns:
            Statistics of the M pairs. Non-finite points make that pair's statistics
            non-finite; :func:`torchslam.fastgo.pair_status` reports and the optimiser
            excludes such pairs.
        """
        if isinstance(points_i, Tensor):
            check_shape(points_i, "M K 3", "points_i")
            return PairStats.from_padded(points_i, points_j, weights=weights)
        if len(points_i) != len(points_j):
            raise ShapeError(f"points_j: expected {len(points_i)} tensors like points_i, got {len(points_j)}")
        if weights is not None and len(weights) != len(points_i):
            raise ShapeError(f"weights: expected {len(points_i)} tensors like points_i, got {len(weights)}")
        if len(points_i) == 0:
            raise ShapeError("points_i: expected at least one correspondence set, got none")
        for m, (a, b) in enumerate(zip(points_i, points_j)):
            d: dict[str, int] = {}
            check_shape(a, "K 3", f"points_i[{m}]", d)
            check_shape(b, "K 3", f"points_j[{m}]", d)
            if weights is not None:
                check_shape(weights[m], "K", f"weights[{m}]", d)
        pi = torch.cat(list(points_i))
        pj = torch.cat(list(points_j))
        check_float(pi, "points_i")
        pj = pj.to(pi.dtype)
        lengths = torch.tensor([a.shape[0] for a in points_i], dtype=torch.int64, device=pi.device)
        seg = torch.repeat_interleave(torch.arange(len(points_i), device=pi.device), lengths)
        w = None if weights is None else torch.cat(list(weights)).to(pi.dtype)
        return PairStats._reduce(pi, pj, w, seg, len(points_i), lengths)

    @staticmethod
    def from_padded(
        points_i: Tensor,
        points_j: Tensor,
        mask: Tensor | None = None,
        weights: Tensor | None = None,
    ) -> "PairStats":
        """Summarise M padded correspondence sets.

        Args:
            points_i: (M, K, 3) points in frame i, metres.
            points_j: (M, K, 3) matching points in frame j.
            mask: optional (M, K) bool, True for real correspondences (padding is ignored
                even when it holds NaN).
            weights: optional (M, K) non-negative weights.

        Returns:
            Statistics of the M pairs.
        """
        d: dict[str, int] = {}
        check_shape(points_i, "M K 3", "points_i", d)
        check_shape(points_j, "M K 3", "points_j", d)
        check_float(points_i, "points_i")
        w = torch.ones(points_i.shape[:2], dtype=points_i.dtype, device=points_i.device)
        if weights is not None:
            check_shape(weights, "M K", "weights", d)
            w = weights.to(points_i.dtype)
        count = torch.full((points_i.shape[0],), points_i.shape[1], dtype=torch.int64, device=points_i.device)
        if mask is not None:
            check_shape(mask, "M K", "mask", d)
            if mask.dtype != torch.bool:
                raise ShapeError(f"mask: expected a bool tensor, got {mask.dtype}")
            w = torch.where(mask, w, torch.zeros_like(w))
            keep = mask[..., None]
            points_i = torch.where(keep, points_i, torch.zeros_like(points_i))
            points_j = torch.where(keep, points_j.to(points_i.dtype), torch.zeros_like(points_i))
            count = mask.sum(-1)
        pj = points_j.to(points_i.dtype)
        wi = w[..., None] * points_i
        return PairStats(
            n=w.sum(-1),
            count=count,
            s_i=wi.sum(-2),
            s_j=(w[..., None] * pj).sum(-2),
            S_ii=wi.transpose(-1, -2) @ points_i,
            S_ij=wi.transpose(-1, -2) @ pj,
            S_jj=(w[..., None] * pj).transpose(-1, -2) @ pj,
        )

    @staticmethod
    def from_gram(G: Tensor, count: Tensor) -> "PairStats":
        """Statistics of M pairs from the Gram matrices of their weighted correspondence rows.

        Args:
            G: (M, 7, 7) ``sum_k w_k x_k x_k^T`` over each pair's correspondences, with
                ``x = [1, p_i, p_j]`` (points in metres): ``n = G[0, 0]``, ``s_i = G[0, 1:4]``,
                ``s_j = G[0, 4:7]`` and ``S_ii``, ``S_ij``, ``S_jj`` its 3 x 3 blocks. One matrix
                product of the rows gives every sum at once.
            count: (M,) int64 correspondences of each pair (unweighted).

        Returns:
            Statistics of the M pairs.
        """
        check_shape(G, "M 7 7", "G")
        check_float(G, "G")
        return PairStats(
            n=G[:, 0, 0], count=count, s_i=G[:, 0, 1:4], s_j=G[:, 0, 4:7],
            S_ii=G[:, 1:4, 1:4], S_ij=G[:, 1:4, 4:7], S_jj=G[:, 4:7, 4:7],
        )

    @staticmethod
    def _reduce(pi: Tensor, pj: Tensor, w: Tensor | None, seg: Tensor, M: int, lengths: Tensor) -> "PairStats":
        # One (K, 34) row per correspondence (weight, first moments, the three outer products),
        # reduced by one segment sum; chunked so memory stays bounded for millions of points.
        acc = pi.new_zeros(M, 34)
        chunk = 1 << 18
        for start in range(0, pi.shape[0], chunk):
            a, b = pi[start:start + chunk], pj[start:start + chunk]
            wk = None if w is None else w[start:start + chunk]
            wa = a if wk is None else wk[:, None] * a
            wb = b if wk is None else wk[:, None] * b
            n_src = torch.ones_like(a[:, :1]) if wk is None else wk[:, None]
            rows = torch.cat(
                [
                    n_src, wa, wb,
                    (wa[:, :, None] * a[:, None, :]).reshape(-1, 9),
                    (wa[:, :, None] * b[:, None, :]).reshape(-1, 9),
                    (wb[:, :, None] * b[:, None, :]).reshape(-1, 9),
                ],
                dim=1,
            )
            acc = acc.index_add(0, seg[start:start + chunk], rows)
        return PairStats(
            n=acc[:, 0],
            count=lengths,
            s_i=acc[:, 1:4],
            s_j=acc[:, 4:7],
            S_ii=acc[:, 7:16].reshape(M, 3, 3),
            S_ij=acc[:, 16:25].reshape(M, 3, 3),
            S_jj=acc[:, 25:34].reshape(M, 3, 3),
        )

    # ------------------------------------------------------------------ algebra
    def __len__(self) -> int:
        return self.n.shape[0]

    def __getitem__(self, index) -> "PairStats":
        """Select pairs (int, slice, bool mask or int64 index tensor); always keeps the M axis."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return PairStats(*(getattr(self, f)[index] for f in _FIELDS))

    def merge(self, other: "PairStats") -> "PairStats":
        """Return the statistics of the union of both correspondence sets, pair by pair.

        Use it when a pair gains correspondences later: sums simply add.

        Args:
            other: statistics of the same M pairs (same orientation i -> j).
        """
        if len(other) != len(self):
            raise ShapeError(f"other: expected {len(self)} pairs like self, got {len(other)}")
        return PairStats(*(getattr(self, f) + getattr(other, f).to(getattr(self, f).dtype) for f in _FIELDS))

    @staticmethod
    def cat(stats: Sequence["PairStats"]) -> "PairStats":
        """Concatenate statistics along the pair axis."""
        if len(stats) == 0:
            raise ShapeError("stats: expected at least one PairStats, got none")
        return PairStats(*(torch.cat([getattr(s, f) for s in stats]) for f in _FIELDS))

    def swapped(self) -> "PairStats":
        """Return the statistics of the reversed pairs (j, i)."""
        return PairStats(self.n, self.count, self.s_j, self.s_i, self.S_jj, self.S_ij.transpose(-1, -2), self.S_ii)

    def weighted(self, weights: Tensor) -> "PairStats":
        """Return the statistics with every correspondence of pair m weighted by ``weights[m]``.

        Args:
            weights: (M,) non-negative pair weights (may require grad).
        """
        check_shape(weights, f"{len(self)}", "weights")
        w = weights.to(self.n.dtype)
        return PairStats(
            self.n * w, self.count, self.s_i * w[:, None], self.s_j * w[:, None],
            self.S_ii * w[:, None, None], self.S_ij * w[:, None, None], self.S_jj * w[:, None, None],
        )

    def to(self, *args, **kwargs) -> "PairStats":
        """Move/cast like ``Tensor.to`` (``count`` keeps int64)."""
        out = {f: getattr(self, f).to(*args, **kwargs) for f in _FIELDS if f != "count"}
        dev = out["n"].device
        return PairStats(count=self.count.to(dev), **out)

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the statistics."""
        return self.n.dtype

    @property
    def device(self) -> torch.device:
        """Device of the statistics."""
        return self.n.device

    # ------------------------------------------------------------------ derived quantities
    def centred(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Return weighted means and centred moments.

        Returns:
            ``(mean_i (M,3), mean_j (M,3), C_ii, C_ij, C_jj (M,3,3))`` with
            ``C_ab = S_ab - n mean_a mean_b^T``. Pairs with ``n = 0`` give zeros.
        """
        n = self.n
        inv = torch.where(n > 0, 1 / torch.where(n > 0, n, torch.ones_like(n)), torch.zeros_like(n))
        mi = self.s_i * inv[:, None]
        mj = self.s_j * inv[:, None]
        C_ii = self.S_ii - self.s_i[:, :, None] * mi[:, None, :]
        C_ij = self.S_ij - self.s_i[:, :, None] * mj[:, None, :]
        C_jj = self.S_jj - self.s_j[:, :, None] * mj[:, None, :]
        return mi, mj, C_ii, C_ij, C_jj

    def as_vector(self) -> Tensor:
        """Pack the 28 statistics of each pair into an (M, 28) tensor.

        Order: ``n, s_i (3), s_j (3), S_ii upper triangle (6), S_ij (9), S_jj upper triangle (6)``.
        """
        r = torch.tensor([a for a, _ in _TRIU], device=self.device)
        c = torch.tensor([b for _, b in _TRIU], device=self.device)
        return torch.cat(
            [self.n[:, None], self.s_i, self.s_j, self.S_ii[:, r, c], self.S_ij.reshape(-1, 9), self.S_jj[:, r, c]], dim=1
        )

    @staticmethod
    def from_vector(vector: Tensor, count: Tensor | None = None) -> "PairStats":
        """Inverse of :meth:`as_vector`.

        Args:
            vector: (M, 28) packed statistics.
            count: optional (M,) int64 correspondence counts (default: ``round(n)``).
        """
        check_shape(vector, "M 28", "vector")
        check_float(vector, "vector")
        M = vector.shape[0]

        def sym(v: Tensor) -> Tensor:
            S = vector.new_zeros(M, 3, 3)
            for k, (a, b) in enumerate(_TRIU):
                S[:, a, b] = v[:, k]
                S[:, b, a] = v[:, k]
            return S

        if count is None:
            count = torch.nan_to_num(vector[:, 0]).round().to(torch.int64)
        return PairStats(
            n=vector[:, 0], count=count, s_i=vector[:, 1:4], s_j=vector[:, 4:7],
            S_ii=sym(vector[:, 7:13]), S_ij=vector[:, 13:22].reshape(M, 3, 3), S_jj=sym(vector[:, 22:28]),
        )

    def state_dict(self) -> dict[str, Tensor]:
        """Return the fields as a dict of tensors (``torch.save`` it; see :meth:`from_state_dict`)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @staticmethod
    def from_state_dict(state: dict[str, Tensor]) -> "PairStats":
        """Rebuild statistics from :meth:`state_dict` output; missing keys are named."""
        missing = [f for f in _FIELDS if f not in state]
        if missing:
            raise ShapeError(f"state: missing PairStats fields {missing}")
        return PairStats(**{f: state[f] for f in _FIELDS})
