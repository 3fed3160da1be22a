"""MILD: loop-closure candidates by multi-index hashing of binary descriptors.

GC-SLAM detects loops with MILD (FastGO paper §IV-C, its ref. [3]: Han and Fang, "MILD:
Multi-index hashing for appearance based loop closure detection", ICME 2017). Instead of a
trained bag-of-words vocabulary, image similarity is measured by matching descriptors directly,
and multi-index hashing (Norouzi et al.) makes that fast: every 256-bit descriptor is cut into
``m`` disjoint substrings of ``256 / m`` bits, and substring ``t`` of every stored descriptor
indexes hash table ``t``. A query descriptor probes the ``m`` tables with its own substrings;
every stored descriptor that agrees with it exactly on at least one substring is a candidate,
and a candidate becomes a match when its full Hamming distance is within ``max_distance``.

NI-SLAM's relocalisation (NI-SLAM §9.1) retrieves keyframes with DBoW2 and a vocabulary
pretrained on another dataset; torchslam offers this vocabulary-free database for that step too.

By the pigeonhole principle two descriptors less than ``m`` bits apart agree on at least one
of ``m`` substrings, so every match closer than ``m`` bits (16 by default) is found; farther
matches up to ``max_distance`` are found with a probability that falls with the distance (the
efficiency/recall trade-off MILD analyses).

Tensor layout. A hash table is a pair of (n,) arrays sorted by ``(substring value, descriptor
id)``, and the m tables are stacked as rows of (m, n) arrays so they are probed together. A
bucket is found by ``searchsorted`` in a small run and through CSR bucket offsets in a large one.
Tables are kept as a few sorted *levels* of geometrically decreasing size (an LSM tree): adding
a keyframe creates a small level and merges levels of similar size with a linear
``searchsorted``-and-scatter merge, so insertion costs amortised O(log N) per descriptor and a
query probes O(log N) levels. No Python loop runs over descriptors; candidate pairs are expanded
and checked in cache-sized chunks.

Scoring (torchslam's choice, after MILD's distance-weighted vote). Each query descriptor q
votes at most once per keyframe k, with the weight of its closest matched descriptor there:
``w(d) = exp(-(d / sigma)^2)``. The score normalises the votes by both feature counts,

    s_k = sum_q max_{j in k, d(q, j) <= max_distance} w(d(q, j)) / sqrt(|Q| |K_k|),

a cosine-style normalisation: a keyframe compared with its own descriptors scores ~1, an
unrelated place ~0, and keyframes with many features are not favoured just for their size.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from ..devices import numpy_viewable
from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, DTypeError, Limit, TorchSlamError, check_limits, check_shape
from ..features.matching import hamming_distance_indexed, pack_descriptors

__all__ = ["MILDConfig", "MILDDatabase", "MILDError", "substring_keys"]

logger = logging.getLogger(__name__)

_DESCRIPTOR_BITS = 256
# Candidate pairs handled at once on a CPU (see MILDDatabase._hit_chunks).
_HIT_CHUNK = 1 << 15


class MILDError(TorchSlamError, ValueError):
    """A MILD database call is inconsistent with the database (repeated keyframe id, other device)."""


@dataclass(frozen=True)
class MILDConfig:
    """Settings of the MILD loop detector.

    Attributes:
        tables: number of hash tables m (substrings per descriptor); GC-SLAM: 16.
        bits: bits per substring; ``tables * bits`` must be 256 and ``bits`` a multiple of 8.
        max_distance: largest Hamming distance (bits) at which a candidate counts as a match.
        sigma: width in bits of the vote weight ``exp(-(d / sigma)^2)``.
        top_k: number of loop candidates returned by ``query``; GC-SLAM: 5.
        exclude_recent: the most recently added keyframes that ``query`` never returns
            (temporal neighbours, already linked by tracking).
        min_score: candidates must score above this to be returned.
    """

    tables: int = 16
    bits: int = 16
    max_distance: int = 50
    sigma: float = 25.0
    top_k: int = 5
    exclude_recent: int = 1
    min_score: float = 0.0

    LIMITS: ClassVar[dict[str, Limit]] = {
        "tables": AT_LEAST_1, "bits": Limit(ge=8, le=32), "max_distance": Limit(ge=0, le=256), "sigma": POSITIVE,
        "top_k": AT_LEAST_1, "exclude_recent": NON_NEGATIVE, "min_score": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        check_limits(self)
        if self.tables < 1 or self.bits < 8 or self.bits % 8 or self.tables * self.bits != _DESCRIPTOR_BITS:
            raise ConfigError(
                f"tables/bits: need tables * bits == 256 with bits a multiple of 8, got {self.tables} x {self.bits}"
            )


def substring_keys(descriptors: Tensor, tables: int = 16) -> Tensor:
    """Cut each 256-bit descriptor into ``tables`` equal substrings and read each as an integer.

    Substring ``t`` is bytes ``[t * nb, (t + 1) * nb)`` with ``nb = 32 / tables``, read little-endian.

    Args:
        descriptors: (K, 32) uint8.
        tables: number of substrings (8 bits each or more, a divisor of 32 bytes).

    Returns:
        (tables, K) int64 substring values in ``[0, 2^(256 / tables))``.
    """
    check_shape(descriptors, "K 32", "descriptors")
    if tables < 1 or 32 % tables:
        raise ConfigError(f"tables: must divide the 32 descriptor bytes, got {tables}")
    nb = 32 // tables
    k = descriptors.shape[0]
    shifts = 8 * torch.arange(nb, dtype=torch.int64, device=descriptors.device)
    parts = descriptors.reshape(k, tables, nb).to(torch.int64) << shifts
    return parts.sum(-1).T.contiguous()


def _search_rows(keys: Tensor, values: Tensor, right: bool, ascending: tuple[np.ndarray, np.ndarray] | None = None) -> Tensor:
    """``torch.searchsorted(keys, values, right=right)`` of (m, n) sorted rows and (m, Q) values.

    On the host it runs row by row in NumPy with the values in ascending order: ``values`` sorted
    per row already (``ascending`` None: a sorted run, as in :func:`_merge`), or ``ascending`` =
    (their per-row ``argsort``, the values in that order; :func:`_ascending`), the positions then
    scattered back to the values' own order. A binary search over ascending values reuses its
    cache lines, about twice torch's speed on random queries; the positions are the same integers.
    """
    if not (numpy_viewable(keys) and numpy_viewable(values)):
        return torch.searchsorted(keys, values, right=right)
    k = keys.numpy()
    side = "right" if right else "left"
    out = np.empty(values.shape, dtype=np.int64)
    for t in range(k.shape[0]):  # one table per row (16 by default)
        if ascending is None:
            out[t] = np.searchsorted(k[t], values[t].numpy(), side)
        else:
            order, sorted_values = ascending
            out[t, order[t]] = np.searchsorted(k[t], sorted_values[t], side)
    return torch.from_numpy(out)


def _ascending(values: Tensor) -> tuple[np.ndarray, np.ndarray] | None:
    """(m, Q) host values' per-row ``argsort`` and the values in that order, for every level's
    :func:`_search_rows`; None off the host (torch searches them as they are)."""
    if not numpy_viewable(values):
        return None
    v = values.numpy()
    order = np.argsort(v, axis=1, kind="stable")
    return order, np.take_along_axis(v, order, axis=1)


class _Level:
    """One sorted run of all m tables: ``keys`` and ``ids`` (m, n), sorted by (key, id) per row.

    When the run is large compared with the ``2^bits`` possible substring values it also keeps
    CSR bucket offsets ``offsets`` (m, 2^bits + 1): bucket ``v`` of table ``t`` is
    ``keys[t, offsets[t, v] : offsets[t, v + 1]]``, a lookup without binary search (which is
    cache-unfriendly on large runs).
    """

    __slots__ = ("keys", "ids", "offsets")

    def __init__(self, keys: Tensor, ids: Tensor, bits: int) -> None:
        self.keys = keys
        self.ids = ids
        self.offsets = None
        m, n = keys.shape
        if 2**bits <= 4 * n:
            buckets = 2**bits
            flat = (keys.to(torch.int64) + buckets * torch.arange(m, device=keys.device)[:, None]).flatten()
            counts = torch.bincount(flat, minlength=m * buckets).reshape(m, buckets)
            self.offsets = torch.cat([counts.new_zeros(m, 1), torch.cumsum(counts, 1)], dim=1)

    @property
    def size(self) -> int:
        return int(self.keys.shape[1])

    def bucket_ranges(self, qkeys: Tensor, ascending: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[Tensor, Tensor]:
        """(m, Q) start and end positions of each query substring's bucket in each table;
        ``ascending``: ``qkeys`` sorted per row on the host (:func:`_ascending`)."""
        if self.offsets is not None:
            k = qkeys.to(torch.int64)
            return torch.gather(self.offsets, 1, k), torch.gather(self.offsets, 1, k + 1)
        return _search_rows(self.keys, qkeys, False, ascending), _search_rows(self.keys, qkeys, True, ascending)


def _merge(old: _Level, new: _Level, bits: int) -> _Level:
    """Merge two levels; every id in ``new`` is larger than every id in ``old``."""
    m, na, nb = old.keys.shape[0], old.size, new.size
    dev = old.keys.device
    # Equal keys: old entries first, which keeps (key, id) order since new ids are larger.
    pos_old = _search_rows(new.keys, old.keys, False) + torch.arange(na, device=dev)
    pos_new = _search_rows(old.keys, new.keys, True) + torch.arange(nb, device=dev)
    keys = old.keys.new_empty(m, na + nb)
    ids = old.ids.new_empty(m, na + nb)
    keys.scatter_(1, pos_old, old.keys)
    keys.scatter_(1, pos_new, new.keys)
    ids.scatter_(1, pos_old, old.ids)
    ids.scatter_(1, pos_new, new.ids)
    return _Level(keys, ids, bits)


class MILDDatabase:
    """Keyframe descriptor database with multi-index hash tables (MILD).

    Example::

        db = MILDDatabase(MILDConfig())
        db.add(0, features0.descriptors)
        db.add(1, features1.descriptors)
        keyframe_ids, scores = db.query(features_new.descriptors)

    The database lives on the device of the first descriptors added; later calls must use the
    same device.
    """

    def __init__(self, cfg: MILDConfig | None = None) -> None:
        self.cfg = MILDConfig() if cfg is None else cfg
        self._device: torch.device | None = None
        self._words: Tensor | None = None  # (capacity, 4) int64 packed descriptors
        self._owner: Tensor | None = None  # (capacity,) int64 keyframe slot of each descriptor
        self._n = 0
        self._levels: list[_Level] = []
        self._kf_ids: list[int] = []
        self._kf_index: dict[int, int] = {}
        self._kf_start: list[int] = []
        self._kf_count: list[int] = []
        self._key_dtype = torch.int32 if self.cfg.bits < 32 else torch.int64

    def __len__(self) -> int:
        """Number of keyframes in the database."""
        return len(self._kf_ids)

    @property
    def num_descriptors(self) -> int:
        """Number of descriptors stored over all keyframes."""
        return self._n

    @property
    def num_levels(self) -> int:
        """Number of sorted levels the hash tables are currently split into."""
        return len(self._levels)

    @property
    def keyframe_ids(self) -> Tensor:
        """(N,) int64 keyframe ids in insertion order."""
        return torch.tensor(self._kf_ids, dtype=torch.int64, device=self._device)

    def _check(self, descriptors: Tensor, name: str) -> None:
        check_shape(descriptors, "K 32", name)
        if descriptors.dtype != torch.uint8:
            raise DTypeError(f"{name}: expected uint8 descriptors, got {descriptors.dtype}")
        if self._device is not None and descriptors.device != self._device:
            raise MILDError(f"{name}: the database is on {self._device}, got descriptors on {descriptors.device}")

    def _reserve(self, extra: int) -> None:
        need = self._n + extra
        cap = 0 if self._words is None else self._words.shape[0]
        if need <= cap:
            return
        new_cap = max(need, 2 * cap, 1024)
        words = torch.zeros(new_cap, 4, dtype=torch.int64, device=self._device)
        owner = torch.zeros(new_cap, dtype=torch.int64, device=self._device)
        if self._words is not None:
            words[: self._n] = self._words[: self._n]
            owner[: self._n] = self._owner[: self._n]
        self._words, self._owner = words, owner

    def add(self, keyframe_id: int, descriptors: Tensor) -> None:
        """Insert the descriptors of one keyframe.

        Args:
            keyframe_id: caller's id of the keyframe, unique in this database.
            descriptors: (K, 32) uint8 descriptors; K = 0 is allowed (the keyframe then never scores).

        Raises:
            MILDError: ``keyframe_id`` is already present, or ``descriptors`` is on another device.
        """
        self._check(descriptors, "descriptors")
        keyframe_id = int(keyframe_id)
        if keyframe_id in self._kf_index:
            raise MILDError(f"keyframe_id: {keyframe_id} is already in the database")
        if self._device is None:
            self._device = descriptors.device
        k = descriptors.shape[0]
        if self._n + k >= 2**31:
            raise MILDError(f"descriptors: the database holds at most 2^31 - 1 descriptors, got {self._n} + {k}")
        slot = len(self._kf_ids)
        self._reserve(k)
        if k:
            self._words[self._n : self._n + k] = pack_descriptors(descriptors)
            self._owner[self._n : self._n + k] = slot
            keys = substring_keys(descriptors, self.cfg.tables).to(self._key_dtype)  # (m, K)
            keys, order = torch.sort(keys, dim=1, stable=True)
            ids = (order + self._n).to(torch.int32)
            self._levels.append(_Level(keys, ids, self.cfg.bits))
            # Merge runs of similar size so that sizes fall geometrically along the list.
            while len(self._levels) > 1 and self._levels[-2].size <= 2 * self._levels[-1].size:
                new = self._levels.pop()
                self._levels[-1] = _merge(self._levels[-1], new, self.cfg.bits)
        self._kf_ids.append(keyframe_id)
        self._kf_index[keyframe_id] = slot
        self._kf_start.append(self._n)
        self._kf_count.append(k)
        self._n += k

    def _hit_chunks(self, descriptors: Tensor):
        """Yield all (query index, stored id) pairs that share a substring, in chunks.

        A pair appears once per table on which the two descriptors agree. On a CPU the pairs come
        in chunks of about ``_HIT_CHUNK`` so that the work on them stays in cache (real ORB
        substrings are far from uniform: common buckets give millions of pairs per query).

        Yields:
            query_index: (H,) int64.
            stored_id: (H,) int64 global descriptor ids (insertion order).
        """
        dev = descriptors.device
        q = descriptors.shape[0]
        qkeys = substring_keys(descriptors, self.cfg.tables).to(self._key_dtype)  # (m, Q)
        ascending = _ascending(qkeys)  # on the host every level searches the queries in ascending order
        for level in self._levels:
            lo, hi = level.bucket_ranges(qkeys, ascending)  # (m, Q)
            counts = (hi - lo).flatten()  # (m * Q,): probe t * Q + i
            starts = lo.flatten()
            csum = torch.cumsum(counts, 0)
            total = int(csum[-1]) if csum.numel() else 0
            if total == 0:
                continue
            # Cut the probe list where the running hit count crosses multiples of the chunk size.
            step = _HIT_CHUNK if dev.type == "cpu" else total
            bounds = [0, counts.shape[0]]
            if total > step:
                marks = torch.arange(step, total, step, device=dev)
                cuts = (torch.searchsorted(csum, marks, right=False) + 1).tolist()
                bounds = sorted(set(bounds) | set(cuts))
            # Per probe: its query descriptor, and the flat position in ``ids`` of its bucket
            # start minus the number of hits before it, so hit h of the chunk sits at base + h.
            probe_query = torch.arange(counts.shape[0], device=dev) % q
            probe_table = torch.arange(counts.shape[0], device=dev) // q
            flat_start = probe_table * level.size + starts
            ids_flat = level.ids.view(-1)
            for p0, p1 in zip(bounds[:-1], bounds[1:]):
                cnt = counts[p0:p1]
                local = torch.cumsum(cnt, 0)
                n = int(local[-1])
                if n == 0:
                    continue
                probe = torch.repeat_interleave(torch.arange(p1 - p0, device=dev), cnt, output_size=n)  # (H,)
                base = flat_start[p0:p1] - (local - cnt)
                flat = base[probe] + torch.arange(n, device=dev)
                yield probe_query[p0:p1][probe], ids_flat[flat].to(torch.int64)

    def candidates(self, descriptors: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Stored descriptors that agree with a query descriptor on at least one substring.

        This is the multi-index lookup alone, before any distance check.

        Args:
            descriptors: (Q, 32) uint8 query descriptors.

        Returns:
            query_index: (H,) int64 index into ``descriptors``.
            keyframe_ids: (H,) int64 id of the keyframe holding the candidate.
            descriptor_index: (H,) int64 index of the candidate within that keyframe's descriptors.
            Each pair appears once, sorted by (query_index, stored order).
        """
        self._check(descriptors, "descriptors")
        n = max(self._n, 1)
        codes = [torch.unique(qi * n + ids) for qi, ids in self._hit_chunks(descriptors)]
        pair = torch.unique(torch.cat(codes)) if codes else torch.zeros(0, dtype=torch.int64, device=descriptors.device)
        q_idx, ids = pair // n, pair % n
        if ids.numel() == 0:
            return q_idx, ids.clone(), ids.clone()
        slot = self._owner[ids]
        start = torch.tensor(self._kf_start, dtype=torch.int64, device=ids.device)
        return q_idx, self.keyframe_ids[slot], ids - start[slot]

    def similarity(self, descriptors: Tensor) -> tuple[Tensor, Tensor]:
        """Score every keyframe against a query descriptor set (see the module docstring).

        Args:
            descriptors: (Q, 32) uint8 query descriptors.

        Returns:
            keyframe_ids: (N,) int64 in insertion order.
            scores: (N,) float64 similarity, ~1 for the same view, 0 for no matched descriptor.
        """
        self._check(descriptors, "descriptors")
        n_kf = len(self._kf_ids)
        dev = descriptors.device if self._device is None else self._device
        scores = torch.zeros(n_kf, dtype=torch.float64, device=dev)
        q = descriptors.shape[0]
        if n_kf == 0 or q == 0 or self._n == 0:
            return self.keyframe_ids, scores
        qwords = pack_descriptors(descriptors)
        words = self._words[: self._n]
        kept_q, kept_id, kept_d = [], [], []
        for qi, ids in self._hit_chunks(descriptors):
            d = hamming_distance_indexed(qwords, qi, words, ids, chunk=_HIT_CHUNK)
            ok = d <= self.cfg.max_distance
            kept_q.append(qi[ok])
            kept_id.append(ids[ok])
            kept_d.append(d[ok])
        if not kept_q:
            return self.keyframe_ids, scores
        q_idx, ids, dist = torch.cat(kept_q), torch.cat(kept_id), torch.cat(kept_d)
        if dist.numel():
            # One vote per (query descriptor, keyframe): its closest match there. Taking the
            # minimum also removes the repeats of a pair found through several tables.
            pair = q_idx * n_kf + self._owner[ids]
            uniq, inverse = torch.unique(pair, return_inverse=True)
            dmin = torch.full(uniq.shape, _DESCRIPTOR_BITS + 1, dtype=torch.int64, device=dev)
            dmin.scatter_reduce_(0, inverse, dist, reduce="amin")
            votes = torch.exp(-((dmin.to(torch.float64) / self.cfg.sigma) ** 2))
            scores.index_add_(0, uniq % n_kf, votes)
        counts = torch.tensor(self._kf_count, dtype=torch.float64, device=dev)
        norm = torch.sqrt(counts * q)
        scores = torch.where(counts > 0, scores / norm.clamp(min=1.0), torch.zeros_like(scores))
        return self.keyframe_ids, scores

    def query(self, descriptors: Tensor) -> tuple[Tensor, Tensor]:
        """Return the best loop-closure candidates for a query descriptor set.

        The ``exclude_recent`` most recently added keyframes are skipped; of the rest, the
        ``top_k`` highest-scoring keyframes whose score exceeds ``min_score`` are returned, best
        first (earlier keyframes first on ties).

        Args:
            descriptors: (Q, 32) uint8 descriptors of the new keyframe.

        Returns:
            keyframe_ids: (k,) int64 candidate keyframe ids, k <= top_k.
            scores: (k,) float64 their scores.
        """
        ids, scores = self.similarity(descriptors)
        eligible = max(0, len(self._kf_ids) - self.cfg.exclude_recent)
        scores = scores[:eligible]
        order = torch.sort(scores, descending=True, stable=True).indices[: self.cfg.top_k]
        order = order[scores[order] > self.cfg.min_score]
        logger.debug("MILD query: %d of %d keyframes eligible, %d returned", eligible, len(self._kf_ids), order.numel())
        return ids[order], scores[order]
