"""Device drivers: one interface per device kind, backends by URL scheme.

``open_drive``, ``open_tracker`` and ``open_controller`` pick the backend for a
URL scheme from the lazy tables below (like python-can's interface table: a
backend module is imported only when a URL uses it). :func:`open_cell` opens
every device of a :class:`~elastocal.drivers.config.CellConfig` together,
sharing one CAN network per channel and one Modbus link per endpoint.
"""

from __future__ import annotations

import importlib
from types import MappingProxyType

from elastocal.errors import InputError

#: URL scheme -> (module, class) per device kind
DRIVE_BACKENDS = MappingProxyType({
    "canopen": ("elastocal.drivers.canopen_drive", "CanopenDrive"),
    "modbus+tcp": ("elastocal.drivers.modbus_drive", "ModbusDrive"),
    "modbus+rtu": ("elastocal.drivers.modbus_drive", "ModbusDrive"),
})
TRACKER_BACKENDS = MappingProxyType({
    "tracker+tcp": ("elastocal.drivers.tracker", "LineTracker"),
    "tracker+serial": ("elastocal.drivers.tracker", "LineTracker"),
    "tracker+emscon": ("elastocal.drivers.emscon", "EmsconTracker"),
})
CONTROLLER_BACKENDS = MappingProxyType({
    "modbus+tcp": ("elastocal.drivers.controller", "ModbusCellController"),
    "modbus+rtu": ("elastocal.drivers.controller", "ModbusCellController"),
})


def backend(table, scheme: str, kind: str):
    """The backend class for ``scheme`` in ``table`` (imported on first use)."""
    try:
        module_name, class_name = table[scheme]
    except KeyError:
        raise InputError(f"no {kind} backend for {scheme}://; one of {', '.join(sorted(table))}") from None
    return getattr(importlib.import_module(module_name), class_name)


def open_drive(config, *, links=None):
    """Open the drive of a :class:`~elastocal.drivers.config.DriveConfig`."""
    return backend(DRIVE_BACKENDS, config.url.scheme, "drive")(config, links=links)


def open_tracker(config, *, links=None):
    """Open the tracker of a :class:`~elastocal.drivers.config.TrackerConfig`."""
    return backend(TRACKER_BACKENDS, config.url.scheme, "tracker")(config, links=links)


def open_controller(config, *, links=None):
    """Open the controller of a :class:`~elastocal.drivers.config.ControllerConfig`."""
    return backend(CONTROLLER_BACKENDS, config.url.scheme, "controller")(config, links=links)


def open_cell(config):
    """Open every device of a cell; see :class:`elastocal.drivers.cell.CellDevices`."""
    from elastocal.drivers.cell import CellDevices

    return CellDevices.open(config)
