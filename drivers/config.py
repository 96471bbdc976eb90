"""The cell configuration (``cell.toml``) resolved into frozen dataclasses.

``cell.toml`` names every device of a calibration cell by a URL
(docs/cell-config.md)::

    canopen://virtual/cell?node=5            CiA 402 drive on a python-can bus
    modbus+tcp://127.0.0.1:1502?unit=1       Modbus TCP drive or cell controller
    modbus+rtu:///dev/pts/3?baud=115200&unit=1
    tracker+tcp://127.0.0.1:7000             laser tracker, line protocol over TCP
    tracker+serial:///dev/ttyUSB0?baud=115200

:func:`load_cell_config` reads the file once; every value is validated here,
so errors name the file and the key. Nothing in this module does I/O on a
device.
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, field, replace
from typing import Any, Mapping
from urllib.parse import parse_qsl, urlsplit

from elastocal.errors import InputError, check_known_keys
from elastocal.textfiles import read_text_file

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

N_JOINTS = 6

#: URL schemes per device kind (the backends live in the lazy tables of drivers/__init__.py)
DRIVE_SCHEMES = ("canopen", "modbus+tcp", "modbus+rtu")
TRACKER_SCHEMES = ("tracker+tcp", "tracker+serial")
CONTROLLER_SCHEMES = ("modbus+tcp", "modbus+rtu")

#: register value types and their size in 16-bit registers
REGISTER_TYPES = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2, "float64": 4}
#: unit -> (quantity, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "A": ("current", 1.0), "mA": ("current", 1e-3),
    "rad": ("angle", 1.0), "mrad": ("angle", 1e-3), "urad": ("angle", 1e-6),
    "deg": ("angle", math.pi / 180.0),
    "rad/s": ("angular_velocity", 1.0), "mrad/s": ("angular_velocity", 1e-3),
    "deg/s": ("angular_velocity", math.pi / 180.0),
    "N*m": ("torque", 1.0), "1": ("count", 1.0),
}
#: quantity each named drive register must have
DRIVE_REGISTER_QUANTITY = {"current": "current", "position": "angle", "velocity": "angular_velocity",
                           "torque": "torque", "status": "count"}
#: registers of the cell-controller handshake (docs/cell-config.md)
CONTROLLER_REGISTERS = {
    # name: (quantity, may elastocal write it, count); every register is read unless the config
    # declares it `access = "write"` (the app writes only what a person declared writable)
    "command": ("count", True, 1), "sequence": ("count", True, 1), "pose": ("count", True, 1),
    "path": ("count", True, 1), "speed": ("angular_velocity", True, 1), "target": ("angle", True, 6),
    "ack": ("count", False, 1), "status": ("count", False, 1), "error": ("count", False, 1),
    "q": ("angle", False, 6),
}
CONTROLLER_REQUIRED = ("command", "sequence", "ack", "status")
HIDDEN_EFFECTS = ("none", "link_compliance", "thermal_drift", "static_friction", "backlash")


# ------------------------------------------------------------------- URLs
@dataclass(frozen=True)
class DeviceUrl:
    """A parsed device URL. ``host`` is the CAN interface for ``canopen``;
    ``path`` the CAN channel, serial device or empty; ``params`` the query."""

    text: str
    scheme: str
    host: str
    port: int | None
    path: str
    params: tuple[tuple[str, str], ...] = ()

    def param(self, key: str, default: str | None = None) -> str | None:
        for k, v in self.params:
            if k == key:
                return v
        return default

    def int_param(self, key: str, default: int, *, source: str = "url", low: int = 0,
                  high: int = 2**31) -> int:
        raw = self.param(key)
        if raw is None:
            return default
        try:
            value = int(raw, 0)
        except ValueError:
            raise InputError(f"{key}={raw!r} is not an integer in {self.text}", source=source) from None
        if not low <= value <= high:
            raise InputError(f"{key}={value} is outside {low}..{high} in {self.text}", source=source)
        return value

    def float_param(self, key: str, default: float, *, source: str = "url") -> float:
        raw = self.param(key)
        if raw is None:
            return default
        try:
            value = float(raw)
        except ValueError:
            raise InputError(f"{key}={raw!r} is not a number in {self.text}", source=source) from None
        if not math.isfinite(value) or value <= 0:
            raise InputError(f"{key}={raw} must be a positive number in {self.text}", source=source)
        return value

    # --------------------------------------------------------- per scheme
    @property
    def can_interface(self) -> str:
        return self.host

    @property
    def can_channel(self) -> str:
        return self.path.lstrip("/")

    def with_port(self, port: int) -> "DeviceUrl":
        """The same URL with another TCP port (used for ephemeral ports)."""
        query = "&".join(f"{k}={v}" for k, v in self.params)
        text = f"{self.scheme}://{self.host}:{port}{self.path}" + (f"?{query}" if query else "")
        return replace(self, text=text, port=port)

    def with_path(self, path: str) -> "DeviceUrl":
        """The same URL with another path (serial device or CAN channel)."""
        query = "&".join(f"{k}={v}" for k, v in self.params)
        netloc = self.host + (f":{self.port}" if self.port is not None else "")
        if not path.startswith("/"):
            path = "/" + path
        text = f"{self.scheme}://{netloc}{path}" + (f"?{query}" if query else "")
        return replace(self, text=text, path=path)

    def with_param(self, key: str, value) -> "DeviceUrl":
        """The same URL with the query parameter ``key`` set to ``value`` (added or replaced)."""
        params = tuple((k, v) for k, v in self.params if k != key) + ((key, str(value)),)
        query = "&".join(f"{k}={v}" for k, v in params)
        netloc = self.host + (f":{self.port}" if self.port is not None else "")
        return replace(self, text=f"{self.scheme}://{netloc}{self.path}?{query}", params=params)

    def with_host(self, host: str) -> "DeviceUrl":
        query = "&".join(f"{k}={v}" for k, v in self.params)
        netloc = host + (f":{self.port}" if self.port is not None else "")
        text = f"{self.scheme}://{netloc}{self.path}" + (f"?{query}" if query else "")
        return replace(self, text=text, host=host)

    def __str__(self) -> str:
        return self.text


def parse_device_url(text: str, *, allowed: tuple[str, ...] | None = None,
                     source: str = "url") -> DeviceUrl:
    """Parse and check a device URL (see the module docstring)."""
    if not isinstance(text, str) or "://" not in text:
        raise InputError(f"expected a device URL like modbus+tcp://127.0.0.1:1502?unit=1, got {text!r}",
                         source=source)
    parts = urlsplit(text)
    scheme = parts.scheme.lower()
    known = DRIVE_SCHEMES + TRACKER_SCHEMES
    if scheme not in known:
        raise InputError(f"unknown device scheme {scheme!r} in {text}; one of {', '.join(sorted(set(known)))}",
                         source=source)
    if allowed is not None and scheme not in allowed:
        raise InputError(f"{scheme}:// cannot be used here; expected one of {', '.join(allowed)}", source=source)
    try:
        port = parts.port
    except ValueError:
        raise InputError(f"bad port in {text}", source=source) from None
    params = tuple(parse_qsl(parts.query, keep_blank_values=True))
    url = DeviceUrl(text=text, scheme=scheme, host=parts.hostname or "", port=port, path=parts.path,
                    params=params)
    if scheme == "canopen":
        if not url.host:
            raise InputError(f"{text}: give the python-can interface, e.g. canopen://virtual/cell?node=5",
                             source=source)
        if not url.can_channel:
            raise InputError(f"{text}: give the CAN channel after the interface, e.g. canopen://virtual/cell?node=5",
                             source=source)
        if url.param("node") is None:
            raise InputError(f"{text}: the node id is missing (?node=1..127)", source=source)
        url.int_param("node", 0, source=source, low=1, high=127)
        url.int_param("bitrate", 1_000_000, source=source, low=10_000, high=1_000_000)
    elif scheme in ("modbus+tcp", "tracker+tcp"):
        if not url.host or url.port is None:
            raise InputError(f"{text}: give host and port, e.g. {scheme}://127.0.0.1:1502", source=source)
        if scheme == "modbus+tcp":
            url.int_param("unit", 1, source=source, low=0, high=247)
    else:  # serial
        if not url.path:
            raise InputError(f"{text}: give the serial device, e.g. {scheme}:///dev/ttyUSB0?baud=115200",
                             source=source)
        url.int_param("baud", 115200, source=source, low=300, high=10_000_000)
        if scheme == "modbus+rtu":
            url.int_param("unit", 1, source=source, low=1, high=247)
    return url


# -------------------------------------------------------------- registers
@dataclass(frozen=True)
class RegisterSpec:
    """One Modbus value: ``value_SI = raw * scale * unit_factor``."""

    name: str
    address: int
    type: str = "uint16"
    count: int = 1
    scale: float = 1.0
    unit: str = "1"
    table: str = "holding"          # "holding" or "input"
    access: str = "read"            # "read" or "write"
    word_order: str = "big"
    fault_mask: int = 0             # status registers: bits meaning "fault"
    ready_mask: int = 0             # status registers: bits that must be set for valid data

    @property
    def n_registers(self) -> int:
        return REGISTER_TYPES[self.type] * self.count

    @property
    def si_factor(self) -> float:
        return self.scale * UNITS[self.unit][1]

    @property
    def quantity(self) -> str:
        return UNITS[self.unit][0]


def _register(name: str, table: Mapping[str, Any], *, source: str, where: str,
              default_access: str = "read", default_count: int = 1) -> RegisterSpec:
    col = f"{where}.{name}"
    if not isinstance(table, Mapping):
        raise InputError("expected an inline table {address = ..., type = ...}", source=source, column=col)
    check_known_keys(table, ("address", "type", "count", "scale", "unit", "table", "access", "word_order",
                             "fault_mask", "ready_mask"), source=source, where=col)
    address = table.get("address")
    if isinstance(address, bool) or not isinstance(address, int) or not 0 <= address <= 65535:
        raise InputError(f"address must be an integer 0..65535, got {address!r}", source=source, column=col)
    rtype = table.get("type", "uint16")
    if rtype not in REGISTER_TYPES:
        raise InputError(f"type must be one of {', '.join(REGISTER_TYPES)}, got {rtype!r}", source=source, column=col)
    count = table.get("count", default_count)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise InputError(f"count must be a positive integer, got {count!r}", source=source, column=col)
    scale = table.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale == 0:
        raise InputError(f"scale must be a finite non-zero number, got {scale!r}", source=source, column=col)
    unit = table.get("unit", "1")
    if unit not in UNITS:
        raise InputError(f"unit must be one of {', '.join(UNITS)}, got {unit!r}", source=source, column=col)
    kind = table.get("table", "holding")
    if kind not in ("holding", "input"):
        raise InputError(f"table must be 'holding' or 'input', got {kind!r}", source=source, column=col)
    access = table.get("access", default_access)
    if access not in ("read", "write"):
        raise InputError(f"access must be 'read' or 'write', got {access!r}", source=source, column=col)
    if access == "write" and kind != "holding":
        raise InputError("only holding registers can be written", source=source, column=col)
    word_order = table.get("word_order", "big")
    if word_order not in ("big", "little"):
        raise InputError(f"word_order must be 'big' or 'little', got {word_order!r}", source=source, column=col)
    masks = {}
    for key in ("fault_mask", "ready_mask"):
        m = table.get(key, 0)
        if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= 0xFFFF:
            raise InputError(f"{key} must be an integer 0..0xFFFF", source=source, column=col)
        masks[key] = m
    if address + REGISTER_TYPES[rtype] * count - 1 > 65535:
        raise InputError("register block runs past address 65535", source=source, column=col)
    return RegisterSpec(name=name, address=address, type=rtype, count=count, scale=float(scale), unit=unit,
                        table=kind, access=access, word_order=word_order, **masks)


def _check_overlaps(specs: tuple[RegisterSpec, ...], *, source: str, where: str) -> None:
    taken: dict[tuple[str, int], str] = {}
    for spec in specs:
        for a in range(spec.address, spec.address + spec.n_registers):
            key = (spec.table, a)
            if key in taken:
                raise InputError(f"register {a} is used by both {taken[key]} and {spec.name}",
                                 source=source, column=f"{where}.{spec.name}")
            taken[key] = spec.name


# ---------------------------------------------------------------- devices
@dataclass(frozen=True)
class DriveConfig:
    """One joint drive. ``registers`` only for Modbus drives."""

    joint: int
    url: DeviceUrl
    registers: tuple[RegisterSpec, ...] = ()
    rate_hz: float = 1000.0
    timeout_s: float = 0.5
    retries: int = 2
    max_current_a: float = 200.0

    def register(self, name: str) -> RegisterSpec | None:
        return next((r for r in self.registers if r.name == name), None)

    @property
    def name(self) -> str:
        return f"drive J{self.joint}"


@dataclass(frozen=True)
class TrackerConfig:
    url: DeviceUrl
    markers: tuple[str, ...]
    rate_hz: float = 100.0
    timeout_s: float = 1.0
    retries: int = 2
    #: where the tracker head stands, robot base coordinates [m] (optional; used by
    #: `elastocal plan` to keep only poses whose markers it can see)
    base_p_tracker: tuple[float, float, float] | None = None

    @property
    def name(self) -> str:
        return "tracker"


@dataclass(frozen=True)
class PathSpec:
    """A path taught on the controller: a straight joint-space line from ``u`` to ``v``."""

    id: int
    u: tuple[float, ...]
    v: tuple[float, ...]
    speed_rad_s: float


@dataclass(frozen=True)
class ControllerConfig:
    url: DeviceUrl
    registers: tuple[RegisterSpec, ...]
    poses: tuple[tuple[int, tuple[float, ...]], ...] = ()
    paths: tuple[PathSpec, ...] = ()
    timeout_s: float = 0.5
    retries: int = 2
    move_timeout_s: float = 120.0

    def register(self, name: str) -> RegisterSpec | None:
        return next((r for r in self.registers if r.name == name), None)

    def pose(self, number: int) -> tuple[float, ...]:
        for n, q in self.poses:
            if n == number:
                return q
        raise InputError(f"pose {number} is not in [controller.poses]")

    def path(self, number: int) -> PathSpec:
        for p in self.paths:
            if p.id == number:
                return p
        raise InputError(f"path {number} is not in [[controller.path]]")

    @property
    def name(self) -> str:
        return "controller"


@dataclass(frozen=True)
class SimConfig:
    """Parameters of the simulated cell (``elastocal sim serve``)."""

    seed: int = 0
    hidden: str = "none"
    start_q: tuple[float, ...] = (0.0, 0.2, -0.4, 0.0, 0.5, 0.0)
    move_speed_rad_s: float = 0.5
    run_speed_rad_s: float = 0.05
    coulomb_nm: tuple[float, ...] = (40.0, 90.0, 70.0, 12.0, 10.0, 6.0)
    viscous_nm_s_rad: tuple[float, ...] = (300.0, 600.0, 450.0, 60.0, 50.0, 30.0)
    load_friction: tuple[float, ...] = (0.02, 0.02, 0.02, 0.03, 0.03, 0.03)
    tracker_noise_m: float = 10e-6
    current_noise_a: float = 0.02
    gear_ratios: tuple[float, ...] = (150.0, 160.0, 140.0, 80.0, 80.0, 60.0)
    can_reply_delay_s: float = 50e-6
    modbus_reply_delay_s: float = 0.0
    tracker_reply_delay_s: float = 0.0


@dataclass(frozen=True)
class CellConfig:
    """A whole cell, resolved from ``cell.toml``."""

    name: str
    robot: str                              # "hh150" (bundled) or a path
    drives: tuple[DriveConfig, ...]
    tracker: TrackerConfig | None = None
    controller: ControllerConfig | None = None
    history: pathlib.Path | None = None
    sim: SimConfig = field(default_factory=SimConfig)
    plan: pathlib.Path | None = None        # the cell's calibration plan (default for `calibrate --plan`)
    source: str = "<cell.toml>"
    base_dir: pathlib.Path | None = None

    def drive(self, joint: int) -> DriveConfig:
        for d in self.drives:
            if d.joint == joint:
                return d
        raise InputError(f"no [[drive]] for joint {joint}", source=self.source)

    def robot_path(self) -> pathlib.Path:
        """The robot description file this cell uses."""
        from elastocal.identify.robot import bundled_robot_path

        if self.robot in ("hh150",) or ("/" not in self.robot and not self.robot.endswith(".toml")):
            path = bundled_robot_path(self.robot)
            if not path.exists():
                raise InputError(f"no bundled robot named {self.robot!r}", source=self.source, column="cell.robot")
            return path
        path = pathlib.Path(self.robot)
        if not path.is_absolute() and self.base_dir is not None:
            path = self.base_dir / path
        return path

    def load_robot(self):
        """The :class:`~elastocal.identify.robot.Robot` named by ``[cell] robot``."""
        from elastocal.identify.robot import load_robot

        return load_robot(self.robot_path())

    def to_toml(self) -> str:
        """The configuration as cell.toml text (round-trips through :func:`parse_cell_config`)."""
        return _to_toml(self)


# ---------------------------------------------------------------- parsing
def _num(table: Mapping, key: str, default: float, *, source: str, where: str, positive: bool = True) -> float:
    if key not in table:
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"expected a finite number, got {v!r}", source=source, column=f"{where}.{key}")
    if positive and v <= 0:
        raise InputError(f"must be > 0, got {v!r}", source=source, column=f"{where}.{key}")
    return float(v)


def _int(table: Mapping, key: str, default: int, *, source: str, where: str, low: int = 0) -> int:
    if key not in table:
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise InputError(f"expected an integer >= {low}, got {v!r}", source=source, column=f"{where}.{key}")
    return v


def _vec(table: Mapping, key: str, default: tuple[float, ...] | None, *, source: str, where: str,
         n: int = N_JOINTS, nonneg: bool = False) -> tuple[float, ...]:
    if key not in table:
        if default is None:
            raise InputError("missing required key", source=source, column=f"{where}.{key}")
        return default
    v = table[key]
    try:
        out = tuple(float(x) for x in v if not isinstance(x, bool))
    except (TypeError, ValueError):
        raise InputError(f"expected a list of {n} numbers, got {v!r}", source=source, column=f"{where}.{key}") from None
    if len(out) != n or len(out) != len(v) or not all(math.isfinite(x) for x in out):
        raise InputError(f"expected {n} finite numbers, got {v!r}", source=source, column=f"{where}.{key}")
    if nonneg and any(x < 0 for x in out):
        raise InputError("values must be >= 0", source=source, column=f"{where}.{key}")
    return out


def _drive(t: Mapping, i: int, *, source: str) -> DriveConfig:
    where = f"drive[{i}]"
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    check_known_keys(t, ("joint", "url", "registers", "rate_hz", "timeout_s", "retries", "max_current_a"),
                source=source, where=where)
    joint = t.get("joint")
    if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= N_JOINTS:
        raise InputError(f"joint must be 1..{N_JOINTS}, got {joint!r}", source=source, column=f"{where}.joint")
    if "url" not in t:
        raise InputError("missing required key", source=source, column=f"{where}.url")
    url = parse_device_url(t["url"], allowed=DRIVE_SCHEMES, source=f"{source}, {where}.url")
    regs: tuple[RegisterSpec, ...] = ()
    if url.scheme.startswith("modbus"):
        table = t.get("registers")
        if not isinstance(table, Mapping):
            raise InputError("a Modbus drive needs a [drive.registers] map with current and position",
                             source=source, column=f"{where}.registers")
        specs = []
        for name, spec_table in table.items():
            if name not in DRIVE_REGISTER_QUANTITY:
                raise InputError(f"unknown drive register {name!r}; one of {', '.join(DRIVE_REGISTER_QUANTITY)}",
                                 source=source, column=f"{where}.registers.{name}")
            spec = _register(name, spec_table, source=source, where=f"{where}.registers")
            want = DRIVE_REGISTER_QUANTITY[name]
            if spec.quantity != want:
                raise InputError(f"unit {spec.unit!r} is not a unit of {want.replace('_', ' ')}",
                                 source=source, column=f"{where}.registers.{name}")
            if spec.count != 1:
                raise InputError("drive registers hold one value (count = 1)", source=source,
                                 column=f"{where}.registers.{name}")
            if spec.access != "read":
                raise InputError("elastocal only reads drive registers (access = 'read')", source=source,
                                 column=f"{where}.registers.{name}")
            specs.append(spec)
        names = {s.name for s in specs}
        for need in ("current", "position"):
            if need not in names:
                raise InputError(f"missing the {need} register", source=source, column=f"{where}.registers")
        regs = tuple(specs)
        _check_overlaps(regs, source=source, where=f"{where}.registers")
    elif "registers" in t:
        raise InputError("registers are only for modbus drives", source=source, column=f"{where}.registers")
    default_rate = 1000.0 if url.scheme == "canopen" else 100.0
    return DriveConfig(joint=joint, url=url, registers=regs,
                       rate_hz=_num(t, "rate_hz", default_rate, source=source, where=where),
                       timeout_s=_num(t, "timeout_s", 0.5, source=source, where=where),
                       retries=_int(t, "retries", 2, source=source, where=where),
                       max_current_a=_num(t, "max_current_a", 200.0, source=source, where=where))


def _tracker(t: Mapping, *, source: str) -> TrackerConfig:
    where = "tracker"
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    check_known_keys(t, ("url", "markers", "rate_hz", "timeout_s", "retries", "base_p_tracker"), source=source,
                where=where)
    if "url" not in t:
        raise InputError("missing required key", source=source, column="tracker.url")
    base_p_tracker = None
    if "base_p_tracker" in t:
        v = t["base_p_tracker"]
        ok = (isinstance(v, list) and len(v) == 3
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v))
        if not ok:
            raise InputError(f"expected 3 finite numbers [m], got {v!r}", source=source,
                             column="tracker.base_p_tracker")
        base_p_tracker = tuple(float(x) for x in v)
    url = parse_device_url(t["url"], allowed=TRACKER_SCHEMES, source=f"{source}, tracker.url")
    markers = t.get("markers", [])
    if not isinstance(markers, list) or not markers or not all(isinstance(m, str) and m for m in markers):
        raise InputError("markers must be a non-empty list of marker names", source=source, column="tracker.markers")
    if len(set(markers)) != len(markers):
        raise InputError("marker names repeat", source=source, column="tracker.markers")
    return TrackerConfig(url=url, markers=tuple(markers),
                         rate_hz=_num(t, "rate_hz", 100.0, source=source, where=where),
                         timeout_s=_num(t, "timeout_s", 1.0, source=source, where=where),
                         retries=_int(t, "retries", 2, source=source, where=where),
                         base_p_tracker=base_p_tracker)


def _controller(t: Mapping, *, source: str) -> ControllerConfig:
    where = "controller"
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    check_known_keys(t, ("url", "registers", "poses", "path", "timeout_s", "retries", "move_timeout_s"),
                source=source, where=where)
    if "url" not in t:
        raise InputError("missing required key", source=source, column="controller.url")
    url = parse_device_url(t["url"], allowed=CONTROLLER_SCHEMES, source=f"{source}, controller.url")
    table = t.get("registers")
    if not isinstance(table, Mapping):
        raise InputError("missing [controller.registers]", source=source, column="controller.registers")
    specs = []
    for name, spec_table in table.items():
        if name not in CONTROLLER_REGISTERS:
            raise InputError(f"unknown controller register {name!r}; one of {', '.join(CONTROLLER_REGISTERS)}",
                             source=source, column=f"controller.registers.{name}")
        quantity, writable, count = CONTROLLER_REGISTERS[name]
        spec = _register(name, spec_table, source=source, where="controller.registers", default_access="read",
                         default_count=count)
        if spec.quantity != quantity:
            raise InputError(f"unit {spec.unit!r} is not a unit of {quantity.replace('_', ' ')}",
                             source=source, column=f"controller.registers.{name}")
        if spec.count != count:
            raise InputError(f"{name} holds {count} value(s), got count = {spec.count}", source=source,
                             column=f"controller.registers.{name}")
        if not writable and spec.access == "write":
            raise InputError(f"{name} is written by the controller; elastocal only reads it",
                             source=source, column=f"controller.registers.{name}")
        specs.append(spec)
    names = {s.name for s in specs}
    for need in CONTROLLER_REQUIRED:
        if need not in names:
            raise InputError(f"missing the {need} register", source=source, column="controller.registers")
    regs = tuple(specs)
    _check_overlaps(regs, source=source, where="controller.registers")
    poses = []
    for key, q in (t.get("poses") or {}).items():
        try:
            number = int(key)
        except ValueError:
            raise InputError(f"pose keys are numbers, got {key!r}", source=source, column="controller.poses") from None
        poses.append((number, _vec({"q": q}, "q", None, source=source, where=f"controller.poses.{key}")))
    paths = []
    for i, p in enumerate(t.get("path") or [], start=1):
        pw = f"controller.path[{i}]"
        if not isinstance(p, Mapping):
            raise InputError("expected a table", source=source, column=pw)
        check_known_keys(p, ("id", "u", "v", "speed_rad_s"), source=source, where=pw)
        pid = _int(p, "id", i, source=source, where=pw, low=1)
        paths.append(PathSpec(id=pid, u=_vec(p, "u", None, source=source, where=pw),
                              v=_vec(p, "v", None, source=source, where=pw),
                              speed_rad_s=_num(p, "speed_rad_s", 0.05, source=source, where=pw)))
    if len({p.id for p in paths}) != len(paths):
        raise InputError("path ids repeat", source=source, column="controller.path")
    return ControllerConfig(url=url, registers=regs, poses=tuple(sorted(poses)), paths=tuple(paths),
                            timeout_s=_num(t, "timeout_s", 0.5, source=source, where=where),
                            retries=_int(t, "retries", 2, source=source, where=where),
                            move_timeout_s=_num(t, "move_timeout_s", 120.0, source=source, where=where))


def _sim(t: Mapping, *, source: str) -> SimConfig:
    where = "sim"
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    d = SimConfig()
    check_known_keys(t, tuple(SimConfig.__dataclass_fields__), source=source, where=where)
    hidden = t.get("hidden", d.hidden)
    if hidden not in HIDDEN_EFFECTS:
        raise InputError(f"hidden must be one of {', '.join(HIDDEN_EFFECTS)}, got {hidden!r}",
                         source=source, column="sim.hidden")
    kw = dict(
        seed=_int(t, "seed", d.seed, source=source, where=where),
        hidden=hidden,
        start_q=_vec(t, "start_q", d.start_q, source=source, where=where),
        move_speed_rad_s=_num(t, "move_speed_rad_s", d.move_speed_rad_s, source=source, where=where),
        run_speed_rad_s=_num(t, "run_speed_rad_s", d.run_speed_rad_s, source=source, where=where),
        coulomb_nm=_vec(t, "coulomb_nm", d.coulomb_nm, source=source, where=where, nonneg=True),
        viscous_nm_s_rad=_vec(t, "viscous_nm_s_rad", d.viscous_nm_s_rad, source=source, where=where, nonneg=True),
        load_friction=_vec(t, "load_friction", d.load_friction, source=source, where=where, nonneg=True),
        tracker_noise_m=_num(t, "tracker_noise_m", d.tracker_noise_m, source=source, where=where, positive=False),
        current_noise_a=_num(t, "current_noise_a", d.current_noise_a, source=source, where=where, positive=False),
        gear_ratios=_vec(t, "gear_ratios", d.gear_ratios, source=source, where=where),
        can_reply_delay_s=_num(t, "can_reply_delay_s", d.can_reply_delay_s, source=source, where=where,
                               positive=False),
        modbus_reply_delay_s=_num(t, "modbus_reply_delay_s", d.modbus_reply_delay_s, source=source, where=where,
                                  positive=False),
        tracker_reply_delay_s=_num(t, "tracker_reply_delay_s", d.tracker_reply_delay_s, source=source,
                                   where=where, positive=False),
    )
    for key in ("tracker_noise_m", "current_noise_a", "can_reply_delay_s", "modbus_reply_delay_s",
                "tracker_reply_delay_s"):
        if kw[key] < 0:
            raise InputError("must be >= 0", source=source, column=f"sim.{key}")
    if any(g <= 0 for g in kw["gear_ratios"]):
        raise InputError("gear ratios must be > 0", source=source, column="sim.gear_ratios")
    return SimConfig(**kw)


def _optional_path(table: Mapping, key: str, message: str, *, source: str,
                   base_dir: pathlib.Path | None) -> pathlib.Path | None:
    """The optional path ``cell.<key>``, relative to the config file's folder."""
    value = table.get(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise InputError(message, source=source, column=f"cell.{key}")
    path = pathlib.Path(value)
    return base_dir / path if not path.is_absolute() and base_dir is not None else path


def parse_cell_config(text: str, *, source: str = "<cell.toml>",
                      base_dir: pathlib.Path | None = None) -> CellConfig:
    """Parse cell.toml text; every error names the file and the key."""
    try:
        doc = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source=source) from None
    check_known_keys(doc, ("cell", "drive", "tracker", "controller", "sim"), source=source, where="")
    cell = doc.get("cell")
    if not isinstance(cell, Mapping):
        raise InputError("missing [cell] table", source=source, column="cell")
    check_known_keys(cell, ("name", "robot", "history", "plan"), source=source, where="cell")
    name = cell.get("name", "cell")
    robot = cell.get("robot")
    if not isinstance(robot, str) or not robot:
        raise InputError('missing robot (a robot.toml path or "hh150")', source=source, column="cell.robot")
    history_path = _optional_path(cell, "history", "history must be a path", source=source, base_dir=base_dir)
    plan_path = _optional_path(cell, "plan", "plan must be the path of a plan.toml", source=source,
                               base_dir=base_dir)
    drive_tables = doc.get("drive", [])
    if not isinstance(drive_tables, list):
        raise InputError("drives are [[drive]] tables", source=source, column="drive")
    drives = tuple(_drive(t, i, source=source) for i, t in enumerate(drive_tables, start=1))
    joints = [d.joint for d in drives]
    if len(set(joints)) != len(joints):
        raise InputError(f"joints repeat among [[drive]] tables: {joints}", source=source, column="drive")
    _check_can_nodes(drives, source=source)
    tracker = _tracker(doc["tracker"], source=source) if "tracker" in doc else None
    controller = _controller(doc["controller"], source=source) if "controller" in doc else None
    sim = _sim(doc["sim"], source=source) if "sim" in doc else SimConfig()
    return CellConfig(name=str(name), robot=robot, drives=tuple(sorted(drives, key=lambda d: d.joint)),
                      tracker=tracker, controller=controller, history=history_path, sim=sim, plan=plan_path,
                      source=source, base_dir=base_dir)


