"""GC-SLAM's optimisation side: keyframe poses, pairs, MILD loop detection and FastGO.

The tracker hands each new keyframe over as a :class:`KeyframeEvent`. An :class:`Optimizer`
holds what the optimisation thread owns (keyframe poses, pair statistics, the MILD database)
and exposes the phases of one keyframe's insertion: :meth:`Optimizer.begin` (add the keyframe
and its odometry pair, query MILD), :meth:`Optimizer.optimized` (take the per-keyframe FastGO
result) and :meth:`Optimizer.close_loops` (register, test and accept loop candidates, §IV-C).
The FastGO call between them is made by ``system.insert_keyframes``, for one optimiser or for
several sequences at once. A :class:`Worker` runs insertions in a background thread, inline,
or leaves them for the lockstep driver (deferred).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ...errors import TorchSlamError
from ...fastgo import FastGOConfig, FastGOProblem, PairStats, accept_loop_closures, optimize
from ...geometry import se3_inverse
from ...loop import MILDDatabase
from ...registration.sparse import FrameFeatures, register_sparse_batch
from ..base import add_stage_ms
from ..monitor import Monitor
from .config import GCSlamConfig

__all__ = ["Anchor", "KeyframeEvent", "Optimizer", "Worker"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Anchor:
    """Where an unlinked keyframe starts: the last tracked frame's keyframe and pose relative to it."""

    kf: int  # keyframe id of the last tracked frame
    T_kf: Tensor  # (4, 4) float64 that frame's pose in keyframe ``kf``, p_kf = T p_frame


@dataclass
class KeyframeEvent:
    """What the tracker hands the optimiser for one new keyframe."""

    kf: int  # keyframe id (0, 1, ...)
    reference: int | None  # keyframe it was registered to, None for an unlinked keyframe
    T_ref_kf: Tensor | None  # (4, 4) float64 relative pose, p_ref = T p_kf
    stats: PairStats | None  # statistics of that registration's correspondences
    features: FrameFeatures  # ORB features of the keyframe (for MILD and loop registration)
    anchor: Anchor | None = None  # unlinked keyframe only: the last tracked frame
    frame_index: int = 0  # the keyframe's sequence frame index (the TensorBoard step)


