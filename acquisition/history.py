"""The calibration history of a cell: an embedded SQLite database (docs/history.md).

One file per cell (``[cell] history`` in cell.toml) holds every calibration
(its JSON as docs/formats.md §4, the hash of the log it came from, the plan it was
measured with, when it was recorded) and every check (which calibration it
tested, its verdict, the reasons and the whole result). Times are wall-clock
UTC, integer nanoseconds since the Unix epoch, given by the caller.

Nothing here prints; :class:`History` is a context manager around one
``sqlite3`` connection, records are frozen dataclasses.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import pathlib
import sqlite3
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.formats.calibration import FORMAT, CalibratedParameter, Calibration, calibration_from_json, \
    is_stiffness_name
from elastocal.diagnose.check import VERDICTS

SCHEMA_VERSION = 1
APPLICATION = "elastocal.history"
#: a check's estimate of a parameter enters the drift only when its own
#: relative std is below this (a short check does not determine every joint)
MAX_CHECK_RELATIVE_STD = 0.02
#: a calibrated value whose std is larger than this share of it (or that the calibration marks
#: ``"determined": false``, identify/evidence.py) is not determined by its data (a joint the poses
#: hardly load): its drift is marked as such, never shown as a finding
DETERMINED_RELATIVE_STD = 0.1
#: the friction tolerance of a recorded check that does not state its own (`check --friction-tolerance`)
DEFAULT_FRICTION_TOLERANCE = 0.2

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE calibration (
    id INTEGER PRIMARY KEY,
    time_ns INTEGER NOT NULL,          -- when it was recorded (UTC, ns since the epoch)
    created TEXT NOT NULL,             -- the calibration's own "created"
    robot TEXT NOT NULL,
    json TEXT NOT NULL,                -- the calibration JSON (docs/formats.md §4)
    log_sha256 TEXT,                   -- the log (or data file) it was identified from
    log_path TEXT,
    plan TEXT                          -- plan.toml text it was measured with
);
CREATE TABLE check_run (
    id INTEGER PRIMARY KEY,
    time_ns INTEGER NOT NULL,
    calibration_id INTEGER NOT NULL REFERENCES calibration(id),
    verdict TEXT NOT NULL CHECK (verdict IN ('holds', 'recalibrate')),
    reasons TEXT NOT NULL,             -- JSON list of sentences
    result TEXT NOT NULL,              -- JSON: the check --json object
    log_sha256 TEXT,
    log_path TEXT
);
"""