def _check_can_nodes(drives: tuple[DriveConfig, ...], *, source: str) -> None:
    seen: dict[tuple[str, str, int], int] = {}
    for d in drives:
        if d.url.scheme != "canopen":
            continue
        key = (d.url.can_interface, d.url.can_channel, int(d.url.param("node")))
        if key in seen:
            raise InputError(f"joints {seen[key]} and {d.joint} use the same CAN node {key[2]} on "
                             f"{key[0]}/{key[1]}", source=source, column="drive")
        seen[key] = d.joint


def load_cell_config(path: str | pathlib.Path) -> CellConfig:
    """Read and validate a cell.toml file."""
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_cell_config(text, source=str(path), base_dir=path.parent)


# -------------------------------------------------------------- writing
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def _register_toml(spec: RegisterSpec, *, default_access: str) -> str:
    items = [f"address = {spec.address}", f"type = {_toml_value(spec.type)}"]
    if spec.count != 1:
        items.append(f"count = {spec.count}")
    if spec.scale != 1.0:
        items.append(f"scale = {spec.scale!r}")
    if spec.unit != "1":
        items.append(f"unit = {_toml_value(spec.unit)}")
    if spec.table != "holding":
        items.append(f"table = {_toml_value(spec.table)}")
    if spec.access != default_access:
        items.append(f"access = {_toml_value(spec.access)}")
    if spec.word_order != "big":
        items.append(f"word_order = {_toml_value(spec.word_order)}")
    if spec.fault_mask:
        items.append(f"fault_mask = {spec.fault_mask}")
    if spec.ready_mask:
        items.append(f"ready_mask = {spec.ready_mask}")
    return f"{spec.name} = {{ " + ", ".join(items) + " }"


