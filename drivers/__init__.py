"""Device drivers: one interface per device kind, backends by URL scheme.

``open_drive``, ``open_tracker``, ``open_controller``, ``open_guidance`` and
``open_force_sensor`` pick the backend for a
URL scheme from the lazy tables below (like python-can's interface table: a
backend module is imported only when a URL uses it). Backends of other
packages come in through entry points, named by their URL scheme, in the
groups of :data:`ENTRY_POINT_GROUPS` (``elastocal.drives``,
``elastocal.trackers``; docs/devices.md shows an adapter): like python-can's
``can.interface`` plugins, they are looked up only when a URL's scheme is not
built in, and a package can add schemes but not replace the built-in ones.
:func:`open_cell` opens
every device of a :class:`~elastocal.drivers.config.CellConfig` together,
sharing one CAN network per channel and one Modbus link per endpoint.
"""

from __future__ import annotations

import importlib
import importlib.metadata
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
#: the robot controller's real-time guidance channel (elastocal.drivers.guidance)
GUIDANCE_BACKENDS = MappingProxyType({
    "egm": ("elastocal.drivers.egm", "EgmGuidance"),
    "rsi": ("elastocal.drivers.rsi", "RsiGuidance"),
})
#: force/torque sensors (elastocal.drivers.force)
FORCE_BACKENDS = MappingProxyType({
    "netft": ("elastocal.drivers.force", "NetFtSensor"),
})


#: URL scheme -> (module, class) of the frozen parameters its backend reads from the URL, parsed
#: once with the URL (drivers.urls; ``url.settings``); light modules, so that reading a cell.toml
#: imports no device library
URL_PARAMS = MappingProxyType({
    "canopen": ("elastocal.drivers.url_params", "CanopenParams"),
    "modbus+tcp": ("elastocal.drivers.url_params", "ModbusTcpParams"),
    "modbus+rtu": ("elastocal.drivers.url_params", "ModbusRtuParams"),
    "tracker+tcp": ("elastocal.drivers.url_params", "TrackerTcpParams"),
    "tracker+serial": ("elastocal.drivers.url_params", "TrackerSerialParams"),
    "tracker+emscon": ("elastocal.drivers.url_params", "EmsconParams"),
    "egm": ("elastocal.drivers.guidance", "GuidanceParams"),
    "rsi": ("elastocal.drivers.guidance", "GuidanceParams"),
    "netft": ("elastocal.drivers.force", "NetFtParams"),
})


#: device kind -> entry-point group where other packages register backends (name = URL scheme,
#: value = "module:Class", the class built like the built-in ones: ``Class(config, links=links)``)
ENTRY_POINT_GROUPS = MappingProxyType({"drive": "elastocal.drives", "tracker": "elastocal.trackers"})


def plugin_entry_points(kind: str) -> dict[str, list]:
    """URL scheme -> the installed entry points registering a ``kind`` backend for it (built-in
    schemes left out: they cannot be replaced). Read from the installed packages on every call."""
    group = ENTRY_POINT_GROUPS.get(kind)
    if group is None:
        return {}
    builtin = {"drive": DRIVE_BACKENDS, "tracker": TRACKER_BACKENDS}[kind]
    out: dict[str, list] = {}
    for ep in importlib.metadata.entry_points(group=group):
        scheme = ep.name.strip().lower()
        if scheme and scheme not in builtin and all(e.value != ep.value for e in out.get(scheme, [])):
            out.setdefault(scheme, []).append(ep)
    return out


def _plugin(scheme: str, kind: str):
    eps = plugin_entry_points(kind).get(scheme)
    if not eps:
        return None
    if len(eps) > 1:
        raise InputError(f"{scheme}:// is registered as a {kind} backend by several installed packages: "
                         + ", ".join(f"{_dist_name(e)} ({e.value})" for e in eps) + "; uninstall all but one")
    ep = eps[0]
    try:
        cls = ep.load()
    except Exception as exc:  # noqa: BLE001 - any import failure of an outside package is reported in one line
        raise InputError(f"the {kind} backend {scheme}:// of {_dist_name(ep)} ({ep.value}) cannot be loaded: "
                         f"{type(exc).__name__}: {exc}") from None
    from elastocal.drivers.base import Drive, Tracker

    base = {"drive": Drive, "tracker": Tracker}[kind]
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise InputError(f"the {kind} backend {scheme}:// of {_dist_name(ep)} ({ep.value}) is not a subclass of "
                         f"elastocal.drivers.base.{base.__name__}")
    return cls


def _dist_name(ep) -> str:
    dist = getattr(ep, "dist", None)
    return f"package {dist.name}" if dist is not None else "an installed package"


def backend(table, scheme: str, kind: str):
    """The backend class for ``scheme`` in ``table`` (imported on first use), else the one an
    installed package registers for it by entry point (:data:`ENTRY_POINT_GROUPS`)."""
    if scheme in table:
        module_name, class_name = table[scheme]
        return getattr(importlib.import_module(module_name), class_name)
    cls = _plugin(scheme, kind)
    if cls is None:
        known = sorted(set(table) | set(plugin_entry_points(kind)))
        raise InputError(f"no {kind} backend for {scheme}://; one of {', '.join(known)}")
    return cls


def open_drive(config, *, links=None):
    """Open the drive of a :class:`~elastocal.drivers.config.DriveConfig`."""
    return backend(DRIVE_BACKENDS, config.url.scheme, "drive")(config, links=links)


def open_tracker(config, *, links=None):
    """Open the tracker of a :class:`~elastocal.drivers.config.TrackerConfig`."""
    return backend(TRACKER_BACKENDS, config.url.scheme, "tracker")(config, links=links)


def open_controller(config, *, links=None):
    """Open the controller of a :class:`~elastocal.drivers.config.ControllerConfig`."""
    return backend(CONTROLLER_BACKENDS, config.url.scheme, "controller")(config, links=links)


def open_guidance(url, *, n_joints: int, source: str = "url"):
    """Listen for the robot controller's guidance channel at ``url`` (a parsed
    :class:`~elastocal.drivers.urls.DeviceUrl`; ``egm://`` or ``rsi://``) for a robot of ``n_joints``."""
    return backend(GUIDANCE_BACKENDS, url.scheme, "guidance")(url, n_joints=n_joints, source=source)


def open_force_sensor(url, *, source: str = "url"):
    """Open the force/torque sensor at ``url`` (``netft://``); :meth:`start` begins its stream."""
    return backend(FORCE_BACKENDS, url.scheme, "force sensor")(url, source=source)


def open_cell(config):
    """Open every device of a cell; see :class:`elastocal.drivers.cell.CellDevices`."""
    from elastocal.drivers.cell import CellDevices

    return CellDevices.open(config)
