"""The cell configuration (``cell.toml``) resolved into frozen dataclasses.

``cell.toml`` names every device of a calibration cell by a URL
(:mod:`elastocal.drivers.urls`, docs/cell-config.md), Modbus devices with their
register maps (:mod:`elastocal.drivers.registers`).

:func:`load_cell_config` reads the file once; every value is validated here,
so errors name the file and the key. Nothing in this module does I/O on a
device. The ``[sim]`` section belongs to the simulated cell: it is kept as the
raw table here and validated by :func:`elastocal.sims.config.sim_config`.

Why one module over 500 lines: every section of cell.toml is read and written here
(URLs and register maps are in drivers.urls and drivers.registers), so that a key is
validated, named in its errors and written back in one place.
"""

from __future__ import annotations

import contextlib
import math
import pathlib
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

import tomli_w

from elastocal.drivers.registers import (
    CONTROLLER_REGISTERS,
    CONTROLLER_REQUIRED,
    DRIVE_REGISTER_QUANTITY,
    RegisterSpec,
    _check_overlaps,
    _register,
)
from elastocal.drivers.endpoints import check_endpoints
from elastocal.drivers.guidance_config import (
    ForceSensorConfig,
    GuidanceConfig,
    guidance_doc,
    parse_force_sensor,
    parse_guidance,
)
from elastocal.drivers.urls import CONTROLLER_SCHEMES, DRIVE_SCHEMES, TRACKER_SCHEMES, DeviceUrl, parse_device_url
from elastocal.errors import InputError, check_known_keys
from elastocal.formats.textfiles import read_text_file
from elastocal.model.tracker_noise import TrackerNoise, parse_tracker_noise, tracker_noise_doc

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

#: the joints of the default robot (the HH-150); a cell's drives are joints 1..N of its robot
N_JOINTS = 6
#: the most joints a cell's drives may number (the log's limit)
MAX_JOINTS = 64


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
    #: the tracker's noise law as its maker states it (optional; model/tracker_noise.py): weights,
    #: noise floor and outlier test where the readings are not repeated enough to estimate it
    noise: TrackerNoise | None = None

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
class CellConfig:
    """A whole cell, resolved from ``cell.toml``."""

    name: str
    robot: str                              # "hh150" (bundled) or a path
    drives: tuple[DriveConfig, ...]
    tracker: TrackerConfig | None = None
    controller: ControllerConfig | None = None
    history: pathlib.Path | None = None
    #: the raw ``[sim]`` table (read by :func:`elastocal.sims.config.sim_config`)
    sim: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    plan: pathlib.Path | None = None        # the cell's calibration plan (default for `calibrate --plan`)
    guidance: GuidanceConfig | None = None  # the controller's real-time guidance channel (`elastocal stream`)
    force_sensor: ForceSensorConfig | None = None
    source: str = "<cell.toml>"
    base_dir: pathlib.Path | None = None

    def drive(self, joint: int) -> DriveConfig:
        for d in self.drives:
            if d.joint == joint:
                return d
        raise InputError(f"no [[drive]] for joint {joint}", source=self.source)

    def robot_path(self) -> pathlib.Path:
        """The robot description file this cell uses."""
        from elastocal.formats.robot_toml import bundled_robot_path

        if self.robot in ("hh150",) or ("/" not in self.robot and not self.robot.endswith(".toml")):
            path = bundled_robot_path(self.robot)
            if not path.exists():
                raise InputError(f"no bundled robot named {self.robot!r}", source=self.source, column="cell.robot")
            return path
        path = pathlib.Path(self.robot)
        if not path.is_absolute() and self.base_dir is not None:
            path = self.base_dir / path
        return path

    @contextlib.contextmanager
    def key_errors(self, key: str, path: pathlib.Path | None):
        """An error about the file ``path`` that the key ``cell.<key>`` names as a whole (it cannot be
        read, it is no such file) is said as an error of the key, with the file in the message; an
        error at a line or field inside that file still names the file."""
        try:
            yield
        except InputError as exc:
            if path is None or exc.source != str(path) or exc.row is not None or exc.column is not None:
                raise
            raise InputError(f"{path}: {exc.detail}", source=self.source, column=f"cell.{key}") from None

    def load_robot(self):
        """The :class:`~elastocal.model.robot.Robot` named by ``[cell] robot``, with the cell's
        tracker markers, taught poses and paths checked against it (names and joint limits)."""
        from elastocal.formats.robot_toml import load_robot

        path = self.robot_path()
        with self.key_errors("robot", path):
            robot = load_robot(path)
        _check_against_robot(self, robot)
        return robot

    def to_toml(self) -> str:
        """The configuration as cell.toml text (round-trips through :func:`parse_cell_config`)."""
        return _to_toml(self)


