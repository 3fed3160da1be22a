"""Many NI-SLAM sequences in lockstep: one frame of every sequence per step, the heavy stages batched.

``run_lockstep`` is to a group of sequences what ``run_sequence`` is to one: it starts one
``NISlam`` per sequence, feeds them their frames step by step through ``track_frames`` (one
batched back-projection, tracking step and fusion per step for all sequences still running)
and returns one ``RunResult`` per sequence, the same as ``run_sequence`` would have returned for
it alone up to floating-point round-off of the batched kernels.

Sequences of different lengths leave the active set when they run out of frames (their system
is finished right away, which frees its maps). A sequence whose start, decode, phase or finish
raises is returned as that exception; the others go on. Ctrl-C stops every sequence, finishes
each with what it has computed and marks it ``interrupted``.

Timing:
    ``wall_s`` of every result is the group's wall-clock time, from the start of the first
    sequence to the last finish: the frames of all sequences were interleaved, so no shorter
    span belongs to one of them (``fps_end_to_end`` is thus a sequence's share of the group).
    ``compute_s`` is a sequence's own work (``start``, its phases of every step, ``finish``)
    plus an equal share of each batched call it took part in (``StepReport.compute_s``); the
    sum over sequences is the group's compute time. Time spent waiting for frames (decode) is
    in neither share but is in ``wall_s``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

from ..data.frame import Frame, Sequence
from ..errors import ConfigError
from . import gcslam as _gcslam
from .base import RunResult, SystemOutput, empty_output
from .gcslam import GCSlam, GCSlamConfig
from .memory import check_run_memory
from .monitor import Monitor
from .nislam import NISlam, NISlamConfig, track_frames

__all__ = ["CPU_BATCH_PIXELS", "default_max_batch", "run_lockstep"]

logger = logging.getLogger(__name__)

# Orthographic pixels per batched call on the CPU: ``max_batch`` defaults to this over the
# orthographic image size (at least 1). On the CPU a batched call saves per-operation overhead
# but its images leave the caches as B grows. Measured with ``scripts/bench_batch.py`` (one
# thread, 2-core AMD EPYC shared with other jobs): at the default 360 x 480 one (B, ...) batch
# per step gave 0.94x to 0.78x the frames/s of running the sequences one after another for
# B = 2 to 16, and at 180 x 240 1.04x to 1.09x up to B = 32 but 0.85x at B = 64; this budget
# (one sequence per call at 360 x 480, six at 180 x 240) gave 0.99x to 1.09x. On other devices
# the whole group is one batch.
CPU_BATCH_PIXELS = 2**18


def default_max_batch(system_cfg: NISlamConfig | GCSlamConfig, device: str, n: int) -> int:
    """Sequences per batched call when none is given: ``CPU_BATCH_PIXELS`` worth on the CPU, else all ``n``.

    GC-SLAM batches only its FastGO solves, whose size does not grow with images: all ``n``.
    """
    if isinstance(system_cfg, GCSlamConfig):
        return max(n, 1)
    if str(device).startswith("cpu"):
        return max(1, CPU_BATCH_PIXELS // (system_cfg.kcc.ortho_height * system_cfg.kcc.ortho_width))
    return max(n, 1)


def run_lockstep(
    system_cfg: NISlamConfig | GCSlamConfig,
    sequences: list[Sequence],
    device: str = "cpu",
    monitors: list[Monitor] | None = None,
    max_frames: int | None = None,
    max_batch: int | None = None,
) -> list[RunResult | BaseException]:
    """Run NI-SLAM or GC-SLAM on several sequences at once, one frame of each per step.

    NI-SLAM batches its per-frame tensor work (``nislam.track_frames``); GC-SLAM tracks each
    frame on its own and optimises the new keyframes of all sequences in one FastGO call
    (``gcslam.track_frames``, with the optimisation inline instead of in a thread).

    Args:
        system_cfg: NI-SLAM or GC-SLAM settings, shared by every sequence.
        sequences: the sequences; any lengths, cameras and image sizes (sequences that share a
            camera share the back-projection call, all share the tracking step).
        device: where tensors live ("cpu", "cuda", ...).
        monitors: one monitor per sequence, or None for no monitoring.
        max_frames: stop each sequence after this many frames.
        max_batch: the most sequences in one batched call; None takes ``default_max_batch``.

    Returns:
        Per sequence, in order, its ``RunResult`` or the exception that stopped it.

    Raises:
        ConfigError: an argument is not what it should be (named in the message), or the
            configuration needs more memory than the device has (``slam.memory``).
    """
    if not isinstance(system_cfg, (NISlamConfig, GCSlamConfig)):
        raise ConfigError(f"system_cfg: expected an NISlamConfig or GCSlamConfig, got {type(system_cfg).__name__}")
    if not isinstance(sequences, (list, tuple)) or not sequences:
        raise ConfigError(f"sequences: expected a non-empty list of sequences, got {sequences!r}")
    if monitors is not None and len(monitors) != len(sequences):
        raise ConfigError(f"monitors: expected one monitor per sequence ({len(sequences)}), got {len(monitors)}")
    if max_frames is not None and not (isinstance(max_frames, int) and max_frames >= 0):
        raise ConfigError(f"max_frames: expected a non-negative integer or None, got {max_frames!r}")
    if max_batch is not None and not (isinstance(max_batch, int) and max_batch >= 1):
        raise ConfigError(f"max_batch: expected a positive integer or None, got {max_batch!r}")
    if max_batch is None:
        max_batch = default_max_batch(system_cfg, device, len(sequences))

    n = len(sequences)
    monitors = list(monitors) if monitors is not None else [Monitor() for _ in range(n)]
    if isinstance(system_cfg, GCSlamConfig):
        systems: list = [GCSlam(system_cfg, device=device, monitor=m, deferred=True) for m in monitors]
        step = _gcslam.track_frames
    else:
        systems = [NISlam(system_cfg, device=device, monitor=m) for m in monitors]
        step = track_frames
    # Every NI-SLAM sequence keeps its keyframe images at once; GC-SLAM tracks one frame at a time.
    batch = 1 if isinstance(system_cfg, GCSlamConfig) else n
    check_run_memory(systems[0], [getattr(s, "camera", None) for s in sequences], batch=batch)
    failed: list[BaseException | None] = [None] * n
    outputs: list[SystemOutput | None] = [None] * n
    frames_in: list[Iterator[Frame] | None] = [None] * n
    processed = [0] * n
    compute = [0.0] * n
    interrupted = False
    t_start = time.perf_counter()

    def finish(i: int) -> None:
        t0 = time.perf_counter()
        try:
            outputs[i] = systems[i].finish()
            systems[i] = None  # its keyframe maps are no longer needed
        except Exception as exc:  # noqa: BLE001 - reported in the sequence's place
            failed[i] = exc
            logger.warning("%s: finish failed: %s", sequences[i].name, exc)
        compute[i] += time.perf_counter() - t0

    active: list[int] = []
    try:
        for i, seq in enumerate(sequences):
            t0 = time.perf_counter()
            try:
                systems[i].start(seq)
                frames_in[i] = iter(seq)
                active.append(i)
            except Exception as exc:  # noqa: BLE001 - reported in the sequence's place
                failed[i] = exc
                logger.warning("%s: start failed: %s", seq.name, exc)
            compute[i] += time.perf_counter() - t0
        while active:
            stepping, frames = [], []
            for i in active:
                frame = None
                if max_frames is None or processed[i] < max_frames:
                    try:
                        frame = next(frames_in[i])
                    except StopIteration:
                        pass
                    except Exception as exc:  # noqa: BLE001 - a sequence that cannot be read stops alone
                        failed[i] = exc
                        logger.warning("%s: reading frame %d failed: %s", sequences[i].name, processed[i], exc)
                        continue
                if frame is None:
                    finish(i)
                else:
                    stepping.append(i)
                    frames.append(frame)
            if not stepping:
                break
            report = step([systems[i] for i in stepping], frames, max_batch)
            for k, i in enumerate(stepping):
                compute[i] += report.compute_s[k]
                if report.errors[k] is not None:
                    failed[i] = report.errors[k]
                    systems[i] = None
                    logger.warning("%s: frame %d failed: %s", sequences[i].name, frames[k].index, report.errors[k])
                else:
                    processed[i] += 1
            active = [i for i in stepping if failed[i] is None]
    except KeyboardInterrupt:
        interrupted = True
        logger.warning("interrupted; finishing every sequence with what was computed")
    for i in range(n):
        if failed[i] is None and outputs[i] is None and frames_in[i] is not None:
            finish(i)
    wall_s = time.perf_counter() - t_start

    results: list[RunResult | BaseException] = []
    for i, seq in enumerate(sequences):
        if failed[i] is not None:
            results.append(failed[i])
            continue
        # Only a Ctrl-C before its start leaves a sequence without output: it computed nothing.
        output = outputs[i] if outputs[i] is not None else empty_output()
        results.append(RunResult.of(seq, output, processed[i], wall_s, compute[i], interrupted))
    return results
