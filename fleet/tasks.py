"""One fleet task: one log (or table folder) analysed where the task runs.

A :class:`FleetTask` holds paths and options, never data: the process that
runs it opens its own files. :func:`run_task` computes exactly what the
single-log command computes — the same library functions
(:func:`~elastocal.diagnose.pipeline.identify_data`,
:func:`~elastocal.diagnose.pipeline.diagnose_data` and ``diagnosis_json``,
:func:`~elastocal.diagnose.check.check_calibration`) on the same tables — and
returns a small frozen :class:`LogResult`. It never raises: a bad file is a
result with its one-line error.
"""

from __future__ import annotations

import datetime as _dt
import pathlib
import time
from dataclasses import dataclass, field
from typing import Any, Mapping

from elastocal.errors import ElastocalError, InputError
from elastocal.model.kinds import KinematicForm, TorqueSource, expect

#: the analyses a fleet runs, one per single-log command
COMMANDS = ("identify", "diagnose", "check")


@dataclass(frozen=True)
class FleetTask:
    """What to do with one input. ``calibration`` and ``calibration_id`` are the
    check's: the current calibration of the cell's history, read once by the
    caller (a small document, not data)."""

    command: str
    path: str
    tables: bool = False
    cell_config: str | None = None
    cell: str = ""
    model: tuple[str, ...] = ("joint_stiffness",)
    torque: TorqueSource = TorqueSource.CURRENT
    form: KinematicForm = KinematicForm.EXACT
    exclude_outliers: bool = False
    calibration: Any = None          # elastocal.formats.calibration.Calibration
    calibration_id: int | None = None
    alpha: float = 1e-3
    friction_tolerance: float = 0.2

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque, "torque")
        expect(KinematicForm, self.form, "form")
        if self.command not in COMMANDS:
            raise ValueError(f"command must be one of {', '.join(COMMANDS)}, got {self.command!r}")


@dataclass(frozen=True)
class LogResult:
    """What one task gives back (one row of the results table, docs/cli.md ``fleet``).

    ``parameters`` are (name, value, std) in the command's order; ``verdict`` is
    diagnose's (None: no missing effect found), ``decision`` check's (``holds``
    or ``recalibrate``). ``time_ns`` is when the data were measured (the log's
    first session, UTC ns; None for tables). ``calibration`` (identify) and
    ``check`` (check: its ``--json`` object) are what ``--record`` stores."""

    path: str
    command: str
    cell: str = ""
    robot: str = ""
    sha256: str = ""
    error: str = ""
    note: str = ""
    parameters: tuple[tuple[str, float, float | None], ...] = ()
    residual_rms: float | None = None
    noise_floor: float | None = None
    verdict: str | None = None
    decision: str | None = None
    seconds: float = 0.0
    time_ns: int | None = None
    cell_config: str | None = None
    calibration: Any = field(default=None, repr=False)   # a Calibration
    calibration_id: int | None = None
    check: Mapping[str, Any] | None = field(default=None, repr=False)
    plan: str | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        return not self.error


def error_text(exc: BaseException) -> str:
    """One line for an error: an expected error's own message, else its type and message."""
    if isinstance(exc, InputError):
        exc = exc.on_command_line()        # as `elastocal identify|diagnose|check` says it
    text = str(exc) if isinstance(exc, ElastocalError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split()) or type(exc).__name__


def _utc_ns(started_utc: str | None) -> int | None:
    if not started_utc:
        return None
    try:
        t = _dt.datetime.fromisoformat(str(started_utc).replace("Z", "+00:00"))
    except ValueError:
        return None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.timezone.utc)
    return int(t.timestamp()) * 1_000_000_000 + t.microsecond * 1000


@dataclass(frozen=True)
class _Data:
    robot: Any
    static: Any
    runs: Any
    files: tuple[pathlib.Path, ...]
    data_file: pathlib.Path          # the file whose hash names the data (the log, or the table check uses)
    cell: str
    note: str
    time_ns: int | None
    plan: str | None
    #: where the log's cell.toml says the tracker stands (a prior on the registration, as
    #: ``elastocal identify LOG`` takes it)
    tracker_prior: tuple[float, float, float] | None = None


