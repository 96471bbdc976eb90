"""Guided calibration procedures: steps over a :class:`CellIO`, recorded to MCAP.

A procedure is a list of :class:`Step` built from the plan:

* ``static``: per pose, the unloaded reference then each load state; at each,
  wait until the cell settles (joint speeds about zero, tracker spread below a
  threshold over a window), then ``repeats`` readings of every marker;
* ``friction``: the same slow path forward (UV) and backward (VU), at each
  speed and load, recorded continuously;
* ``sweep``: joint 2 (the plan's ``[sweep] joint``, the compensator's) swept forward (+) and
  backward (-) for the compensator;
* ``check``: a few static poses under one load and one UV/VU pair.

Steps that need a person (hanging or removing a load, clearing the cell
before the first move) ask for confirmation first; an abort at any prompt
ends the procedure with a complete log. A step is the unit of resumption:
``resume_from`` copies the completed steps of an interrupted log and runs the
rest. Acquisition computes no physics: nominal load wrenches are the plan's
masses times the robot's gravity vector.
"""

from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass
from typing import Sequence


from elastocal.formats import logformat as lf
from elastocal.acquisition.cellio import CellIO
from elastocal.acquisition.logreader import LogReader, read_log
from elastocal.formats.plan import UNLOADED, Plan
from elastocal.acquisition.recorder import Recorder
from elastocal.acquisition.session import Session
from elastocal.acquisition.steps import PERSON_S, build_steps
from elastocal.acquisition.ui import Aborted, AutoUI, OperatorUI
from elastocal.errors import Arg, DeviceError, InputError
from elastocal.formats.textfiles import read_text_file


@dataclass(frozen=True)
class Outcome:
    """How a calibration session ended."""

    path: str
    status: str                 # "completed" or "aborted"
    steps_total: int
    steps_done: int             # done in this log, including the ones copied from resume_from
    steps_resumed: int          # copied from resume_from
    duration_s: float
    message: str = ""
    skipped: tuple[str, ...] = ()   # labels of the steps an unattended run left out (they need a person)


# ------------------------------------------------------------------ running
def _copy_completed(old_path: str | pathlib.Path, rec: Recorder, last_done_event: int) -> None:
    """Copy the messages of an interrupted log up to its last ``step_done``."""
    events_seen = -1
    for topic, m in LogReader(old_path).raw_messages():
        if topic in (lf.TOPIC_SESSION, lf.TOPIC_ROBOT, lf.TOPIC_CELL, lf.TOPIC_PLAN):
            continue
        rec.copy(topic, m.log_time, m.publish_time, m.data)
        if topic == lf.TOPIC_EVENT:
            events_seen += 1
            if events_seen == last_done_event:
                break
    rec.flush()


def _procedures(plan: Plan, procedures: Sequence[str] | None) -> tuple[str, ...]:
    procs = tuple(procedures) if procedures else plan.procedures
    for p in procs:
        if p not in plan.procedures and not (p == "check" and plan.check is not None):
            raise InputError(f"procedure {p!r} is not in the plan", source=plan.source, column="procedures")
    return procs


def _check_out(out_path: str | pathlib.Path, overwrite: bool, resume_from) -> None:
    out = pathlib.Path(out_path)
    if out.exists() and not overwrite:
        raise InputError(("already exists; choose another ", Arg("out"), ", or ", Arg("force", True),
                          " to overwrite it"), source=str(out))
    if resume_from is not None:
        if not pathlib.Path(resume_from).is_file():
            raise InputError("cannot read: no such log", source=str(resume_from))
        if pathlib.Path(resume_from).resolve() == out.resolve():
            raise InputError((Arg("resume"), " must name the interrupted log, ", Arg("out"), " a new file"),
                             source=str(out))


def _without_a_person(steps: list, procs: Sequence[str], plan: Plan) -> tuple[list, tuple[str, ...]]:
    """(the steps that run with nobody at the cell, what is left out); refused when none remains."""
    skipped = tuple(s.label if s.needs_person else s.leaves_out for s in steps if s.needs_person or s.leaves_out)
    steps = [s for s in steps if not s.needs_person]
    if not steps:
        raise InputError(f"no step of {', '.join(procs)} runs without a person at the cell (each hangs a "
                         "load): nothing to do unattended", source=plan.source)
    return steps, skipped


