"""Run one system on one sequence and write its run folder: the library behind ``torchslam run``."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch

from ..config import config_file, config_from_dict, config_to_dict, deep_merge, nest_dotted, parse_overrides, read_yaml_mapping
from ..data.frame import Frame, Sequence
from ..data.synthetic import SyntheticConfig, generate_sequence
from ..data.tum import MAX_DEPTH_TIME_OFFSET, TUMSequence, check_depth_time_offset
from ..errors import AT_LEAST_1, NON_NEGATIVE, POSITIVE, ConfigError, Limit, TorchSlamError, check_limits
from ..allocator import setup_allocator
from ..threads import setup_threads
from ..systems.base import check_max_frames, run_sequence
from ..systems.monitor import Monitor, TensorBoardMonitor
from .outputs import write_run
from .progress import log_final, log_hparams, progress_callback
from ..systems.registry import get_system
from .runfolder import prepare_run_folder

__all__ = ["DataConfig", "RunOptions", "load_sequence", "resolve_config", "run"]

logger = logging.getLogger(__name__)

SYNTHETIC = "synthetic"
#: ``data.depth_time_offset``'s value that estimates the latency from the images.
AUTO = "auto"


@dataclass(frozen=True)
class DataConfig:
    """How a sequence is read: the ``data:`` section of a run config.

    Attributes:
        stride: use every ``stride``-th frame.
        start: first frame (after association).
        end: one past the last frame, or None for all.
        max_gap: largest colour/depth timestamp gap accepted when associating, seconds.
        prefetch: frames decoded ahead in a background thread (0 = decode inline).
        register_colour: register an unregistered colour image to the depth image where the
            calibration knows the colour camera (``TUMSequence``; 7-Scenes by preset).
        synthetic: the generator's settings when ``--data synthetic``.
        depth_time_offset: each depth image was taken at its stamp plus this, seconds
            (``TUMSequence``; the depth stream's latency against the colour stream), or
            ``"auto"``: estimated from the images when the folder is opened
            (:func:`~torchslam.app.calibrate_time.estimate_depth_time_offset`, about 10 s at 640x480),
            for folders whose depth stamps differ from their colour stamps (unsynchronised
            streams, as TUM's); a folder that stamps both alike is taken as synchronised (0).
            Not for ``--data synthetic``, whose latency is ``synthetic.depth_time_offset``.
    """

    stride: int = 1
    start: int = 0
    end: int | None = None
    max_gap: float = 0.02
    prefetch: int = 2
    register_colour: bool = True
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    depth_time_offset: float | str = 0.0

    LIMITS: ClassVar[dict[str, Limit]] = {
        "stride": AT_LEAST_1, "start": NON_NEGATIVE, "end": NON_NEGATIVE, "max_gap": POSITIVE, "prefetch": NON_NEGATIVE,
    }

    def __post_init__(self) -> None:
        check_limits(self)
        if self.depth_time_offset != AUTO:
            try:
                offset = check_depth_time_offset(self.depth_time_offset, "data.depth_time_offset")
            except ConfigError:
                raise ConfigError(
                    f"data.depth_time_offset: expected seconds within +-{MAX_DEPTH_TIME_OFFSET} or '{AUTO}', got {self.depth_time_offset!r}"
                ) from None
            object.__setattr__(self, "depth_time_offset", offset)


@dataclass(frozen=True)
class RunOptions:
    """Everything about a run that is not the system's own config.

    ``params`` is a checkpoint of learned config values (``torchslam.learn.save_checkpoint``)
    applied on top of the config file and below ``--set`` overrides, or of a network a run can
    use (the learned KCC channels, which it selects: ``kcc.features=learned`` with its path). With ``tensorboard``, the
    ATE so far, running stage times and counters are logged every ``monitor_every`` frames.
    ``out`` must be a missing or empty folder; ``overwrite`` clears one that holds only the
    files of an earlier run (see ``runfolder.prepare_run_folder``).
    ``threads`` is the intra-op thread count; None takes ``TORCHSLAM_THREADS`` or else the
    default of :mod:`torchslam.threads`. :func:`run` applies it to the whole process.
    """

    system: str
    data: str
    out: Path
    device: str = "cpu"
    tensorboard: bool = True
    max_frames: int | None = None
    params: Path | None = None
    monitor_every: int = 30
    overwrite: bool = False
    threads: int | None = None


def resolve_config(
    system: str,
    config_path: str | os.PathLike | None,
    overrides: Iterable[str],
    params: str | os.PathLike | None = None,
) -> tuple[Any, DataConfig, dict[str, Any]]:
    """Merge the system's defaults, its YAML file, a learned-parameter checkpoint and ``--set`` overrides.

    The YAML file holds the system's keys at the top level and an optional ``data:`` section;
    ``--set data.stride=2`` and ``--set kcc.sigma=0.3`` address the two parts. Sections merge key
    by key, so the latter keeps the file's other ``kcc`` values. ``params`` (a
    ``torchslam.learn`` checkpoint of config values, e.g. ``kcc.sigma``, or of the learned KCC
    channels, ``learn.params.checkpoint_overrides``) is applied after the file and before ``--set``; a checkpoint of another system or with unknown keys raises a
    ConfigError naming the file and the key.

    Returns:
        (system config, data config, the resolved config as plain data for ``config.yaml``).
    """
    spec = get_system(system)
    layers: list[tuple[str, dict[str, Any]]] = []
    if config_path is not None:
        path = config_file(config_path)
        layers.append((str(path), read_yaml_mapping(path)))
    if params is not None:
        from ..learn.params import (
            checkpoint_overrides,  # lazy: torch.load and the learn package
        )

        values = checkpoint_overrides(params, spec.config_cls, system)
        layers.append((str(params), nest_dotted(values, f"{params}: ")))
    layers.append(("--set", parse_overrides(list(overrides))))
    system_data: dict[str, Any] = {}
    data_data: dict[str, Any] = {}
    for source, layer in layers:
        layer = dict(layer)
        layer.pop("system", None)
        d = layer.pop("data", None) or {}
        # Validate each layer on its own so an error names the file or --set it came from.
        config_from_dict(spec.config_cls, deep_merge(system_data, layer), source=source)
        config_from_dict(DataConfig, deep_merge(data_data, d), source=f"{source} (data)")
        system_data = deep_merge(system_data, layer)
        data_data = deep_merge(data_data, d)
    system_cfg = config_from_dict(spec.config_cls, system_data)
    data_cfg = config_from_dict(DataConfig, data_data)
    resolved = {"system": system, **config_to_dict(system_cfg), "data": config_to_dict(data_cfg)}
    return system_cfg, data_cfg, resolved


def load_sequence(data: str, cfg: DataConfig, device: str = "cpu") -> Sequence:
    """Open ``data``: a TUM-layout folder, or ``synthetic`` for the built-in generated sequence.

    For a CUDA ``device`` the frames are decoded into page-locked memory (``TUMSequence``'s
    ``pin_memory``): each is copied to the GPU once, without blocking the host.
    """
    if data == SYNTHETIC:
        if cfg.depth_time_offset != 0.0:  # a number or auto
            raise ConfigError("data.depth_time_offset: not for --data synthetic (its depth latency is data.synthetic.depth_time_offset)")
        return generate_sequence(cfg.synthetic)

    def open_tum(offset: float) -> TUMSequence:
        return TUMSequence(
            data, max_gap=cfg.max_gap, stride=cfg.stride, start=cfg.start, end=cfg.end, prefetch=cfg.prefetch,
            register_colour=cfg.register_colour, pin_memory=torch.device(device).type == "cuda", depth_time_offset=offset,
        )

    if cfg.depth_time_offset != AUTO:
        return open_tum(cfg.depth_time_offset)
    # Opened at the stamps (the estimator reads frames by index; ``prefetch`` only serves
    # iteration), and kept wherever the latency stays 0.
    seq = open_tum(0.0)
    if bool((seq.depth_timestamps == seq.timestamps).all()):
        logger.info("%s: depth and colour stamped alike; data.depth_time_offset auto: 0", seq.name)
        return seq
    from .calibrate_time import estimate_depth_time_offset

    # A best-effort calibration: where it cannot decide, the stamps are taken as they are (0).
    try:
        est = estimate_depth_time_offset(seq)
    except TorchSlamError as exc:
        logger.warning("%s: data.depth_time_offset auto: not estimated (%s); using 0", seq.name, exc)
        return seq
    if est.at_edge:
        logger.warning("%s: data.depth_time_offset auto: the best latency lies at the search range's edge (%+.1f ms); using 0",
                       seq.name, 1000 * est.offset)
        return seq
    logger.info("%s: data.depth_time_offset auto: %+.1f ms (rotation RMS %.3f deg at 0, %.3f at the estimate; %d pairs)",
                seq.name, 1000 * est.offset, est.cost_at_zero, est.cost_at_offset, est.pairs)
    return open_tum(est.offset)


def default_out_dir(system: str, data: str, root: str | os.PathLike = "logs") -> Path:
    """``logs/<system>-<data name>-<YYYYmmdd-HHMMSS>``, with ``-2``, ``-3`` ... if that exists already."""
    name = SYNTHETIC if data == SYNTHETIC else Path(data).resolve().name
    base = Path(root) / f"{system}-{name}-{time.strftime('%Y%m%d-%H%M%S')}"
    out, k = base, 2
    while out.exists():
        out, k = base.with_name(f"{base.name}-{k}"), k + 1
    return out


def run(
    options: RunOptions,
    config_path: str | os.PathLike | None = None,
    overrides: Iterable[str] = (),
    progress: Callable[[Iterable[Frame]], Iterable[Frame]] | None = None,
) -> dict[str, Any]:
    """Run ``options.system`` on ``options.data`` and write the run folder ``options.out``.

    The folder is checked before any data is read (see ``RunOptions``). Ctrl-C stops tracking
    and the frames processed so far are written, with ``"interrupted": true``.

    Returns:
        The metrics written to ``metrics.json``.

    Raises:
        ConfigError: for a bad ``max_frames`` (before anything is read) or config.
        OutputFolderError: ``out`` is a file, not writable, or not empty (without ``overwrite``).
        OutputWriteError: some output files could not be written; the others were.
    """
    check_max_frames(options.max_frames)
    threads = setup_threads(options.threads, flag_name="--threads")
    allocator = setup_allocator()
    spec = get_system(options.system)
    system_cfg, data_cfg, resolved = resolve_config(options.system, config_path, overrides, params=options.params)
    out = Path(options.out)
    prepare_run_folder(out, overwrite=options.overwrite)
    sequence = load_sequence(options.data, data_cfg, options.device)
    monitor: Monitor = TensorBoardMonitor(out) if options.tensorboard else Monitor()
    try:
        system = spec.build(system_cfg, device=options.device, monitor=monitor)
        on_frame = progress_callback(system, sequence, monitor, every=options.monitor_every) if options.tensorboard else None
        result = run_sequence(system, sequence, progress=progress, max_frames=options.max_frames, on_frame=on_frame)
        resolved["device"] = options.device
        extra = {"device": options.device, "data": options.data, **threads.to_dict(), **allocator.to_dict()}
        if options.params is not None:
            extra["params"] = str(options.params)
        metrics = write_run(out, options.system, result, sequence, config=resolved, extra=extra)
        # The results are on disk; what follows only adds TensorBoard figures.
        if options.tensorboard:
            log_final(monitor, result.output, sequence, f"{options.system} on {sequence.name}")
        log_hparams(monitor, resolved, metrics)
    finally:
        monitor.close()
    return metrics