def _to_toml(c: CellConfig) -> str:
    robot = c.robot
    if "/" in robot or robot.endswith(".toml"):
        robot = str(c.robot_path().resolve())
    lines = ["[cell]", f"name = {_toml_value(c.name)}", f"robot = {_toml_value(robot)}"]
    if c.history is not None:
        lines.append(f"history = {_toml_value(str(c.history))}")
    if c.plan is not None:
        lines.append(f"plan = {_toml_value(str(c.plan.resolve()))}")
    for d in c.drives:
        lines += ["", "[[drive]]", f"joint = {d.joint}", f"url = {_toml_value(d.url.text)}",
                  f"rate_hz = {d.rate_hz!r}", f"timeout_s = {d.timeout_s!r}", f"retries = {d.retries}",
                  f"max_current_a = {d.max_current_a!r}"]
        if d.registers:
            lines.append("[drive.registers]")
            lines += [_register_toml(r, default_access="read") for r in d.registers]
    if c.tracker is not None:
        t = c.tracker
        lines += ["", "[tracker]", f"url = {_toml_value(t.url.text)}", f"markers = {_toml_value(list(t.markers))}",
                  f"rate_hz = {t.rate_hz!r}", f"timeout_s = {t.timeout_s!r}", f"retries = {t.retries}"]
        if t.base_p_tracker is not None:
            lines.append(f"base_p_tracker = {_toml_value(list(t.base_p_tracker))}")
    if c.controller is not None:
        k = c.controller
        lines += ["", "[controller]", f"url = {_toml_value(k.url.text)}", f"timeout_s = {k.timeout_s!r}",
                  f"retries = {k.retries}", f"move_timeout_s = {k.move_timeout_s!r}", "[controller.registers]"]
        lines += [_register_toml(r, default_access="read") for r in k.registers]
        if k.poses:
            lines.append("[controller.poses]")
            lines += [f'"{n}" = {_toml_value(list(q))}' for n, q in k.poses]
        for p in k.paths:
            lines += ["[[controller.path]]", f"id = {p.id}", f"u = {_toml_value(list(p.u))}",
                      f"v = {_toml_value(list(p.v))}", f"speed_rad_s = {p.speed_rad_s!r}"]
    s = c.sim
    lines += ["", "[sim]"]
    for name in SimConfig.__dataclass_fields__:
        value = getattr(s, name)
        lines.append(f"{name} = {_toml_value(list(value) if isinstance(value, tuple) else value)}")
    return "\n".join(lines) + "\n"