def iso_utc(time_ns: int) -> str:
    """``2026-11-22T10:00:00Z`` for integer ns since the epoch."""
    t = _dt.datetime.fromtimestamp(time_ns // 1_000_000_000, tz=_dt.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


@dataclass(frozen=True)
class CalibrationRecord:
    id: int
    time_ns: int
    created: str
    robot: str
    calibration: Calibration
    log_sha256: str | None
    log_path: str | None
    plan: str | None

    @property
    def time(self) -> str:
        return iso_utc(self.time_ns)


@dataclass(frozen=True)
class CheckRecord:
    id: int
    time_ns: int
    calibration_id: int
    verdict: str
    reasons: tuple[str, ...]
    result: Mapping[str, Any]
    log_sha256: str | None
    log_path: str | None

    @property
    def time(self) -> str:
        return iso_utc(self.time_ns)


@dataclass(frozen=True, eq=False)
class Drift:
    """Values of parameters over the calibrations and the checks, in time order.

    ``calibration_*`` arrays are (n_calibrations, n_parameters), ``check_*``
    (n_checks, n_parameters); NaN where a record lacks the parameter or, for
    a check, where its data determine it worse than
    :data:`MAX_CHECK_RELATIVE_STD`."""

    names: tuple[str, ...]
    units: tuple[str, ...]
    calibration_time_ns: np.ndarray
    calibration_value: np.ndarray
    calibration_std: np.ndarray
    check_time_ns: np.ndarray
    check_value: np.ndarray
    check_verdict: tuple[str, ...]
    check_unexplained_m: np.ndarray    # rms of measured - predicted deflection; NaN without static data
    check_noise_floor_m: np.ndarray
    #: (n_calibrations, n_parameters): whether the calibration determines the value (:func:`is_determined`)
    calibration_determined: np.ndarray
    #: (n_checks, 6): each joint's friction along the check's runs, measured / predicted - 1; NaN where
    #: the check did not measure it
    check_friction_relative: np.ndarray
    #: (n_checks, 6): the joints whose friction failed the check (significant and beyond its tolerance)
    check_friction_failed: np.ndarray
    #: (n_checks,): the relative friction change each check tolerated (NaN without friction)
    check_friction_tolerance: np.ndarray


def is_determined(p: CalibratedParameter) -> bool:
    """Whether a calibrated parameter (docs/formats.md §4) is determined by its data: not marked
    ``"determined": false``, with a finite std within :data:`DETERMINED_RELATIVE_STD` of its value."""
    if not p.is_result or p.std is None:
        return False
    return math.isfinite(p.std) and p.std <= DETERMINED_RELATIVE_STD * abs(p.value)


def clean(obj):
    """A JSON-safe copy: non-finite floats become null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean(v) for v in obj]
    return obj


def _calibration_from_json(doc: Mapping[str, Any], source: str) -> Calibration:
    if not isinstance(doc, Mapping) or doc.get("format") != FORMAT:
        raise InputError(f"a stored calibration is not {FORMAT}", source=source)
    return calibration_from_json(dict(doc), source)


class History:
    """The history database of one cell. ``History(path)`` opens (and, with
    ``create=True``, creates) it; use it as a context manager."""

    def __init__(self, path: str | pathlib.Path, *, create: bool = True) -> None:
        self.path = pathlib.Path(path)
        if not self.path.exists():
            if not create:
                raise InputError("no history yet: record a calibration with `elastocal history add`",
                                 source=str(self.path))
            if not self.path.parent.is_dir():
                raise InputError("the folder of the history database does not exist", source=str(self.path))
        try:
            self._db = sqlite3.connect(str(self.path), timeout=10.0)
            self._db.execute("PRAGMA foreign_keys = ON")
            self._init()
        except sqlite3.DatabaseError as exc:
            if hasattr(self, "_db"):
                self._db.close()
            raise InputError(f"not an elastocal history database ({exc})", source=str(self.path)) from None

    def _init(self) -> None:
        tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not tables:
            with self._db:
                self._db.executescript(_SCHEMA)
                self._db.executemany("INSERT INTO meta (key, value) VALUES (?, ?)",
                                     [("application", APPLICATION), ("schema_version", str(SCHEMA_VERSION))])
            return
        if "meta" not in tables:
            raise sqlite3.DatabaseError("a SQLite file of another application")
        meta = dict(self._db.execute("SELECT key, value FROM meta"))
        if meta.get("application") != APPLICATION:
            raise sqlite3.DatabaseError("a SQLite file of another application")
        if meta.get("schema_version") != str(SCHEMA_VERSION):
            raise InputError(f"history schema version {meta.get('schema_version')} is not {SCHEMA_VERSION}; "
                             "a newer elastocal wrote it", source=str(self.path))

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> "History":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------- writing
    def add_calibration(self, calibration: Calibration, *, time_ns: int, log_sha256: str | None = None,
                        log_path: str | None = None, plan: str | None = None) -> int:
        """Record a calibration; returns its id (the current calibration from now on)."""
        doc = calibration.to_json()
        with self._db:
            cur = self._db.execute(
                "INSERT INTO calibration (time_ns, created, robot, json, log_sha256, log_path, plan) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (int(time_ns), calibration.created, calibration.robot, json.dumps(doc), log_sha256, log_path, plan))
        return int(cur.lastrowid)

    def add_check(self, *, calibration_id: int, time_ns: int, verdict: str, reasons: Sequence[str],
                  result: Mapping[str, Any], log_sha256: str | None = None, log_path: str | None = None) -> int:
        """Record a check of calibration ``calibration_id``; returns its id. The
        same data (``log_sha256``) checked again against the same calibration is
        not recorded twice: the id of the check already recorded is returned."""
        if verdict not in VERDICTS:
            raise InputError(f"verdict must be one of {', '.join(VERDICTS)}, got {verdict!r}")
        if self.calibration(calibration_id) is None:
            raise InputError(f"no calibration {calibration_id} in the history", source=str(self.path))
        if log_sha256 is not None:
            row = self._db.execute("SELECT id FROM check_run WHERE calibration_id = ? AND log_sha256 = ? "
                                   "ORDER BY id LIMIT 1", (int(calibration_id), log_sha256)).fetchone()
            if row is not None:
                return int(row[0])
        with self._db:
            cur = self._db.execute(
                "INSERT INTO check_run (time_ns, calibration_id, verdict, reasons, result, log_sha256, log_path) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (int(time_ns), int(calibration_id), verdict, json.dumps(list(reasons)),
                 json.dumps(result, allow_nan=True), log_sha256, log_path))
        return int(cur.lastrowid)

    # ------------------------------------------------------------- reading
    def _calibration_row(self, row: tuple) -> CalibrationRecord:
        rid, time_ns, created, robot, text, sha, path, plan = row
        cal = _calibration_from_json(json.loads(text), f"{self.path}, calibration {rid}")
        return CalibrationRecord(id=rid, time_ns=time_ns, created=created, robot=robot, calibration=cal,
                                 log_sha256=sha, log_path=path, plan=plan)

    def calibrations(self) -> tuple[CalibrationRecord, ...]:
        """Every calibration, oldest first."""
        rows = self._db.execute("SELECT id, time_ns, created, robot, json, log_sha256, log_path, plan "
                                "FROM calibration ORDER BY time_ns, id").fetchall()
        return tuple(self._calibration_row(r) for r in rows)

    def calibration(self, calibration_id: int) -> CalibrationRecord | None:
        row = self._db.execute("SELECT id, time_ns, created, robot, json, log_sha256, log_path, plan "
                               "FROM calibration WHERE id = ?", (int(calibration_id),)).fetchone()
        return None if row is None else self._calibration_row(row)

    def current(self) -> CalibrationRecord | None:
        """The calibration in force: the most recently recorded one."""
        row = self._db.execute("SELECT id, time_ns, created, robot, json, log_sha256, log_path, plan "
                               "FROM calibration ORDER BY time_ns DESC, id DESC LIMIT 1").fetchone()
        return None if row is None else self._calibration_row(row)

    def calibrations_from_log(self, log_sha256: str) -> tuple[CalibrationRecord, ...]:
        """The calibrations identified from the log (or data file) with this SHA-256, oldest first."""
        rows = self._db.execute("SELECT id, time_ns, created, robot, json, log_sha256, log_path, plan "
                                "FROM calibration WHERE log_sha256 = ? ORDER BY time_ns, id", (log_sha256,)).fetchall()
        return tuple(self._calibration_row(r) for r in rows)

    def checks(self) -> tuple[CheckRecord, ...]:
        """Every check, oldest first."""
        rows = self._db.execute("SELECT id, time_ns, calibration_id, verdict, reasons, result, log_sha256, log_path "
                                "FROM check_run ORDER BY time_ns, id").fetchall()
        return tuple(CheckRecord(id=r[0], time_ns=r[1], calibration_id=r[2], verdict=r[3],
                                 reasons=tuple(json.loads(r[4])), result=json.loads(r[5]), log_sha256=r[6],
                                 log_path=r[7]) for r in rows)

    def drift(self, names: Sequence[str] | None = None) -> Drift:
        """Parameter values over time: calibrated values with their std, and
        the values each check's data gave (static parameters only). ``names``
        defaults to every parameter of any calibration, k1..kN first."""
        cals = self.calibrations()
        checks = self.checks()
        if names is None:
            seen: dict[str, None] = {}
            for rec in cals:
                for n in rec.calibration.names:
                    seen.setdefault(n, None)
            stiff = sorted((n for n in seen if is_stiffness_name(n)), key=lambda n: int(n[1:]))
            names = tuple(stiff + [n for n in seen if n not in stiff])
        names = tuple(names)
        units = []
        for n in names:
            unit = ""
            for rec in cals:
                p = rec.calibration.find(n)
                if p is not None:
                    unit = p.unit or ""
                    break
            units.append(unit)
        cv = np.full((len(cals), len(names)), np.nan)
        cs = np.full((len(cals), len(names)), np.nan)
        cd = np.zeros((len(cals), len(names)), dtype=bool)
        for i, rec in enumerate(cals):
            for j, n in enumerate(names):
                p = rec.calibration.find(n)
                if p is not None:
                    cv[i, j] = p.value
                    cs[i, j] = math.nan if p.std is None else p.std
                    cd[i, j] = is_determined(p)
        kv = np.full((len(checks), len(names)), np.nan)
        unexplained = np.full(len(checks), np.nan)
        floor = np.full(len(checks), np.nan)
        friction_rel = np.full((len(checks), 6), np.nan)
        friction_failed = np.zeros((len(checks), 6), dtype=bool)
        friction_tol = np.full(len(checks), np.nan)
        by_id = {rec.id: rec.calibration for rec in cals}
        for i, rec in enumerate(checks):
            _friction_drift(rec.result, by_id.get(rec.calibration_id), names, kv[i])
            friction_tol[i] = _friction_levels(rec.result, rec.verdict, friction_rel[i], friction_failed[i])
            defl = rec.result.get("deflection") if isinstance(rec.result, Mapping) else None
            if not isinstance(defl, Mapping):
                continue
            unexplained[i] = float(defl.get("rms_unexplained", math.nan))
            floor[i] = float(defl.get("noise_floor", math.nan))
            params = defl.get("parameters", {})
            for j, n in enumerate(names):
                p = params.get(n)
                if p is None or p.get("check") is None or p.get("check_std") is None:
                    continue
                value, std = float(p["check"]), float(p["check_std"])
                if value != 0.0 and std / abs(value) <= MAX_CHECK_RELATIVE_STD:
                    kv[i, j] = value
        return Drift(names=names, units=tuple(units),
                     calibration_time_ns=np.array([r.time_ns for r in cals], dtype=np.int64),
                     calibration_value=cv, calibration_std=cs,
                     check_time_ns=np.array([r.time_ns for r in checks], dtype=np.int64), check_value=kv,
                     check_verdict=tuple(r.verdict for r in checks), check_unexplained_m=unexplained,
                     check_noise_floor_m=floor, calibration_determined=cd,
                     check_friction_relative=friction_rel, check_friction_failed=friction_failed,
                     check_friction_tolerance=friction_tol)


#: friction parameters of joint j, which a check's UV/VU runs see together (the mean friction along its path)
FRICTION_PREFIXES = ("fc", "fv", "fl")


def _friction_drift(result: object, calibration: Calibration | None, names: Sequence[str], row: np.ndarray) -> None:
    """A check's friction as parameter values: the runs give the level of each joint's total friction
    along the check path, measured against what the calibration predicts there; each of the joint's
    friction parameters is shown at its calibrated value times that ratio (what the check says it has
    become, if the friction changed in proportion). Only joints the check determined are filled."""
    friction = result.get("friction") if isinstance(result, Mapping) else None
    if calibration is None or not isinstance(friction, Mapping) or not isinstance(friction.get("joints"), Mapping):
        return
    for joint, f in friction["joints"].items():
        if not isinstance(f, Mapping):
            continue
        measured, predicted = f.get("measured"), f.get("predicted")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (measured, predicted)) or not predicted:
            continue
        for prefix in FRICTION_PREFIXES:
            name = f"{prefix}{joint}"
            p = calibration.find(name)
            if name in names and p is not None:
                row[names.index(name)] = p.value * measured / predicted


def _friction_levels(result: object, verdict: str, relative: np.ndarray, failed: np.ndarray) -> float:
    """A check's friction per joint (measured / predicted - 1) and the joints that failed it: significant
    at the check's level (alpha over the joints) and beyond its tolerance, as diagnose/check.py decides;
    a record without p-values fails a joint beyond the tolerance of a check that asked to recalibrate.
    Returns the tolerance (NaN when the check has no friction)."""
    friction = result.get("friction") if isinstance(result, Mapping) else None
    if not isinstance(friction, Mapping) or not isinstance(friction.get("joints"), Mapping):
        return math.nan
    joints = friction["joints"]
    tolerance = friction.get("tolerance")
    tolerance = float(tolerance) if isinstance(tolerance, (int, float)) else DEFAULT_FRICTION_TOLERANCE
    alpha = friction.get("alpha")
    for joint, f in joints.items():
        if not (isinstance(f, Mapping) and str(joint).isdigit() and 1 <= int(joint) <= len(relative)):
            continue
        measured, predicted = f.get("measured"), f.get("predicted")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (measured, predicted)) or not predicted:
            continue
        j = int(joint) - 1
        relative[j] = measured / predicted - 1.0
        beyond = abs(relative[j]) > float(tolerance)
        p = f.get("p_value")
        if isinstance(p, (int, float)) and isinstance(alpha, (int, float)):
            failed[j] = beyond and p < alpha / max(len(joints), 1)
        else:
            failed[j] = beyond and verdict == "recalibrate"
    return tolerance


def drift_summary(drift: Drift) -> dict:
    """Per parameter: first calibrated value, last calibrated value, last check
    estimate, and the latest evidence (a check after the last calibration,
    else the last calibration) relative to the first."""
    out = {}
    for j, name in enumerate(drift.names):
        vals = drift.calibration_value[:, j]
        known = [i for i, v in enumerate(vals) if math.isfinite(v)]
        if not known:
            continue
        first, last_cal = float(vals[known[0]]), float(vals[known[-1]])
        last_cal_t = drift.calibration_time_ns[known[-1]]
        checked = [(t, float(v)) for t, v in zip(drift.check_time_ns, drift.check_value[:, j]) if math.isfinite(v)]
        later = [v for t, v in checked if t >= last_cal_t]
        latest = later[-1] if later else last_cal
        out[name] = {"unit": drift.units[j], "first": first, "last_calibration": last_cal,
                     "last_check": checked[-1][1] if checked else None, "latest": latest,
                     "change": latest / first - 1.0 if first else None,
                     # the change is a finding only when the first and the last calibration determine the value
                     "determined": bool(drift.calibration_determined[known[0], j]
                                        and drift.calibration_determined[known[-1], j])}
    return out


def plot_drift(drift: Drift, path: str | pathlib.Path) -> None:
    """Write the drift plot (PNG or SVG by suffix): :func:`elastocal.report.drift_plot.drift_figure`."""
    path = pathlib.Path(path)
    if path.suffix.lower() not in (".png", ".svg"):
        raise InputError("the drift plot is written as .png or .svg", source=str(path))
    if not len(drift.calibration_time_ns):
        raise InputError("the history holds no calibration to plot", source=str(path))
    from elastocal.report.drift_plot import drift_figure

    drift_figure(drift).savefig(path, dpi=110)


def drift_figure(drift: Drift):
    """The drift plot (:mod:`elastocal.report.drift_plot`)."""
    from elastocal.report.drift_plot import drift_figure as figure

    return figure(drift)