def _load(task: FleetTask) -> _Data:
    """The task's robot and tables, read as the single-log command reads them."""
    from elastocal.errors import InputError

    path = pathlib.Path(task.path)
    cell_robot = None
    if task.command == "check":   # check reads the tables with the cell's robot
        from elastocal.drivers.config import load_cell_config

        cell_robot = load_cell_config(task.cell_config).load_robot()
    if task.tables:
        from elastocal.formats.robot_toml import load_robot
        from elastocal.formats.tables import read_run_table, read_static_table

        static_csv, runs_csv = path / "static.csv", path / "runs.csv"
        if cell_robot is not None:
            robot = cell_robot
        elif (path / "robot.toml").is_file():
            robot = load_robot(path / "robot.toml")
        elif task.cell_config is not None:
            from elastocal.drivers.config import load_cell_config

            robot = load_cell_config(task.cell_config).load_robot()
        else:
            raise InputError("a table folder needs its robot.toml (or a cell.toml above it)", source=str(path))
        static = read_static_table(static_csv, robot) if static_csv.is_file() else None
        runs = read_run_table(runs_csv, robot) if runs_csv.is_file() else None
        files = tuple(p for p in (static_csv, runs_csv) if p.is_file())
        return _Data(robot, static, runs, files, files[0], task.cell, "", None, None)
    from elastocal.acquisition.export import tables_from_log, tracker_position_from_log
    from elastocal.acquisition.logreader import read_log

    contents = read_log(path)
    robot, static, runs = tables_from_log(contents)
    if cell_robot is not None:
        robot = cell_robot
    note = "" if contents.complete else ("the log ends without its MCAP summary (the recorder was killed or is "
                                         "still writing); everything up to its last complete chunk was read")
    cell = task.cell or (contents.cell.name if contents.cell is not None else "")
    started = contents.sessions[0].get("started_utc") if contents.sessions else None
    plan = contents.plan.text if contents.plan is not None else None
    return _Data(robot, static, runs, (path,), path, cell, note, _utc_ns(started), plan,
                 tracker_position_from_log(contents))


def _parameters(params: Mapping[str, Any]) -> tuple[tuple[str, float, float | None], ...]:
    out = []
    for name, p in params.items():
        std = p.get("std")
        out.append((str(name), float(p["value"]), None if std is None else float(std)))
    return tuple(out)


def _identify(task: FleetTask, data: _Data) -> dict:
    from elastocal.errors import InputError
    from elastocal.diagnose.pipeline import identify_data

    if data.static is None and data.runs is None:
        raise InputError("the log holds neither a static experiment nor runs", source=task.path)
    result = identify_data(data.robot, data.static, data.runs, task.model, task.torque, task.form,
                           exclude_outliers=task.exclude_outliers, tracker_prior=data.tracker_prior)
    obj = result.to_json()
    cal = result.calibration(data.robot.name, data.files)
    return {"parameters": _parameters(obj["parameters"]), "residual_rms": obj["residual"]["rms"],
            "noise_floor": obj.get("noise_floor"), "calibration": cal}


def _diagnose(task: FleetTask, data: _Data) -> dict:
    from elastocal.diagnose.pipeline import diagnose_data, diagnosis_json

    static, runs = diagnose_data(data.robot, data.static, data.runs, task.model, task.torque, task.form,
                                 log=None if task.tables else task.path, exclude_outliers=task.exclude_outliers,
                                 tracker_prior=data.tracker_prior)
    obj = diagnosis_json(static, runs)
    return {"residual_rms": obj["residual"]["rms"], "noise_floor": obj.get("noise_floor"),
            "verdict": obj.get("verdict")}


def _check(task: FleetTask, data: _Data) -> dict:
    from elastocal.acquisition.history import clean
    from elastocal.errors import InputError
    from elastocal.diagnose.check import check_calibration

    if task.calibration is None:
        raise InputError("no calibration to check against: the cell's history holds none", source=task.cell_config)
    cal = task.calibration
    if cal.robot and cal.robot != data.robot.name:
        raise InputError(f"the calibration is for {cal.robot!r}, the cell's robot is {data.robot.name!r}",
                         source=task.cell_config)
    if data.static is None and data.runs is None:
        raise InputError("nothing to check: the log holds neither static poses nor runs", source=task.path)
    result = check_calibration(data.robot, cal, static=data.static, runs=data.runs, alpha=task.alpha,
                               friction_tolerance=task.friction_tolerance)
    obj = clean(result.to_json())
    defl = obj.get("deflection") or {}
    params = tuple((str(n), float(p["check"]), None if p.get("check_std") is None else float(p["check_std"]))
                   for n, p in (defl.get("parameters") or {}).items() if p.get("check") is not None)
    return {"parameters": params, "residual_rms": defl.get("rms_unexplained"),
            "noise_floor": defl.get("noise_floor"), "decision": obj["verdict"], "check": obj}


_ANALYSES = {"identify": _identify, "diagnose": _diagnose, "check": _check}


def run_task(task: FleetTask) -> LogResult:
    """Analyse one input; a failure is a result with its error, never an exception."""
    start = time.perf_counter()
    base = {"path": task.path, "command": task.command, "cell_config": task.cell_config,
            "calibration_id": task.calibration_id}
    sha = ""
    try:
        from elastocal.formats.calibration import file_sha256

        data = _load(task)
        sha = file_sha256(data.data_file)
        values = _ANALYSES[task.command](task, data)
    except Exception as exc:  # noqa: BLE001 -- every failure stays with its file (docs/fleet.md)
        if not sha and not task.tables:
            try:
                from elastocal.formats.calibration import file_sha256

                sha = file_sha256(task.path)
            except OSError:
                sha = ""
        return LogResult(**base, cell=task.cell, sha256=sha, error=error_text(exc), seconds=time.perf_counter() - start)
    return LogResult(**base, cell=data.cell, robot=data.robot.name, sha256=sha, note=data.note,
                     time_ns=data.time_ns, plan=data.plan, seconds=time.perf_counter() - start,
                     **values)
