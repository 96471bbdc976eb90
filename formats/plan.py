"""The calibration plan (``plan.toml``, docs/plan-format.md), resolved once into
frozen, validated dataclasses.

A plan names poses, load states, markers, repeats and speeds for the
procedures: ``static`` (before/after load), ``friction`` (UV/VU runs),
``sweep`` (joint-2 sweep for the compensator) and ``check`` (a short
recalibration check). Every error names the file and the key.

Why one module over 500 lines: the plan format is read (a function per section) and
written (:func:`plan_toml`) here, so that one file holds every key the procedures know.
"""

from __future__ import annotations

import hashlib
import math
import pathlib
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import tomli_w

from elastocal.errors import InputError
from elastocal.model.robot import Robot
from elastocal.formats.textfiles import read_text_file

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

PROCEDURES = ("static", "friction", "sweep", "check")
UNLOADED = "0"


@dataclass(frozen=True)
class SettleSpec:
    """When the cell counts as at rest: every joint slower than ``speed_rad_s``
    and the standard deviation of every coordinate of the watched marker below
    ``spread_m`` over the last ``window_s``; give up (DeviceTimeout) after
    ``timeout_s``."""

    speed_rad_s: float = 2e-3
    spread_m: float = 20e-6
    window_s: float = 0.3
    timeout_s: float = 60.0


@dataclass(frozen=True)
class LoadSpec:
    """A load state: a weight hung on the load point (``mass_kg``) or a measured
    force and moment (``force_n``, ``moment_nm``, base axes, on the load point)."""

    id: str
    mass_kg: float | None = None
    force_n: tuple[float, float, float] | None = None
    moment_nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    description: str = ""

    def wrench(self, gravity: Sequence[float]) -> tuple[float, ...]:
        """Nominal wrench (fx, fy, fz, mx, my, mz) on the load point, base axes."""
        if self.mass_kg is not None:
            force = tuple(self.mass_kg * float(g) for g in gravity)
        else:
            force = self.force_n
        return tuple(float(v) for v in (*force, *self.moment_nm))

    def instruction(self) -> str:
        """What the operator does to put the cell in this load state."""
        if self.description:
            what = self.description
        elif self.mass_kg is not None:
            what = f"{self.mass_kg:g} kg"
        else:
            fx, fy, fz = self.force_n
            what = f"force ({fx:g}, {fy:g}, {fz:g}) N"
        return f"hang load {self.id}, {what}, on the load point"


@dataclass(frozen=True)
class PoseSpec:
    id: str
    q: tuple[float, ...]
    loads: tuple[str, ...]   # loaded states measured at this pose, in order


@dataclass(frozen=True)
class StaticSpec:
    poses: tuple[PoseSpec, ...]
    markers: tuple[str, ...]
    repeats: int = 3
    reading_s: float = 0.2
    speed_rad_s: float = 0.3


@dataclass(frozen=True)
class FrictionSpec:
    """One UV/VU path: from ``start`` to ``end`` (UV) and back (VU), at each
    speed (the fastest joint's speed) under each load, ``repeats`` times."""

    id: str
    start: tuple[float, ...]
    end: tuple[float, ...]
    speeds_rad_s: tuple[float, ...]
    loads: tuple[str, ...] = (UNLOADED,)
    repeats: int = 1
    marker: str | None = None


@dataclass(frozen=True)
class SweepSpec:
    """Joint ``joint`` (2 by default; the compensator's on any chain) from ``q2_from`` to ``q2_to``
    (+) and back (-), the other joints at ``q``."""

    q: tuple[float, ...]
    q2_from: float
    q2_to: float
    speed_rad_s: float
    repeats: int = 1
    load: str = UNLOADED
    marker: str | None = None
    joint: int = 2

    def ends(self) -> tuple[tuple[float, ...], ...]:
        """The joint values the sweep starts at and turns at: ``q`` with the swept joint set."""
        j = self.joint - 1
        return tuple(tuple(self.q[:j]) + (v,) + tuple(self.q[j + 1:]) for v in (self.q2_from, self.q2_to))


@dataclass(frozen=True)
class CheckSpec:
    """A short recalibration check: a few static poses under one load, one UV/VU pair."""

    poses: tuple[str, ...]
    load: str
    friction: str | None = None