def _resumed(resume_from, plan: Plan, robot_text: str, steps: list) -> tuple[set[str], dict[str, float], int]:
    """(the steps the interrupted log completed, how long each took [s], the index of its last
    step_done event); refused when the log was recorded with another plan or robot."""
    old = read_log(resume_from)
    if old.plan is None or old.plan.sha256 != plan.sha256:
        raise InputError("the log was recorded with another plan; resume with the same plan.toml",
                         source=str(resume_from))
    if old.robot is None or old.robot.text != robot_text:
        raise InputError("the log was recorded with another robot description", source=str(resume_from))
    done_before = set(old.completed_steps) & {s.id for s in steps}
    took_s: dict[str, float] = {}
    last_done_event = -1
    started_at: dict[str, int] = {}
    for i, e in enumerate(old.events):
        if e["kind"] == "step_start":
            started_at[e.get("step_id")] = e["t_ns"]
        if e["kind"] == "step_done":
            last_done_event = i
            if e.get("step_id") in started_at:
                took_s[e["step_id"]] = (e["t_ns"] - started_at[e["step_id"]]) * 1e-9
    return done_before, took_s, last_done_event


def _run_steps(session: Session, steps: list, done_before: set[str]) -> None:
    """Each step not done before, in order; the last load taken off at the end."""
    for index, step in enumerate(steps):
        if step.id in done_before:
            continue
        session.begin_step(index, step)
        step.action(session)
        session.end_step()
    if session.load_state not in (None, UNLOADED):
        # the last load comes off, confirmed by a person, before the robot moves again
        session.ensure_load(UNLOADED)


def run_procedures(io: CellIO, plan: Plan, out_path: str | pathlib.Path, *, ui: OperatorUI | None = None,
                   procedures: Sequence[str] | None = None, resume_from: str | pathlib.Path | None = None,
                   cell_text: str = "", cell_name: str = "cell", cell_path: str | None = None,
                   robot_text: str | None = None, overwrite: bool = False,
                   recorder_options: dict | None = None, unattended: bool = False) -> Outcome:
    """Run the plan's procedures on ``io`` and record everything to ``out_path``.

    Returns the :class:`Outcome` (completed or aborted by the operator); a
    device failure is recorded as a ``fault`` event and raised, with the
    failed :class:`Outcome` (log path, steps done) as its ``outcome``
    attribute. ``resume_from``
    names an interrupted log of the same plan and robot: its completed steps
    are copied into the new log and skipped.

    ``unattended``: no person is at the cell (a scheduled check). The steps that
    need one (hanging or removing a load) are left out, a check pose reads its
    markers unloaded only, and what was left out is listed in the outcome's
    ``skipped``; the cell is taken as unloaded, as every procedure leaves it,
    and nothing is asked. Refused when no step remains.
    """
    ui = ui if ui is not None else AutoUI(quiet=True)
    robot = io.robot
    plan.validate_for(robot)
    procs = _procedures(plan, procedures)
    steps = build_steps(plan, procs, person_s=0.0 if ui.automatic else PERSON_S, unattended=unattended)
    steps, skipped = _without_a_person(steps, procs, plan) if unattended else (steps, ())
    robot_text = robot_text if robot_text is not None else robot.to_toml()
    out_path = pathlib.Path(out_path)
    _check_out(out_path, overwrite, resume_from)
    done_before, took_s, last_done_event = (_resumed(resume_from, plan, robot_text, steps)
                                            if resume_from is not None else (set(), {}, -1))
    started = time.monotonic()
    world = io.world()
    with Recorder(out_path, overwrite=overwrite, clock=io.clock,
                  resumed_from=None if resume_from is None else str(resume_from),
                  **(recorder_options or {})) as rec:
        rec.document("robot", robot.name, robot_text)
        rec.document("cell", cell_name, cell_text, cell_path)
        rec.document("plan", plan.name, plan.text, plan.source)
        if resume_from is not None and last_done_event >= 0:
            _copy_completed(resume_from, rec, last_done_event)
            rec.event("resume", text=str(resume_from), completed_steps=sorted(done_before))
        io.start()
        session = Session(io, rec, ui, plan, steps, world)
        session.event("procedure_start", procedure=",".join(procs), steps=len(steps))
        remaining = [s for s in steps if s.id not in done_before]
        if unattended:
            session.load_state = UNLOADED
            session.event("unattended", text="no person at the cell: the cell is taken as unloaded; skipped "
                                             + ("; ".join(skipped) or "nothing"))
        for step in steps:          # the steps the resumed log did count as done from the start
            if step.id in done_before:
                session.skip_step(step, took_s.get(step.id))
        try:
            if remaining and not unattended:
                session.confirm(f"the robot will run {len(remaining)} step(s) of {', '.join(procs)}; "
                                f"clear the cell")
            _run_steps(session, steps, done_before)
        except (Aborted, KeyboardInterrupt) as exc:
            text = str(exc) if isinstance(exc, Aborted) else "interrupted (Ctrl-C)"
            session.step = None
            session.event("procedure_end", status="aborted", text=text)
            ui.close()
            return Outcome(str(out_path), "aborted", len(steps), session.done, len(done_before),
                           time.monotonic() - started, text)
        except DeviceError as exc:
            session.event("fault", error=type(exc).__name__, text=str(exc))
            session.step = None
            session.event("procedure_end", status="failed", text=str(exc))
            ui.close()
            # where the log is and how far it got, for the resume hint (the error stays the device's)
            exc.outcome = Outcome(str(out_path), "failed", len(steps), session.done, len(done_before),
                                  time.monotonic() - started, f"{type(exc).__name__}: {exc}")
            raise
        session.event("procedure_end", status="completed")
        ui.close()
    return Outcome(str(out_path), "completed", len(steps), session.done, len(done_before),
                   time.monotonic() - started, skipped=skipped)