def _check_against_robot(config: CellConfig, robot) -> None:
    """The tracker follows markers the robot has; taught poses and path ends lie within its joint limits."""
    src = config.source
    for i, d in enumerate(config.drives, start=1):
        if d.joint > robot.n_joints:
            raise InputError(f"joint {d.joint}: the robot {robot.name!r} has joints 1..{robot.n_joints}", source=src,
                             column=f"drive[{i}].joint")
    if config.tracker is not None:
        for m in config.tracker.markers:
            if m not in robot.marker_names:
                raise InputError(f"unknown marker {m!r}; the robot {robot.name} has {', '.join(robot.marker_names)}",
                                 source=src, column="tracker.markers")
    if config.controller is None:
        return
    taught = [(f"controller.poses.{n}", q) for n, q in config.controller.poses]
    for i, p in enumerate(config.controller.paths, start=1):
        taught += [(f"controller.path[{i}].u", p.u), (f"controller.path[{i}].v", p.v)]
    for key, q in taught:
        if len(q) != robot.n_joints:
            raise InputError(f"{len(q)} joint values; the robot {robot.name!r} has {robot.n_joints} joints",
                             source=src, column=key)
        for j, v in enumerate(q):
            lo, hi = robot.joints[j].lower, robot.joints[j].upper
            if not lo - 1e-9 <= v <= hi + 1e-9:
                raise InputError(f"q{j + 1} = {v:g} {robot.joints[j].unit} is outside the joint limits "
                                 f"[{lo:.4g}, {hi:.4g}] of {robot.name}", source=src, column=key)


# ---------------------------------------------------------------- parsing
#: a sampling rate beyond this is not one a drive or tracker delivers [Hz]
MAX_RATE_HZ = 10_000.0


def _rate(table: Mapping, default: float, *, source: str, where: str) -> float:
    rate = _num(table, "rate_hz", default, source=source, where=where)
    if rate > MAX_RATE_HZ:
        raise InputError(f"{rate:g} Hz is not a plausible sampling rate (at most {MAX_RATE_HZ:g} Hz)",
                         source=source, column=f"{where}.rate_hz")
    return rate


def _joint_angles(table: Mapping, key: str, *, source: str, where: str) -> tuple[float, ...]:
    """Joint coordinates q1..qN [rad]; more than a turn is refused as degrees."""
    q = _vec(table, key, None, source=source, where=where)
    for j, v in enumerate(q):
        if abs(v) > 2 * math.pi + 1e-9:
            raise InputError(f"q{j + 1} = {v:g} is more than a full turn; degrees? joint angles are radians",
                             source=source, column=f"{where}.{key}" if where else key)
    return q


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
         n: int | None = None, nonneg: bool = False) -> tuple[float, ...]:
    """A per-joint list: ``n`` numbers, or any number of them (one per joint of the robot, which
    the simulated cell checks) when ``n`` is None."""
    if key not in table:
        if default is None:
            raise InputError("missing required key", source=source, column=f"{where}.{key}")
        return default
    v = table[key]
    try:
        out = tuple(float(x) for x in v if not isinstance(x, bool))
    except (TypeError, ValueError):
        raise InputError(f"expected a list of {n or 'per-joint'} numbers, got {v!r}", source=source,
                         column=f"{where}.{key}") from None
    if (len(out) != (n or len(out)) or not out or len(out) != len(v)
            or not all(math.isfinite(x) for x in out)):
        raise InputError(f"expected {n or 'one per joint:'} finite numbers, got {v!r}", source=source,
                         column=f"{where}.{key}")
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
    if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= MAX_JOINTS:
        raise InputError(f"joint must be 1..N (the robot's joints), got {joint!r}", source=source,
                         column=f"{where}.joint")
    if "url" not in t:
        raise InputError("missing required key", source=source, column=f"{where}.url")
    url = parse_device_url(t["url"], allowed=DRIVE_SCHEMES, source=f"{source}, {where}.url", kind="drive")
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
                       rate_hz=_rate(t, default_rate, source=source, where=where),
                       timeout_s=_num(t, "timeout_s", 0.5, source=source, where=where),
                       retries=_int(t, "retries", 2, source=source, where=where),
                       max_current_a=_num(t, "max_current_a", 200.0, source=source, where=where))