@dataclass(frozen=True)
class Plan:
    name: str
    source: str
    text: str
    settle: SettleSpec
    loads: tuple[LoadSpec, ...]
    static: StaticSpec | None = None
    friction: tuple[FrictionSpec, ...] = ()
    sweep: SweepSpec | None = None
    check: CheckSpec | None = None
    procedures: tuple[str, ...] = field(default=())

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()

    def load(self, load_id: str) -> LoadSpec | None:
        """The load state ``load_id`` (None for the unloaded state ``"0"``)."""
        if load_id == UNLOADED:
            return None
        for spec in self.loads:
            if spec.id == load_id:
                return spec
        raise KeyError(load_id)

    def pose(self, pose_id: str) -> PoseSpec:
        for p in self.static.poses if self.static else ():
            if p.id == pose_id:
                return p
        raise KeyError(pose_id)

    def validate_for(self, robot: Robot) -> None:
        """Check the plan against a robot: joint limits and marker names."""
        def check_q(q: Sequence[float], where: str) -> None:
            if len(q) != robot.n_joints:
                raise InputError(f"{len(q)} joint values; the robot {robot.name!r} has {robot.n_joints} joints",
                                 source=self.source, column=where)
            for j, (v, lo, hi) in enumerate(zip(q, robot.lower, robot.upper), start=1):
                if not lo <= v <= hi:
                    raise InputError(f"q{j} = {v} {robot.joints[j - 1].unit} is outside the joint limits [{lo:.4g}, {hi:.4g}] of "
                                     f"{robot.name}", source=self.source, column=where)

        def check_marker(m: str | None, where: str) -> None:
            if m is not None and m not in robot.marker_names:
                raise InputError(f"unknown marker {m!r}; the robot has {', '.join(robot.marker_names)}",
                                 source=self.source, column=where)

        if self.static:
            for p in self.static.poses:
                check_q(p.q, f"static.pose[{p.id}].q")
            for m in self.static.markers:
                check_marker(m, "static.markers")
        for f in self.friction:
            check_q(f.start, f"friction[{f.id}].from")
            check_q(f.end, f"friction[{f.id}].to")
            check_marker(f.marker, f"friction[{f.id}].marker")
        if self.sweep:
            s = self.sweep
            for q, key in zip(s.ends(), ("q2_from", "q2_to")):
                check_q(q, f"sweep.{key}")
            check_marker(s.marker, "sweep.marker")


