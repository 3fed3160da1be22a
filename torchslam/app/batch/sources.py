"""The sequences of a batch: command-line sources (folders, globs, ``synthetic[:K]``) expanded
into an ordered list of :class:`BatchSource` with unique, file-system-safe names."""

from __future__ import annotations

import glob
import logging
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

from ...data.synthetic import SYNTHETIC_TRAJECTORIES, SyntheticConfig
from ...errors import ConfigError
from ..run import SYNTHETIC, DataConfig

__all__ = ["BatchSource", "expand_sources"]

logger = logging.getLogger(__name__)

# Names in the batch folder that are not run folders.
_RESERVED_NAMES = frozenset({"summary.md", "summary.csv", "summary.json", "report.md", "report"})
_SYNTHETIC_SOURCE = re.compile(r"^synthetic(?::(.*))?$")


@dataclass(frozen=True)
class BatchSource:
    """One sequence of a batch, before it is opened.

    Attributes:
        index: position in the batch (rows and sharding follow it).
        name: unique, file-system-safe name; the run folder is ``<out>/<name>``.
        spec: what the run records as its data: an absolute folder path, or ``"synthetic"``.
        source: the command-line source it came from (``synthetic:4``, a glob, a folder).
        synthetic: the generator's settings for a synthetic sequence, else None.
        error: why the source yields no sequence (a glob that matches no folder), else None.
    """

    index: int
    name: str
    spec: str
    source: str
    synthetic: SyntheticConfig | None = None
    error: str | None = None


def _safe_name(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    return s or "sequence"


def _synthetic_variant(base: SyntheticConfig, j: int) -> SyntheticConfig:
    """The ``j``-th generated sequence: seed ``base.seed + j``, trajectory kind and length cycled.

    Sequence 0 is ``base`` itself (what ``torchslam run --data synthetic`` runs); the kinds cycle
    through ``SYNTHETIC_TRAJECTORIES`` from ``base.trajectory`` and the lengths through
    ``base.frames`` minus 0, 1, 2, 3 eighths, so a batch mixes motions and lengths.
    """
    kinds = SYNTHETIC_TRAJECTORIES
    kind = kinds[(kinds.index(base.trajectory) + j) % len(kinds)]
    step = max(1, base.frames // 8)
    frames = max(min(base.frames, 2), base.frames - (j % 4) * step)
    return replace(base, seed=base.seed + j, trajectory=kind, frames=frames)


def expand_sources(sources: Iterable[str], data_cfg: DataConfig) -> list[BatchSource]:
    """Turn command-line sources into the batch's ordered list of sequences.

    ``synthetic`` is one generated sequence with ``data_cfg.synthetic``; ``synthetic:K`` is K of
    them with distinct seeds (see :func:`_synthetic_variant`; numbering continues across
    several ``synthetic:K`` sources). A pattern with ``*``, ``?`` or ``[`` expands to the folders
    it matches, sorted (a pattern matching none is kept as a source that fails). Anything else is
    a sequence folder; whether it is one is found out when it is opened. A folder listed twice
    is run once.

    Raises:
        ConfigError: no sources, or ``synthetic:K`` with K not an integer >= 1.
    """
    sources = list(sources)
    if not sources:
        raise ConfigError("SOURCES: expected at least one sequence folder, glob or synthetic:K")
    entries: list[tuple[str, str, SyntheticConfig | None, str | None]] = []  # (name, spec, synthetic, error)
    origins: list[str] = []
    seen: set[str] = set()
    n_synthetic = 0
    for src in sources:
        if not isinstance(src, str) or not src:
            raise ConfigError(f"SOURCES: expected non-empty strings, got {src!r}")
        m = _SYNTHETIC_SOURCE.match(src)
        if m:
            count = 1
            if m.group(1) is not None:
                try:
                    count = int(m.group(1))
                except ValueError:
                    count = 0
                if count < 1:
                    raise ConfigError(f"SOURCES: {src!r}: expected synthetic:K with K an integer >= 1")
            for _ in range(count):
                cfg = _synthetic_variant(data_cfg.synthetic, n_synthetic)
                n_synthetic += 1
                entries.append((f"synthetic-{cfg.trajectory}-seed{cfg.seed}", SYNTHETIC, cfg, None))
                origins.append(src)
            continue
        if glob.has_magic(src):
            folders = sorted(p for p in glob.glob(os.path.expanduser(src)) if os.path.isdir(p))
            if not folders:
                entries.append((Path(src).name, src, None, f"{src}: the pattern matches no folder"))
                origins.append(src)
            paths = folders
        else:
            paths = [os.path.expanduser(src)]
        for p in paths:
            spec = str(Path(p).resolve())
            if spec in seen:
                logger.warning("%s is listed more than once; running it once", spec)
                continue
            seen.add(spec)
            entries.append((Path(spec).name, spec, None, None))
            origins.append(src)
    out: list[BatchSource] = []
    used: set[str] = set()
    for i, ((name, spec, syn, err), origin) in enumerate(zip(entries, origins)):
        base = _safe_name(name)
        unique, k = base, 2
        while unique in used or unique in _RESERVED_NAMES:
            unique, k = f"{base}-{k}", k + 1
        used.add(unique)
        out.append(BatchSource(index=i, name=unique, spec=spec, source=origin, synthetic=syn, error=err))
    return out

