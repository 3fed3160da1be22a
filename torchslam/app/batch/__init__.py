"""Many sequences: ``torchslam batch``.

``sources`` expands the command-line sources, ``summary`` builds the rows, totals and summary
files, ``resume`` decides which run folders are done or must not be replaced, ``distributed``
shares the work out under torchrun, and ``runner`` runs the groups.
"""

from .resume import completed_run
from .runner import BatchOptions, BatchResult, GroupRunner, run_batch, run_group, select_engine
from .sources import BatchSource, expand_sources
from .summary import (
    STATUSES,
    SUMMARY_COLUMNS,
    TIMING_COLUMNS,
    TOTAL_TIMING_KEYS,
    format_table,
    loop_count,
    summary_row,
    summary_totals,
)

__all__ = [
    "STATUSES",
    "SUMMARY_COLUMNS",
    "TIMING_COLUMNS",
    "TOTAL_TIMING_KEYS",
    "BatchOptions",
    "BatchResult",
    "BatchSource",
    "GroupRunner",
    "completed_run",
    "expand_sources",
    "format_table",
    "loop_count",
    "run_batch",
    "run_group",
    "select_engine",
    "summary_row",
    "summary_totals",
]