class Optimizer:
    """Keyframe poses, pairs, the MILD database and FastGO: the optimisation thread's state.

    Poses and pair statistics live on the CPU in float64 whatever device the front-end uses
    (FastGO's cost does not grow with images, and float64 is the back-end's precision).
    """

    def __init__(self, cfg: GCSlamConfig, monitor: Monitor, focal: float | None = None) -> None:
        """
        Args:
            cfg: GC-SLAM settings.
            monitor: where the optimiser's scalars go.
            focal: the camera's focal length in pixels, the scale of the guided loop matching
                window (``cfg.loop_guided``); None matches loop candidates by brute force.
        """
        self.cfg = cfg
        self.monitor = monitor
        self.focal = focal
        self.T_wk: list[Tensor] = []
        self.pairs: list[tuple[int, int]] = []
        self.stats: list[PairStats] = []
        self.pair_kind: list[str] = []  # "odometry" (tracked or relocalised keyframe) or "loop"
        self.features: list[FrameFeatures] = []
        self.mild = MILDDatabase(cfg.mild)
        self.loops = {"candidates": 0, "registered": 0, "accepted": 0, "rejected": 0}
        # Loop candidates whose guided registration was kept, and those matched by brute force.
        self.loop_matching = {"guided": 0, "fallback": 0}
        self.stage_ms: dict[str, float] = {}
        self.fastgo_ms: list[float] = []
        self.generator = torch.Generator().manual_seed(cfg.sparse.seed + 1)

    def _add_ms(self, stage: str, t0: float) -> float:
        return add_stage_ms(self.stage_ms, stage, t0)

    def fastgo_config(self, iterations: int) -> FastGOConfig:
        """FastGO's settings for a run of ``iterations``."""
        return FastGOConfig(iterations=iterations)

    def problem(self) -> FastGOProblem:
        """The pose graph as it stands: all keyframes, all pairs, keyframe 0 fixed."""
        T = torch.stack(self.T_wk)
        if not self.pairs:
            return FastGOProblem(T, torch.zeros(0, 2, dtype=torch.int64), PairStats.empty(0), 0)
        return FastGOProblem(T, torch.tensor(self.pairs, dtype=torch.int64), PairStats.cat(self.stats), 0)

    def begin(self, ev: KeyframeEvent) -> list[int]:
        """Add the keyframe and its odometry pair; query and update MILD; return loop candidates."""
        cfg = self.cfg
        if ev.kf != len(self.T_wk):
            raise TorchSlamError(f"keyframe {ev.kf} inserted out of order (expected {len(self.T_wk)})")
        if ev.reference is None:
            # An unlinked keyframe starts where the last tracked frame was; that guess only
            # matters until a loop closure links it to the rest.
            T0 = torch.eye(4, dtype=torch.float64)
            if ev.anchor is not None:
                T0 = self.T_wk[ev.anchor.kf] @ ev.anchor.T_kf.to(torch.float64)
            self.T_wk.append(T0)
        else:
            self.T_wk.append(self.T_wk[ev.reference] @ ev.T_ref_kf.to(torch.float64))
            self.pairs.append((ev.reference, ev.kf))
            self.stats.append(ev.stats.to("cpu", torch.float64))
            self.pair_kind.append("odometry")
        self.features.append(ev.features)
        t0 = time.perf_counter()
        candidates: list[int] = []
        if cfg.loops and len(self.mild):
            ids, _ = self.mild.query(ev.features.descriptors)
            candidates = [int(c) for c in ids if int(c) != ev.reference]
        self.mild.add(ev.kf, ev.features.descriptors)
        self._add_ms("loop_detection", t0)
        return candidates

    def optimized(self, res, frame_index: int, ms: float) -> None:
        """Take the result of the per-keyframe FastGO run (``ms``: its share of the time)."""
        self.T_wk = list(res.T_wc.unbind(0))
        self.fastgo_ms.append(ms)
        self.stage_ms["fastgo"] = self.stage_ms.get("fastgo", 0.0) + ms
        self.monitor.scalar("optimization/fastgo_ms", ms, frame_index)

    def predicted_poses(self, kf: int, candidates: list[int]) -> Tensor | None:
        """The pose graph's current relative poses of the candidates, the guide of their matching.

        Returns:
            (C, 4, 4) float64 ``T_ck`` with ``p_c = T_ck p_kf`` for each candidate ``c``, or None
            where loop matching is not guided (``cfg.loop_guided`` off, no focal length, or
            ``sparse.guided_radius`` 0).
        """
        if not (self.cfg.loop_guided and self.focal and self.cfg.sparse.guided_radius > 0 and candidates):
            return None
        T_wc = torch.stack([self.T_wk[c] for c in candidates])  # (C, 4, 4)
        return se3_inverse(T_wc) @ self.T_wk[kf]

    def close_loops(self, kf: int, candidates: list[int], frame_index: int = 0) -> None:
        """Register the candidates to keyframe ``kf`` and keep the loops that pass the test of §IV-C."""
        cfg = self.cfg
        t0 = time.perf_counter()
        self.loops["candidates"] += len(candidates)
        T_pred = self.predicted_poses(kf, candidates)
        res = register_sparse_batch([self.features[c] for c in candidates], [self.features[kf]] * len(candidates), cfg.sparse,
                                    self.generator, T_pred=T_pred, focal=self.focal)
        if T_pred is not None:
            guided = int(res.guided.sum())
            self.loop_matching["guided"] += guided
            self.loop_matching["fallback"] += len(candidates) - guided
        ok = [b for b in range(len(candidates)) if bool(res.success[b])]
        t0 = self._add_ms("loop_registration", t0)
        if not ok:
            return
        self.loops["registered"] += len(ok)
        # All verified candidates are tested together; if that is rejected, each on its own, so
        # one false candidate does not take the true ones down with it.
        trials = [ok] if len(ok) == 1 else [ok] + [[b] for b in ok]
        for k, group in enumerate(trials):
            p = self.problem()
            loop_pairs = torch.tensor([(candidates[b], kf) for b in group], dtype=torch.int64)
            loop_stats = res.stats[torch.tensor(group, device=res.stats.device)].to("cpu", torch.float64)
            decision = accept_loop_closures(
                p.T_wc, p.pairs, p.stats, loop_pairs, loop_stats, fixed=0, threshold=float("inf"),
                config=self.fastgo_config(cfg.loop_iterations),
            )
            rms_before, rms_after = decision.cost_before**0.5, decision.cost_after**0.5
            accepted = rms_after <= rms_before * (1.0 + cfg.loop_threshold) + cfg.loop_slack_m
            if accepted:
                self.T_wk = list(decision.result.T_wc.unbind(0))
                for b in group:
                    self.pairs.append((candidates[b], kf))
                    self.pair_kind.append("loop")
                self.stats.append(loop_stats)
                self.loops["accepted"] += len(group)
                self.monitor.scalar("progress/loops_accepted", self.loops["accepted"], frame_index)
                logger.debug("keyframe %d: loop(s) to %s accepted (RMS %.4f -> %.4f m)", kf, [candidates[b] for b in group],
                             rms_before, rms_after)
                if k == 0:
                    break
            else:
                if k > 0 or len(group) == 1:
                    self.loops["rejected"] += len(group)
        self._add_ms("loop_acceptance", t0)

    def finish(self) -> None:
        """One last FastGO run of ``final_iterations`` over all keyframes."""
        if self.cfg.final_iterations and self.pairs:
            t0 = time.perf_counter()
            p = self.problem()
            res = optimize(p.T_wc, p.pairs, p.stats, fixed=0, config=self.fastgo_config(self.cfg.final_iterations))
            self.T_wk = list(res.T_wc.unbind(0))
            self._add_ms("fastgo_final", t0)


