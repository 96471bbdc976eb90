"""Inputs shared by identify, diagnose and report (docs/cli.md): a log, or tables."""

from __future__ import annotations

import argparse
import pathlib
from dataclasses import dataclass, replace

from elastocal.errors import InputError
from elastocal.model.robot import Robot
from elastocal.formats.robot_toml import load_robot
from elastocal.formats.tables import RunTable, StaticTable, read_run_table, read_static_table
from elastocal.model.kinds import KinematicForm, TorqueSource


@dataclass(frozen=True)
class Inputs:
    robot: Robot
    static: StaticTable | None
    runs: RunTable | None
    files: tuple[pathlib.Path, ...]
    log: pathlib.Path | None = None
    #: where the log's cell.toml says the tracker stands ([tracker] base_p_tracker), if it says
    tracker_position: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class TrackerPrior:
    """Where the tracker stands in base coordinates [m] and who says so (a flag or a cell.toml)."""

    base_p_tracker: tuple[float, float, float]
    source: str


def add_input_arguments(parser: argparse.ArgumentParser, *, model_flags: bool = True,
                        several_logs: bool = False) -> None:
    if several_logs:    # the rounds of one cell diagnosed together (docs/plan.md, "The next experiment")
        parser.add_argument("log", nargs="*", help="MCAP logs written by `elastocal calibrate` (instead of tables); "
                                                   "several: their static experiments diagnosed together")
    else:
        parser.add_argument("log", nargs="?", help="an MCAP log written by `elastocal calibrate` (instead of tables)")
    parser.add_argument("--robot", help="robot.toml (docs/formats.md §1)")
    parser.add_argument("--static", help="static deflection table, CSV (docs/formats.md §2)")
    parser.add_argument("--runs", help="run table, CSV (docs/formats.md §3)")
    if model_flags:
        parser.add_argument("--model", default=None,
                            help="comma-separated effects to include (default joint_stiffness; on a table "
                                 "without loads kinematic_errors,tracker_frame)")
        parser.add_argument("--torque", choices=[t.value for t in TorqueSource], default="current",
                            help="joint torques from motor currents (default) or from the wrench columns")
        parser.add_argument("--form", choices=[f.value for f in KinematicForm], default="exact",
                            help="exact (secant, default) or first-order kinematics")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def add_outlier_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--exclude-outliers", action="store_true",
                        help="refit without the static readings far off their repeats (listed as outliers)")


def add_tracker_arguments(parser: argparse.ArgumentParser) -> None:
    """--cell and --tracker-position: a prior on the tracker's registration (docs/absolute.md)."""
    parser.add_argument("--cell", help="cell.toml whose [tracker] base_p_tracker is a prior of 0.1 m on the "
                                       "registration (default: the cell.toml a log carries)")
    parser.add_argument("--tracker-position", metavar="X,Y,Z",
                        help="where the tracker stands in base coordinates [m] (cell.toml's [tracker] "
                             "base_p_tracker): a prior of 0.1 m on the registration (docs/absolute.md)")


def _position(text: str) -> tuple[float, float, float]:
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"expected x,y,z in metres, got {text!r}", source="--tracker-position") from None
    if len(values) != 3 or not all(abs(v) < 100.0 for v in values):
        raise InputError(f"expected 3 finite numbers x,y,z in metres, got {text!r}", source="--tracker-position")
    return tuple(values)



def calibration_robot(args: argparse.Namespace, calibration) -> Robot:
    """The robot a calibration is applied to: ``--robot`` when given, else the description the
    calibration file carries (``robot_description``); refused in one line when neither is there."""
    from elastocal.formats.robot_toml import parse_robot

    if args.robot:
        return load_robot(args.robot)
    if calibration.robot_description:
        return parse_robot(calibration.robot_description, source=f"{args.calibration} (robot_description)")
    raise InputError("the calibration holds no robot description; give the nominal one with --robot",
                     source="--robot")

def tracker_prior(args: argparse.Namespace, inputs: "Inputs | None" = None) -> TrackerPrior | None:
    """The tracker position prior: ``--tracker-position``, else ``--cell``'s [tracker]
    base_p_tracker, else the one of the cell.toml the log carries; None when nobody says."""
    text = getattr(args, "tracker_position", None)
    if text is not None:
        return TrackerPrior(_position(text), "--tracker-position")
    cell_path = getattr(args, "cell", None)
    if cell_path:
        from elastocal.drivers.config import load_cell_config

        cell = load_cell_config(cell_path)
        if cell.tracker is None or cell.tracker.base_p_tracker is None:
            return None
        return TrackerPrior(cell.tracker.base_p_tracker, f"{cell_path} [tracker] base_p_tracker")
    if inputs is not None and inputs.tracker_position is not None:
        return TrackerPrior(inputs.tracker_position, f"{inputs.log}'s cell.toml [tracker] base_p_tracker")
    return None


def prior_line(prior: TrackerPrior | None, registration: dict | None) -> str | None:
    """One line on the prior and how far the registration found is from it (None without a prior)."""
    if prior is None or registration is None:
        return None
    base_p = registration["base_p_tracker"]
    offset = sum((a - b) ** 2 for a, b in zip(base_p, prior.base_p_tracker)) ** 0.5
    where = ", ".join(f"{v:.3f}" for v in base_p)
    said = ", ".join(f"{v:.3f}" for v in prior.base_p_tracker)
    from elastocal.identify.absolute import TRACKER_PRIOR_STD_M

    words = (f": more than 3x the prior's {TRACKER_PRIOR_STD_M:g} m (a wrong cell file, or the tracker moved)"
             if offset > 3.0 * TRACKER_PRIOR_STD_M else "")
    return (f"tracker at ({where}) m in base coordinates, {offset:.3f} m from ({said}) m of {prior.source}"
            f"{words}")