def log_robot_text(robot, robot_path) -> str:
    """The robot description the log keeps: the file as written (comments kept),
    or, for a robot whose URDF is a separate file, the description with the
    URDF inline, so that the log stands alone."""
    if robot.urdf is not None and robot.urdf.path:
        return robot.to_toml()
    return read_text_file(robot_path)


def run_calibration(cell_config, plan: Plan, out_path: str | pathlib.Path, *, yes: bool = True,
                    ui: OperatorUI | None = None, world=None,
                    procedures: Sequence[str] | None = None, resume_from: str | pathlib.Path | None = None,
                    overwrite: bool = False, unattended: bool = False) -> Outcome:
    """The guided calibration of the cell ``cell_config`` (a
    :class:`elastocal.drivers.config.CellConfig`) by ``plan``, recorded to ``out_path``.

    The devices are opened from the config (``elastocal.drivers.open_cell``).
    ``world`` is where a simulated cell hangs its loads: a
    :class:`~elastocal.acquisition.cellio.LoadWorld` (``hang``), or a simulated world
    with ``set_load``/``remove_load``; the caller that serves the simulated cell (or
    opens a served cell's load rig) passes it, None for a real cell. ``yes`` answers
    every prompt automatically (``ui`` defaults to a silent :class:`AutoUI`; otherwise a
    :class:`TerminalUI`) and is refused for a real cell, where a person must
    confirm each load change.
    """
    import contextlib

    from elastocal.acquisition.drivercell import DriverCellIO
    from elastocal.acquisition.ui import TerminalUI
    from elastocal.drivers import open_cell

    if ui is None:
        ui = AutoUI(quiet=True) if yes else TerminalUI()
    if yes and world is None:
        raise InputError((Arg("yes"), " answers the prompts of a simulated cell only; a person confirms every "
                          "load change on a real cell"), argument="yes")
    robot_path = cell_config.robot_path()
    robot = cell_config.load_robot()
    plan.validate_for(robot)
    _procedures(plan, procedures)
    _check_out(out_path, overwrite, resume_from)
    with contextlib.ExitStack() as stack:
        devices = stack.enter_context(open_cell(cell_config))
        io = stack.enter_context(DriverCellIO(robot, cell_config, drives=list(devices.drives.values()),
                                              tracker=devices.tracker, controller=devices.controller,
                                              world=world))
        return run_procedures(io, plan, out_path, ui=ui, procedures=procedures, resume_from=resume_from,
                              cell_text=cell_config.to_toml(), cell_name=cell_config.name,
                              cell_path=str(cell_config.source),
                              robot_text=log_robot_text(robot, robot_path), overwrite=overwrite,
                              unattended=unattended)
