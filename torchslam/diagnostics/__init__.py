"""Diagnostics for running torchslam on accelerators: host-device synchronisation counts."""

from .syncs import SyncEvent, SyncKind, SyncReport, count_syncs

__all__ = ["SyncEvent", "SyncKind", "SyncReport", "count_syncs"]