def input_paths(args: argparse.Namespace) -> list[tuple[str | None, str]]:
    """The input files of the shared flags, with the flag naming each (outputs must differ)."""
    return [(getattr(args, "log", None), "the log"), (getattr(args, "robot", None), "--robot"),
            (getattr(args, "static", None), "--static"), (getattr(args, "runs", None), "--runs")]


def load_log_noted(args: argparse.Namespace, path: str | pathlib.Path, *, with_tracker: bool = False):
    """(robot, static table or None, run table or None) of a log, as
    ``acquisition.export.load_log``, with one note for stderr when the log ends
    without its MCAP summary (a killed recorder): what was read is then only
    what came before its last complete chunk. ``with_tracker``: and where the
    log's cell.toml says the tracker stands (or None)."""
    from elastocal.acquisition.export import tables_from_log, tracker_noise_from_log, tracker_position_from_log
    from elastocal.acquisition.logreader import read_log
    from elastocal.commands._outputs import log_note, note

    contents = read_log(path)
    text = log_note(str(path), contents)
    if text:
        note(args, text)
    if with_tracker:
        robot, static, runs = tables_from_log(contents)
        noise = tracker_noise_from_log(contents)
        if static is not None and noise is not None:      # the cell's stated law travels with the table
            static = replace(static, tracker_noise=noise)
        return robot, static, runs, tracker_position_from_log(contents)
    return tables_from_log(contents)


def _load_several(args: argparse.Namespace, logs: list[str]) -> Inputs:
    """The static experiments of several logs of one robot as one table (pose ids kept apart)."""
    from elastocal.formats.tables import concat_static_tables

    robot, tables, tracker = None, [], None
    for path in logs:
        r, static, runs, where = load_log_noted(args, path, with_tracker=True)
        if runs is not None:
            raise InputError("runs of several logs are not diagnosed together: give the log with runs alone",
                             source=path)
        if static is None:
            raise InputError("the log holds no static experiment", source=path)
        if robot is not None and (r.marker_names != robot.marker_names or r.n_joints != robot.n_joints):
            raise InputError(f"another robot or other markers than {logs[0]}", source=path)
        robot, tracker = robot or r, tracker or where
        tables.append(static)
    if args.robot:
        robot = load_robot(args.robot)
    return Inputs(robot, concat_static_tables(tables), None, tuple(pathlib.Path(p) for p in logs),
                  pathlib.Path(logs[0]), tracker)


def load_inputs(args: argparse.Namespace) -> Inputs:
    if isinstance(args.log, list):      # a command that takes several logs
        if len(args.log) > 1:
            if args.static or args.runs:
                raise InputError("give either logs or --static/--runs tables, not both", source=args.log[0])
            return _load_several(args, args.log)
        args = argparse.Namespace(**{**vars(args), "log": args.log[0] if args.log else None})
    if args.log:
        if args.static or args.runs:
            raise InputError("give either a log or --static/--runs tables, not both", source=args.log)
        robot, static, runs, tracker = load_log_noted(args, args.log, with_tracker=True)
        if args.robot:
            robot = load_robot(args.robot)
        return Inputs(robot, _with_cell_noise(args, _with_robot_noise(robot, static)), runs,
                      (pathlib.Path(args.log),), pathlib.Path(args.log), tracker)
    if not args.robot:
        raise InputError("missing --robot robot.toml (or give a log)", source="--robot")
    if not args.static and not args.runs:
        raise InputError("give --static static.csv and/or --runs runs.csv (or a log)", source="--static")
    robot = load_robot(args.robot)
    static = read_static_table(args.static, robot) if args.static else None
    runs = read_run_table(args.runs, robot) if args.runs else None
    files = tuple(pathlib.Path(p) for p in (args.static, args.runs) if p)
    return Inputs(robot, _with_cell_noise(args, static), runs, files)


def _with_robot_noise(robot: Robot, static: StaticTable | None) -> StaticTable | None:
    """The static table with robot.toml's ``[tracker] noise`` law when no cell.toml named one."""
    if static is None or static.tracker_noise is not None or robot.tracker_noise is None:
        return static
    return replace(static, tracker_noise=robot.tracker_noise)


def _with_cell_noise(args: argparse.Namespace, static: StaticTable | None) -> StaticTable | None:
    """The static table with ``--cell``'s ``[tracker] noise`` law (docs/cell-config.md), when
    both are given (it comes before the one of the cell.toml a log carries)."""
    cell_path = getattr(args, "cell", None)
    if static is None or not cell_path:
        return static
    from elastocal.drivers.config import load_cell_config

    cell = load_cell_config(cell_path)
    if cell.tracker is None or cell.tracker.noise is None:
        return static
    return replace(static, tracker_noise=cell.tracker.noise)


def table_model(args: argparse.Namespace, inputs: "Inputs", model: tuple[str, ...]) -> tuple[str, ...]:
    """The model for these inputs: an absolute-only static table (no loads, no runs) takes the effects
    named, joint_stiffness only when named, and without --model kinematic_errors,tracker_frame."""
    from elastocal.model.effects import parse_model

    if inputs.static is not None and inputs.runs is None and inputs.static.absolute_only:
        return parse_model(args.model, absolute_only=True)
    return model