# ------------------------------------------------------------------ parsing
class _Table:
    """A TOML table with typed getters whose errors name file and key."""

    def __init__(self, data: Any, source: str, where: str) -> None:
        if not isinstance(data, Mapping):
            raise InputError("expected a table", source=source, column=where)
        self.data = data
        self.source = source
        self.where = where

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def fail(self, name: str, message: str) -> InputError:
        return InputError(message, source=self.source, column=self.key(name))

    def check_keys(self, allowed: Sequence[str]) -> None:
        for k in self.data:
            if k not in allowed:
                raise self.fail(k, f"unknown key; expected one of {', '.join(allowed)}")

    def number(self, name: str, default: float | None = None, *, positive: bool = False) -> float:
        if name not in self.data:
            if default is None:
                raise self.fail(name, "missing required key")
            return default
        v = self.data[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(name, f"expected a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.fail(name, f"must be > 0, got {v!r}")
        return float(v)

    def integer(self, name: str, default: int, *, minimum: int = 1) -> int:
        v = self.data.get(name, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            raise self.fail(name, f"expected an integer >= {minimum}, got {v!r}")
        return v

    def text(self, name: str, default: str | None = None) -> str:
        if name not in self.data:
            if default is None:
                raise self.fail(name, "missing required key")
            return default
        v = self.data[name]
        if not isinstance(v, str) or not v.strip():
            raise self.fail(name, f"expected a non-empty string, got {v!r}")
        return v.strip()

    def optional_text(self, name: str) -> str | None:
        return self.text(name) if name in self.data else None

    def vector(self, name: str, n: int, *, required: bool = True) -> tuple[float, ...] | None:
        if name not in self.data:
            if required:
                raise self.fail(name, "missing required key")
            return None
        v = self.data[name]
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            raise self.fail(name, f"expected a list of {n} finite numbers, got {v!r}")
        return tuple(float(x) for x in v)

    def joint_vector(self, name: str) -> tuple[float, ...]:
        """q1..qN (the plan is checked against the robot's N in :meth:`Plan.validate_for`)."""
        v = self.data.get(name)
        q = self.vector(name, len(v) if isinstance(v, list) and v else 6)
        for j, v in enumerate(q, start=1):
            if abs(v) > 2 * math.pi:
                raise self.fail(name, f"q{j} = {v} is larger than 2*pi; degrees? angles are radians")
        return q

    def strings(self, name: str, default: tuple[str, ...] | None = None) -> tuple[str, ...]:
        if name not in self.data:
            if default is None:
                raise self.fail(name, "missing required key")
            return default
        v = self.data[name]
        if not isinstance(v, list) or not all(isinstance(x, str) and x.strip() for x in v):
            raise self.fail(name, f"expected a list of names, got {v!r}")
        out = tuple(x.strip() for x in v)
        if len(set(out)) != len(out):
            raise self.fail(name, "names repeat")
        return out

    def tables(self, name: str) -> list["_Table"]:
        v = self.data.get(name, [])
        if not isinstance(v, list):
            raise self.fail(name, "expected an array of tables ([[...]])")
        return [_Table(t, self.source, f"{self.key(name)}[{i}]") for i, t in enumerate(v, start=1)]

    def table(self, name: str) -> "_Table | None":
        if name not in self.data:
            return None
        return _Table(self.data[name], self.source, self.key(name))


def parse_plan(text: str, *, source: str = "<plan.toml>") -> Plan:
    """Parse plan.toml text; errors name the file and the key."""
    try:
        doc = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source=source) from None
    top = _Table(doc, source, "")
    top.check_keys(("name", "procedures", "settle", "load", "static", "friction", "sweep", "check", "expected"))
    if "expected" in doc and not isinstance(doc["expected"], dict):
        raise top.fail("expected", "must be a table (what the planner predicts; the procedures ignore it)")
    name = top.text("name", "calibration")
    settle = _settle(top.table("settle"))
    loads = _loads(top, source)
    load_ids = [spec.id for spec in loads]
    static = _static(top.table("static"), load_ids)
    friction = _friction(top, load_ids, source)
    sweep = _sweep(top.table("sweep"), load_ids)
    check = _check(top.table("check"), load_ids, static, [f.id for f in friction])
    present = tuple(p for p, spec in (("static", static), ("friction", friction), ("sweep", sweep)) if spec)
    procedures = top.strings("procedures", present)
    for p in procedures:
        if p not in PROCEDURES:
            raise top.fail("procedures", f"unknown procedure {p!r}; one of {', '.join(PROCEDURES)}")
        spec = {"static": static, "friction": friction, "sweep": sweep, "check": check}[p]
        if not spec:
            raise top.fail("procedures", f"procedure {p!r} has no section in the plan")
    if not procedures:
        raise InputError("the plan has no procedure: give [static], [[friction]], [sweep] or [check]",
                         source=source)
    return Plan(name=name, source=source, text=text, settle=settle, loads=tuple(loads), static=static,
                friction=tuple(friction), sweep=sweep, check=check, procedures=procedures)


def _check_load(tbl: _Table, key: str, lid: str, load_ids: Sequence[str], *, allow_unloaded: bool) -> None:
    if lid == UNLOADED and allow_unloaded:
        return
    if lid not in load_ids:
        raise tbl.fail(key, f"unknown load {lid!r}; the plan has {', '.join(load_ids) or 'no [[load]]'}")


def _settle(st: _Table | None) -> SettleSpec:
    settle = SettleSpec()
    if st is None:
        return settle
    st.check_keys(("speed_rad_s", "spread_m", "window_s", "timeout_s"))
    return SettleSpec(speed_rad_s=st.number("speed_rad_s", settle.speed_rad_s, positive=True),
                      spread_m=st.number("spread_m", settle.spread_m, positive=True),
                      window_s=st.number("window_s", settle.window_s, positive=True),
                      timeout_s=st.number("timeout_s", settle.timeout_s, positive=True))


def _loads(top: _Table, source: str) -> list[LoadSpec]:
    loads = []
    for t in top.tables("load"):
        t.check_keys(("id", "mass_kg", "force_n", "moment_nm", "description"))
        lid = t.text("id")
        if lid == UNLOADED:
            raise t.fail("id", f"{UNLOADED!r} is the unloaded state; give loaded states other ids")
        has_mass, has_force = "mass_kg" in t.data, "force_n" in t.data
        if has_mass == has_force:
            raise t.fail("mass_kg", "give either mass_kg (a hung weight) or force_n (a measured force)")
        loads.append(LoadSpec(id=lid, mass_kg=t.number("mass_kg", positive=True) if has_mass else None,
                              force_n=t.vector("force_n", 3) if has_force else None,
                              moment_nm=t.vector("moment_nm", 3, required=False) or (0.0, 0.0, 0.0),
                              description=str(t.data.get("description", "")).strip()))
    load_ids = [spec.id for spec in loads]
    if len(set(load_ids)) != len(load_ids):
        raise InputError("load ids repeat", source=source, column="load")
    return loads


def _static(s: _Table | None, load_ids: Sequence[str]) -> StaticSpec | None:
    if s is None:
        return None
    s.check_keys(("markers", "repeats", "reading_s", "speed_rad_s", "pose"))
    poses = []
    for p in s.tables("pose"):
        p.check_keys(("id", "q", "loads"))
        pl = p.strings("loads", tuple(load_ids))
        for lid in pl:
            _check_load(p, "loads", lid, load_ids, allow_unloaded=False)
        if not pl:
            raise p.fail("loads", "a pose needs at least one loaded state")
        poses.append(PoseSpec(id=p.text("id"), q=p.joint_vector("q"), loads=pl))
    if not poses:
        raise s.fail("pose", "the static procedure needs at least one [[static.pose]]")
    ids = [p.id for p in poses]
    if len(set(ids)) != len(ids):
        raise s.fail("pose", "pose ids repeat")
    return StaticSpec(poses=tuple(poses), markers=s.strings("markers"), repeats=s.integer("repeats", 3),
                      reading_s=s.number("reading_s", 0.2, positive=True),
                      speed_rad_s=s.number("speed_rad_s", 0.3, positive=True))


def _friction(top: _Table, load_ids: Sequence[str], source: str) -> list[FrictionSpec]:
    friction = []
    for f in top.tables("friction"):
        f.check_keys(("id", "from", "to", "speeds_rad_s", "loads", "repeats", "marker"))
        fl = f.strings("loads", (UNLOADED,))
        for lid in fl:
            _check_load(f, "loads", lid, load_ids, allow_unloaded=True)
        speeds = f.data.get("speeds_rad_s")
        if (not isinstance(speeds, list) or not speeds
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in speeds)):
            raise f.fail("speeds_rad_s", f"expected a list of positive speeds, got {speeds!r}")
        start, end = f.joint_vector("from"), f.joint_vector("to")
        if start == end:
            raise f.fail("to", "the path has no length: from and to are equal")
        friction.append(FrictionSpec(id=f.text("id"), start=start, end=end,
                                     speeds_rad_s=tuple(float(v) for v in speeds), loads=fl,
                                     repeats=f.integer("repeats", 1), marker=f.optional_text("marker")))
    fids = [f.id for f in friction]
    if len(set(fids)) != len(fids):
        raise InputError("friction ids repeat", source=source, column="friction")
    return friction


def _sweep(w: _Table | None, load_ids: Sequence[str]) -> SweepSpec | None:
    if w is None:
        return None
    w.check_keys(("q", "q2_from", "q2_to", "speed_rad_s", "repeats", "load", "marker", "joint"))
    lid = w.text("load", UNLOADED)
    _check_load(w, "load", lid, load_ids, allow_unloaded=True)
    sweep = SweepSpec(q=w.joint_vector("q"), q2_from=w.number("q2_from"), q2_to=w.number("q2_to"),
                      speed_rad_s=w.number("speed_rad_s", positive=True), repeats=w.integer("repeats", 1),
                      load=lid, marker=w.optional_text("marker"), joint=w.integer("joint", 2))
    if sweep.joint > len(sweep.q):
        raise w.fail("joint", f"joint {sweep.joint} of a sweep whose q has {len(sweep.q)} joints")
    if sweep.q2_from == sweep.q2_to:
        raise w.fail("q2_to", "the sweep has no length: q2_from and q2_to are equal")
    return sweep


def _check(c: _Table | None, load_ids: Sequence[str], static: StaticSpec | None,
           fids: Sequence[str]) -> CheckSpec | None:
    if c is None:
        return None
    c.check_keys(("poses", "load", "friction"))
    if static is None:
        raise c.fail("poses", "the check measures static poses; the plan has no [static]")
    cposes = c.strings("poses")
    for pid in cposes:
        if pid not in [p.id for p in static.poses]:
            raise c.fail("poses", f"unknown pose {pid!r}")
    lid = c.text("load")
    _check_load(c, "load", lid, load_ids, allow_unloaded=False)
    fid = c.optional_text("friction")
    if fid is not None and fid not in fids:
        raise c.fail("friction", f"unknown friction path {fid!r}")
    return CheckSpec(poses=cposes, load=lid, friction=fid)


def load_plan(path: str | pathlib.Path) -> Plan:
    """Read a plan.toml file."""
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_plan(text, source=str(path))


# ------------------------------------------------------------------ writing
def _floats(values: Sequence) -> list[float]:
    return [float(v) for v in values]


def _load_table(spec: LoadSpec) -> dict:
    t: dict = {"id": spec.id}
    if spec.mass_kg is not None:
        t["mass_kg"] = float(spec.mass_kg)
    else:
        t["force_n"] = _floats(spec.force_n)
        if any(spec.moment_nm):
            t["moment_nm"] = _floats(spec.moment_nm)
    if spec.description:
        t["description"] = spec.description
    return t


def _static_table(items: Sequence[tuple[str, Sequence[float]]], markers: Sequence[str], repeats: int,
                  reading_s: float, speed_rad_s: float, pose_loads: Mapping[str, Sequence[str]] | None) -> dict:
    poses = []
    for pid, q in items:
        pose: dict = {"id": pid, "q": _floats(q)}
        if pose_loads is not None and pid in pose_loads:
            pose["loads"] = [str(x) for x in pose_loads[pid]]
        poses.append(pose)
    return {"markers": [str(m) for m in markers], "repeats": int(repeats), "reading_s": float(reading_s),
            "speed_rad_s": float(speed_rad_s), "pose": poses}


def _friction_table(f: FrictionSpec) -> dict:
    return {"id": f.id, "from": _floats(f.start), "to": _floats(f.end), "speeds_rad_s": _floats(f.speeds_rad_s),
            "loads": [str(x) for x in f.loads], "repeats": int(f.repeats), **({"marker": f.marker} if f.marker else {})}


def plan_toml(*, poses: Sequence[Sequence[float]] | Mapping[str, Sequence[float]], loads: Sequence[LoadSpec],
              markers: Sequence[str], name: str = "calibration", repeats: int = 3, reading_s: float = 0.2,
              speed_rad_s: float = 0.3, settle: SettleSpec | None = None,
              friction: Sequence[FrictionSpec] = (), sweep: SweepSpec | None = None,
              check: CheckSpec | None = None, procedures: Sequence[str] | None = None,
              pose_loads: Mapping[str, Sequence[str]] | None = None,
              expected: Mapping[str, object] | None = None) -> str:
    """plan.toml text for poses (a list, ids P1.., or a mapping id -> q), loads and
    markers, plus optional friction paths, sweep and check; :func:`parse_plan`
    reads it back. ``pose_loads`` gives some poses their own loaded states
    (pose id -> load ids; the others get every load). ``expected``: what the planner
    predicts, written as the informational ``[expected]`` table (numbers and strings,
    one level of sub-tables). For the demo, the ``plan`` command and tests. Written
    by tomli-w."""
    doc: dict = {"name": name}
    if procedures is not None:
        doc["procedures"] = [str(p) for p in procedures]
    s = settle or SettleSpec()
    doc["settle"] = {"speed_rad_s": float(s.speed_rad_s), "spread_m": float(s.spread_m),
                     "window_s": float(s.window_s), "timeout_s": float(s.timeout_s)}
    if loads:
        doc["load"] = [_load_table(spec) for spec in loads]
    items = list(poses.items()) if isinstance(poses, Mapping) else [(f"P{k}", q) for k, q in enumerate(poses, 1)]
    if items:
        doc["static"] = _static_table(items, markers, repeats, reading_s, speed_rad_s, pose_loads)
    if friction:
        doc["friction"] = [_friction_table(f) for f in friction]
    if sweep is not None:
        doc["sweep"] = {"q": _floats(sweep.q), "q2_from": float(sweep.q2_from), "q2_to": float(sweep.q2_to),
                        "speed_rad_s": float(sweep.speed_rad_s), "repeats": int(sweep.repeats), "load": sweep.load,
                        **({"marker": sweep.marker} if sweep.marker else {}),
                        **({"joint": sweep.joint} if sweep.joint != 2 else {})}
    if check is not None:
        doc["check"] = {"poses": [str(p) for p in check.poses], "load": check.load,
                        **({"friction": check.friction} if check.friction else {})}
    text = tomli_w.dumps(doc)
    if expected:
        # last, so that the comment stands just above the table it explains
        text += ("\n# [expected]: what the planner predicts; the procedures ignore it\n"
                 + tomli_w.dumps({"expected": _expected_document(expected)}))
    return text


def _plain(v):
    """A value tomli-w writes: numpy numbers as Python's, sequences as lists."""
    if isinstance(v, (str, bool)):
        return v
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return float(v) if isinstance(v, float) else int(v)


def _expected_document(expected: Mapping[str, object]) -> dict:
    """The ``[expected]`` table: plain keys, and one sub-table per mapping (its None values left out)."""
    return {k: ({kk: _plain(vv) for kk, vv in v.items() if vv is not None} if isinstance(v, Mapping) else _plain(v))
            for k, v in expected.items()}
