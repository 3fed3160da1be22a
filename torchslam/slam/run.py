"""Run one system on one sequence and write its run folder: the library behind ``torchslam run``."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..config import config_from_dict, config_to_dict, deep_merge, nest_dotted, parse_overrides
from ..data.frame import Frame, Sequence
from ..data.synthetic import SyntheticConfig, generate_sequence
from ..data.tum import TUMSequence
from ..errors import ConfigError
from ..threads import setup_threads
from .base import run_sequence
from .monitor import Monitor, TensorBoardMonitor
from .outputs import write_run
from .progress import log_final, log_hparams, progress_callback
from .registry import get_system

__all__ = ["DataConfig", "RunOptions", "load_sequence", "resolve_config", "run"]

logger = logging.getLogger(__name__)

SYNTHETIC = "synthetic"


@dataclass(frozen=True)
class DataConfig:
    """How a sequence is read: the ``data:`` section of a run config.

    Attributes:
        stride: use every ``stride``-th frame.
        start: first frame (after association).
        end: one past the last frame, or None for all.
        max_gap: largest colour/depth timestamp gap accepted when associating, seconds.
        prefetch: frames decoded ahead in a background thread (0 = decode inline).
        synthetic: the generator's settings when ``--data synthetic``.
    """

    stride: int = 1
    start: int = 0
    end: int | None = None
    max_gap: float = 0.02
    prefetch: int = 2
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)


@dataclass(frozen=True)
class RunOptions:
    """Everything about a run that is not the system's own config.

    ``params`` is a checkpoint of learned config values (``torchslam.learn.save_checkpoint``)
    applied on top of the config file and below ``--set`` overrides. With ``tensorboard``, the
    ATE so far, running stage times and counters are logged every ``monitor_every`` frames.
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
    threads: int | None = None


def resolve_config(
    system: str,
    config_path: str | os.PathLike | None,
    overrides: Iterable[str],
    params: str | os.PathLike | None = None,
) -> tuple[Any, DataConfig, dict[str, Any]]:
    """Merge the system's defaults, its YAML file, a learned-parameter checkpoint and ``--set`` overrides.

    The YAML file holds the system's keys at the top level and an optional ``data:`` section;
    ``--set data.stride=2`` and ``--set sigma=0.3`` address the two parts. Sections merge key
    by key, so ``--set kcc.sigma=0.3`` keeps the file's other ``kcc`` values. ``params`` (a
    ``torchslam.learn`` checkpoint of config values, e.g. ``kcc.sigma``) is applied after the
    file and before ``--set``; a checkpoint of another system or with unknown keys raises a
    ConfigError naming the file and the key.

    Returns:
        (system config, data config, the resolved config as plain data for ``config.yaml``).
    """
    spec = get_system(system)
    layers: list[tuple[str, dict[str, Any]]] = []
    if config_path is not None:
        path = Path(config_path)
        try:
            loaded = yaml.safe_load(path.read_text())
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read config ({exc.strerror or exc})") from exc
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            loc = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
            raise ConfigError(f"{path}{loc}: malformed YAML ({getattr(exc, 'problem', exc)})") from exc
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level, got {type(loaded).__name__}")
        layers.append((str(path), dict(loaded or {})))
    if params is not None:
        from ..learn.params import (
            checkpoint_values,  # lazy: torch.load and the learn package
        )

        values = checkpoint_values(params, spec.config_cls, system)
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


def load_sequence(data: str, cfg: DataConfig) -> Sequence:
    """Open ``data``: a TUM-layout folder, or ``synthetic`` for the built-in generated sequence."""
    if data == SYNTHETIC:
        return generate_sequence(cfg.synthetic)
    return TUMSequence(data, max_gap=cfg.max_gap, stride=cfg.stride, start=cfg.start, end=cfg.end, prefetch=cfg.prefetch)


def default_out_dir(system: str, data: str, root: str | os.PathLike = "logs") -> Path:
    """``logs/<system>-<data name>-<YYYYmmdd-HHMMSS>``."""
    name = SYNTHETIC if data == SYNTHETIC else Path(data).resolve().name
    return Path(root) / f"{system}-{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def run(
    options: RunOptions,
    config_path: str | os.PathLike | None = None,
    overrides: Iterable[str] = (),
    progress: Callable[[Iterable[Frame]], Iterable[Frame]] | None = None,
) -> dict[str, Any]:
    """Run ``options.system`` on ``options.data`` and write the run folder ``options.out``.

    Returns:
        The metrics written to ``metrics.json``.
    """
    threads = setup_threads(options.threads, flag_name="--threads")
    spec = get_system(options.system)
    system_cfg, data_cfg, resolved = resolve_config(options.system, config_path, overrides, params=options.params)
    sequence = load_sequence(options.data, data_cfg)
    out = Path(options.out)
    monitor: Monitor = TensorBoardMonitor(out) if options.tensorboard else Monitor()
    try:
        system = spec.build(system_cfg, device=options.device, monitor=monitor)
        on_frame = progress_callback(system, sequence, monitor, every=options.monitor_every) if options.tensorboard else None
        result = run_sequence(system, sequence, progress=progress, max_frames=options.max_frames, on_frame=on_frame)
        if options.tensorboard:
            log_final(monitor, result.output, sequence, f"{options.system} on {sequence.name}", result.frames_processed)
        resolved["device"] = options.device
        extra = {"device": options.device, "data": options.data, **threads.to_dict()}
        if options.params is not None:
            extra["params"] = str(options.params)
        metrics = write_run(out, options.system, result, sequence, config=resolved, extra=extra)
        log_hparams(monitor, resolved, metrics)
    finally:
        monitor.close()
    return metrics

