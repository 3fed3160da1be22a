"""Tools that look at how the library runs rather than at what it computes (device audits)."""

from .device_audit import DEVICE, DeviceAudit, Event, device_audit, is_on_device, on_device

__all__ = ["DEVICE", "DeviceAudit", "Event", "device_audit", "is_on_device", "on_device"]
