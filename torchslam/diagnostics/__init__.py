"""Tools that look at how the library runs rather than at what it computes.

- ``count_syncs`` (``syncs``): every host-device synchronisation a region would make, counted on
  any tensors (the back-end's budgets: all its tensors are device data).
- ``device_audit`` (``device_audit``): a stand-in accelerator on the CPU that tells device data
  from host bookkeeping, counting only the device's read-backs and reporting device/host mixes
  (the systems' budgets and device hygiene).
"""

from .device_audit import DEVICE, DeviceAudit, Event, device_audit, is_on_device, on_device
from .syncs import SyncEvent, SyncKind, SyncReport, count_syncs

__all__ = [
    "DEVICE", "DeviceAudit", "Event", "SyncEvent", "SyncKind", "SyncReport", "count_syncs", "device_audit",
    "is_on_device", "on_device",
]