def _tracker(t: Mapping, *, source: str) -> TrackerConfig:
    where = "tracker"
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    check_known_keys(t, ("url", "markers", "rate_hz", "timeout_s", "retries", "base_p_tracker", "noise"),
                     source=source, where=where)
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
    url = parse_device_url(t["url"], allowed=TRACKER_SCHEMES, source=f"{source}, tracker.url", kind="tracker")
    markers = t.get("markers", [])
    if not isinstance(markers, list) or not markers or not all(isinstance(m, str) and m for m in markers):
        raise InputError("markers must be a non-empty list of marker names", source=source, column="tracker.markers")
    if len(set(markers)) != len(markers):
        raise InputError("marker names repeat", source=source, column="tracker.markers")
    return TrackerConfig(url=url, markers=tuple(markers),
                         rate_hz=_rate(t, 100.0, source=source, where=where),
                         timeout_s=_num(t, "timeout_s", 1.0, source=source, where=where),
                         retries=_int(t, "retries", 2, source=source, where=where),
                         base_p_tracker=base_p_tracker,
                         noise=parse_tracker_noise(t["noise"], source=source) if "noise" in t else None)


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
                         default_count=count or N_JOINTS)
        if spec.quantity != quantity:
            raise InputError(f"unit {spec.unit!r} is not a unit of {quantity.replace('_', ' ')}",
                             source=source, column=f"controller.registers.{name}")
        if count is not None and spec.count != count:
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
        poses.append((number, _joint_angles({key: q}, key, source=source, where="controller.poses")))
    paths = []
    for i, p in enumerate(t.get("path") or [], start=1):
        pw = f"controller.path[{i}]"
        if not isinstance(p, Mapping):
            raise InputError("expected a table", source=source, column=pw)
        check_known_keys(p, ("id", "u", "v", "speed_rad_s"), source=source, where=pw)
        pid = _int(p, "id", i, source=source, where=pw, low=1)
        paths.append(PathSpec(id=pid, u=_joint_angles(p, "u", source=source, where=pw),
                              v=_joint_angles(p, "v", source=source, where=pw),
                              speed_rad_s=_num(p, "speed_rad_s", 0.05, source=source, where=pw)))
    if len({p.id for p in paths}) != len(paths):
        raise InputError("path ids repeat", source=source, column="controller.path")
    return ControllerConfig(url=url, registers=regs, poses=tuple(sorted(poses)), paths=tuple(paths),
                            timeout_s=_num(t, "timeout_s", 0.5, source=source, where=where),
                            retries=_int(t, "retries", 2, source=source, where=where),
                            move_timeout_s=_num(t, "move_timeout_s", 120.0, source=source, where=where))


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
    check_known_keys(doc, ("cell", "drive", "tracker", "controller", "guidance", "force_sensor", "sim"),
                     source=source, where="")
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
    guidance = parse_guidance(doc["guidance"], source=source) if "guidance" in doc else None
    force_sensor = parse_force_sensor(doc["force_sensor"], source=source) if "force_sensor" in doc else None
    sim = doc.get("sim", {})
    if not isinstance(sim, Mapping):
        raise InputError("expected a table", source=source, column="sim")
    sim = MappingProxyType(dict(sim))
    config = CellConfig(name=str(name), robot=robot, drives=tuple(sorted(drives, key=lambda d: d.joint)),
                        tracker=tracker, controller=controller, history=history_path, sim=sim, plan=plan_path,
                        guidance=guidance, force_sensor=force_sensor, source=source, base_dir=base_dir)
    check_endpoints(_cell_devices(config), source=source)
    return config


