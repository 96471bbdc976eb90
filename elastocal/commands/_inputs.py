"""Inputs shared by identify, diagnose and report (docs/cli.md): a log, or tables."""

from __future__ import annotations

import argparse
import pathlib
from dataclasses import dataclass

from elastocal.errors import InputError
from elastocal.identify.robot import Robot, load_robot
from elastocal.identify.tables import RunTable, StaticTable, read_run_table, read_static_table


@dataclass(frozen=True)
class Inputs:
    robot: Robot
    static: StaticTable | None
    runs: RunTable | None
    files: tuple[pathlib.Path, ...]
    log: pathlib.Path | None = None


def add_input_arguments(parser: argparse.ArgumentParser, *, model_flags: bool = True) -> None:
    parser.add_argument("log", nargs="?", help="an MCAP log written by `elastocal calibrate` (instead of tables)")
    parser.add_argument("--robot", help="robot.toml (docs/formats.md §1)")
    parser.add_argument("--static", help="static deflection table, CSV (docs/formats.md §2)")
    parser.add_argument("--runs", help="run table, CSV (docs/formats.md §3)")
    if model_flags:
        parser.add_argument("--model", default="joint_stiffness",
                            help="comma-separated effects to include (default joint_stiffness)")
        parser.add_argument("--torque", choices=("current", "force"), default="current",
                            help="joint torques from motor currents (default) or from the wrench columns")
        parser.add_argument("--form", choices=("exact", "first-order"), default="exact",
                            help="exact (secant, default) or first-order kinematics")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def add_outlier_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--exclude-outliers", action="store_true",
                        help="refit without the static readings far off their repeats (listed as outliers)")


def input_paths(args: argparse.Namespace) -> list[tuple[str | None, str]]:
    """The input files of the shared flags, with the flag naming each (outputs must differ)."""
    return [(getattr(args, "log", None), "the log"), (getattr(args, "robot", None), "--robot"),
            (getattr(args, "static", None), "--static"), (getattr(args, "runs", None), "--runs")]


def load_log_noted(args: argparse.Namespace, path: str | pathlib.Path):
    """(robot, static table or None, run table or None) of a log, as
    ``acquisition.export.load_log``, with one note for stderr when the log ends
    without its MCAP summary (a killed recorder): what was read is then only
    what came before its last complete chunk."""
    from elastocal.acquisition.export import tables_from_log
    from elastocal.acquisition.logreader import read_log
    from elastocal.commands._outputs import log_note, note

    contents = read_log(path)
    text = log_note(str(path), contents)
    if text:
        note(args, text)
    return tables_from_log(contents)


def load_inputs(args: argparse.Namespace) -> Inputs:
    if args.log:
        if args.static or args.runs:
            raise InputError("give either a log or --static/--runs tables, not both", source=args.log)
        robot, static, runs = load_log_noted(args, args.log)
        if args.robot:
            robot = load_robot(args.robot)
        return Inputs(robot, static, runs, (pathlib.Path(args.log),), pathlib.Path(args.log))
    if not args.robot:
        raise InputError("missing --robot robot.toml (or give a log)", source="--robot")
    if not args.static and not args.runs:
        raise InputError("give --static static.csv and/or --runs runs.csv (or a log)", source="--static")
    robot = load_robot(args.robot)
    static = read_static_table(args.static, robot) if args.static else None
    runs = read_run_table(args.runs, robot) if args.runs else None
    files = tuple(pathlib.Path(p) for p in (args.static, args.runs) if p)
    return Inputs(robot, static, runs, files)
