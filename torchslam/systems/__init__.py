"""SLAM systems, the loop that drives them, run outputs and monitors."""

from .base import RunResult, SlamSystem, SystemOutput, empty_output, run_sequence
from .monitor import Monitor, TensorBoardMonitor
from .registry import available_systems, get_system

__all__ = [
    "Monitor",
    "RunResult",
    "SlamSystem",
    "SystemOutput",
    "TensorBoardMonitor",
    "available_systems",
    "empty_output",
    "get_system",
    "run_sequence",
]