def _check_can_nodes(drives: tuple[DriveConfig, ...], *, source: str) -> None:
    seen: dict[tuple[str, str, int], int] = {}
    for d in drives:
        if d.url.scheme != "canopen":
            continue
        key = (d.url.settings.interface, d.url.settings.channel, d.url.settings.node)
        if key in seen:
            raise InputError(f"joints {seen[key]} and {d.joint} use the same CAN node {key[2]} on "
                             f"{key[0]}/{key[1]}", source=source, column="drive")
        seen[key] = d.joint


def _cell_devices(config: CellConfig) -> list[tuple[str, DeviceUrl, tuple[RegisterSpec, ...]]]:
    out = [(d.name, d.url, d.registers) for d in config.drives]
    if config.tracker is not None:
        out.append(("tracker", config.tracker.url, ()))
    if config.controller is not None:
        out.append(("controller", config.controller.url, config.controller.registers))
    return out


def load_cell_config(path: str | pathlib.Path) -> CellConfig:
    """Read and validate a cell.toml file."""
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_cell_config(text, source=str(path), base_dir=path.parent)


# -------------------------------------------------------------- writing
def _register_table(spec: RegisterSpec, *, default_access: str) -> dict[str, Any]:
    """A register as its cell.toml table, keys at their default left out."""
    table: dict[str, Any] = {"address": spec.address, "type": spec.type}
    defaults = {"count": 1, "scale": 1.0, "unit": "1", "table": "holding", "access": default_access,
                "word_order": "big", "fault_mask": 0, "ready_mask": 0}
    for key, default in defaults.items():
        value = getattr(spec, key)
        if value != default:
            table[key] = value
    return table


def _registers(specs: tuple[RegisterSpec, ...]) -> dict[str, Any]:
    return {r.name: _register_table(r, default_access="read") for r in specs}


def _document(c: CellConfig) -> dict[str, Any]:
    """The configuration as the table cell.toml holds (read back by :func:`parse_cell_config`)."""
    robot = c.robot
    if "/" in robot or robot.endswith(".toml"):
        robot = str(c.robot_path().resolve())
    cell: dict[str, Any] = {"name": c.name, "robot": robot}
    if c.history is not None:
        cell["history"] = str(c.history)
    if c.plan is not None:
        cell["plan"] = str(c.plan.resolve())
    doc: dict[str, Any] = {"cell": cell}
    drives = []
    for d in c.drives:
        table: dict[str, Any] = {"joint": d.joint, "url": d.url.text, "rate_hz": d.rate_hz,
                                 "timeout_s": d.timeout_s, "retries": d.retries, "max_current_a": d.max_current_a}
        if d.registers:
            table["registers"] = _registers(d.registers)
        drives.append(table)
    if drives:
        doc["drive"] = drives
    if c.tracker is not None:
        t = c.tracker
        doc["tracker"] = {"url": t.url.text, "markers": list(t.markers), "rate_hz": t.rate_hz,
                          "timeout_s": t.timeout_s, "retries": t.retries}
        if t.base_p_tracker is not None:
            doc["tracker"]["base_p_tracker"] = list(t.base_p_tracker)
        if t.noise is not None:
            doc["tracker"]["noise"] = tracker_noise_doc(t.noise)
    if c.controller is not None:
        k = c.controller
        controller: dict[str, Any] = {"url": k.url.text, "timeout_s": k.timeout_s, "retries": k.retries,
                                      "move_timeout_s": k.move_timeout_s, "registers": _registers(k.registers)}
        if k.poses:
            controller["poses"] = {str(n): list(q) for n, q in k.poses}
        if k.paths:
            controller["path"] = [{"id": p.id, "u": list(p.u), "v": list(p.v), "speed_rad_s": p.speed_rad_s}
                                  for p in k.paths]
        doc["controller"] = controller
    doc.update(guidance_doc(c.guidance, c.force_sensor))
    if c.sim:
        doc["sim"] = {name: list(v) if isinstance(v, tuple) else v for name, v in c.sim.items()}
    return doc


def _to_toml(c: CellConfig) -> str:
    return tomli_w.dumps(_document(c))
