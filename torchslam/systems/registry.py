"""The SLAM systems torchslam ships, looked up by name.

Each entry names the module that defines the system and the capabilities the application
switches on (whether it runs in lockstep); a module that is not part of this installation is
simply not available, and ``run`` says so instead of pretending. Code outside ``systems/``
reaches a system through this table, not by importing it (the few system-specific exceptions
are listed in ``tests/test_layers.py``).
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

from ..errors import ConfigError

__all__ = ["DEFAULT_SYSTEM", "KNOWN_SYSTEMS", "SystemEntry", "SystemSpec", "available_systems", "get_system", "spec_for_config"]


@dataclass(frozen=True)
class SystemSpec:
    """How to configure and build one system.

    Attributes:
        name: the name used on the command line (``--system``).
        description: one line for help texts.
        config_cls: the system's frozen config dataclass (defaults in code).
        build: ``build(config, device, monitor) -> SlamSystem``.
        memory: ``memory(config, camera, batch) -> {part: (bytes, settings behind it)}``, the
            system's own peak-memory parts beyond the input images (``systems.memory``), or None.
        lockstep: the system runs in ``systems.lockstep.run_lockstep`` (a group of sequences
            advancing one frame each per step), which ``torchslam batch`` uses for B > 1.
            ``get_system`` sets it where the system's registry entry declares it.
    """

    name: str
    description: str
    config_cls: type
    build: Callable[..., Any]
    memory: Callable[..., dict[str, tuple[int, str]]] | None = None
    lockstep: bool = False


class SystemEntry(NamedTuple):
    """Where a system lives and what it can do.

    Attributes:
        module: the module that defines it.
        attr: the module attribute holding its ``SystemSpec``.
        description: what it is, for messages.
        lockstep: it runs in ``systems.lockstep.run_lockstep`` (see ``SystemSpec.lockstep``).
    """

    module: str
    attr: str
    description: str
    lockstep: bool = False


KNOWN_SYSTEMS: dict[str, SystemEntry] = {
    "nislam": SystemEntry(
        "torchslam.systems.nislam", "SPEC", "NI-SLAM: non-iterative RGB-D-inertial odometry with kernel cross-correlators",
        lockstep=True,
    ),
    "gcslam": SystemEntry(
        "torchslam.systems.gcslam", "SPEC", "GC-SLAM: ORB/dense registration with FastGO global optimisation", lockstep=True
    ),
}

# What ``torchslam run`` and ``torchslam batch`` run without ``--system``.
DEFAULT_SYSTEM = "nislam"


def _module_exists(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def available_systems() -> list[str]:
    """Names of the systems this installation can run."""
    return [name for name, entry in KNOWN_SYSTEMS.items() if _module_exists(entry.module)]


def get_system(name: str) -> SystemSpec:
    """Return the spec of system ``name``, with the capabilities its registry entry declares.

    Raises:
        ConfigError: for an unknown name, or a known system that this version does not include,
            listing the systems that are available.
    """
    avail = available_systems()
    listing = ", ".join(avail) if avail else "none yet"
    if name not in KNOWN_SYSTEMS:
        raise ConfigError(f"--system {name!r}: unknown system; available systems: {listing}")
    if name not in avail:
        raise ConfigError(
            f"--system {name!r}: {KNOWN_SYSTEMS[name].description} is not implemented in this version of torchslam; "
            f"available systems: {listing}"
        )
    entry = KNOWN_SYSTEMS[name]
    spec: SystemSpec = getattr(importlib.import_module(entry.module), entry.attr)
    return replace(spec, lockstep=True) if entry.lockstep and not spec.lockstep else spec


def spec_for_config(cfg: Any) -> SystemSpec:
    """The spec of the available system whose config class ``cfg`` is.

    Raises:
        ConfigError: when no available system owns ``type(cfg)``.
    """
    for name in available_systems():
        spec = get_system(name)
        if type(cfg) is spec.config_cls:
            return spec
    raise ConfigError(f"cfg: {type(cfg).__name__} is the config of no available system ({', '.join(available_systems())})")