class Worker:
    """Runs the insertion of new keyframes into an :class:`Optimizer` in a background thread, inline, or deferred.

    Deferred (lockstep runs of several sequences): new keyframes wait in ``pending`` until the
    driver inserts those of all sequences together (``system.track_frames``).
    """

    def __init__(
        self, optimizer: Optimizer, insert: Callable[[Optimizer, KeyframeEvent], None], threaded: bool, deferred: bool = False
    ) -> None:
        """
        Args:
            optimizer: the optimiser the keyframes go to.
            insert: inserts one keyframe into one optimiser (``system.insert_keyframe``).
            threaded: insert in a background thread.
            deferred: keep new keyframes in ``pending``; overrides ``threaded``.
        """
        self.optimizer = optimizer
        self._insert = insert
        self.threaded = threaded and not deferred
        self.deferred = deferred
        self.pending: list[KeyframeEvent] = []
        self.error: BaseException | None = None
        if self.threaded:
            self.queue: queue.Queue = queue.Queue()
            self.thread = threading.Thread(target=self._loop, name="torchslam-gcslam-optimizer", daemon=True)
            self.thread.start()

    def _loop(self) -> None:
        while True:
            ev = self.queue.get()
            if ev is None:
                return
            if self.error is not None:
                continue
            try:
                self._insert(self.optimizer, ev)
            except BaseException as exc:  # noqa: BLE001 - reported to the tracking thread at the next call
                self.error = exc

    def submit(self, ev: KeyframeEvent) -> None:
        """Hand over one new keyframe; raises if the background thread has failed."""
        if self.error is not None:
            raise TorchSlamError(f"GC-SLAM optimisation thread failed: {self.error}") from self.error
        if self.threaded:
            self.queue.put(ev)
        elif self.deferred:
            self.pending.append(ev)
        else:
            self._insert(self.optimizer, ev)

    def join(self) -> None:
        """Insert what is pending, stop the thread and raise its error, if any."""
        while self.pending:
            self._insert(self.optimizer, self.pending.pop(0))
        if self.threaded:
            self.queue.put(None)
            self.thread.join()
        if self.error is not None:
            raise TorchSlamError(f"GC-SLAM optimisation thread failed: {self.error}") from self.error
