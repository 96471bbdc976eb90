"""`elastocal import EXPORT... --log LOG.mcap|--joints joints.csv --out static.csv`: tracker
exports plus the robot's joint log as the static table; `elastocal import POSTURES.csv --robot R
--points NAME=X,Y,Z[;…] [--joints COL1,…] --out static.csv`: posture-per-row files (FIGAROH's
calibration CSV among them) as an absolute-only table (docs/import.md)."""

from __future__ import annotations

import argparse
import json

from elastocal.errors import say


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("exports", nargs="+", metavar="EXPORT",
                        help="point files of the tracker software (Leica-style CSV, .xyz, or CSV with --columns); "
                             "with --points, posture-per-row files")
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--log", help="the MCAP log of `elastocal calibrate` (poses, loads, currents, the robot)")
    src.add_argument("--joints", help="a joint/current log CSV: t,q1..q6,i1..i6 [,pose,load] [,fx..mz]; with "
                                      "--points, the joint columns COL1,COL2,… base to tip (default: the robot's "
                                      "joint names)")
    parser.add_argument("--points", metavar="NAME=X,Y,Z[;NAME=X,Y,Z…]",
                        help="posture-per-row files: each row's measured points, a robot marker and its x,y,z "
                             "columns (FIGAROH: R1=x1,y1,z1;R2=x2,y2,z2)")
    parser.add_argument("--angles", choices=("rad", "deg"), default="rad",
                        help="with --points: the unit of the revolute joints' columns (rad)")
    unc = parser.add_mutually_exclusive_group()
    unc.add_argument("--u95", metavar="COL", help="with --points: a column of each row's expanded (k = 2) "
                                                  "uncertainty, in --unit")
    unc.add_argument("--std", metavar="COL", help="with --points: a column of each row's standard uncertainty "
                                                  "per axis, in --unit")
    parser.add_argument("--out", required=True, help="the static table to write (docs/formats.md §2)")
    parser.add_argument("--robot", help="robot.toml to check markers and joint limits against; default: the "
                                        "log's robot (with --log)")
    parser.add_argument("--layout", choices=("auto", "leica", "xyz", "csv"), default="auto",
                        help="the export layout (default: .xyz/.txt files are xyz, --columns means csv, "
                             "else Leica-style CSV)")
    parser.add_argument("--columns", metavar="MAP",
                        help="generic CSV: role=column,... with roles name,x,y,z (required) and t,u95,target,"
                             "temperature,pressure,humidity")
    parser.add_argument("--unit", help="length unit of the coordinates when the header does not say it "
                                       "(m, mm, um, cm, in, ft; .xyz default mm)")
    parser.add_argument("--names", metavar="PATTERN",
                        help="point-name pattern giving pose, load and marker, e.g. 'P{pose}_L{load}_{marker}'")
    parser.add_argument("--by", choices=("name", "time"), default=None,
                        help="pair by name (needs --names) or by timestamp (default: name when --names is given)")
    parser.add_argument("--window", type=float, default=0.5, metavar="S",
                        help="with --joints: joint samples within S seconds around a point are averaged (0.5)")
    parser.add_argument("--tolerance", type=float, default=0.5, metavar="S",
                        help="with --log and --by time: a point up to S seconds outside a reading's window still "
                             "belongs to it (0.5)")
    parser.add_argument("--clock-offset", type=float, default=0.0, metavar="S",
                        help="seconds added to the export's timestamps to put them on the log's clock")
    parser.add_argument("--force", action="store_true", help="overwrite --out")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.acquisition.trackerexports import parse_columns, read_points
    from elastocal.acquisition.trackerimport import NamePattern, build_table, pair_with_joints, pair_with_log, \
        read_joint_csv
    from elastocal.commands._outputs import Outputs, note
    from elastocal.errors import InputError
    from elastocal.formats.tables import format_static_table

    if args.points is not None:
        return _run_postures(args)
    for flag, value in (("--u95", args.u95), ("--std", args.std), ("--angles", args.angles != "rad" or None)):
        if value is not None:
            raise InputError("is for posture-per-row files (with --points)", source=flag)
    if args.log is None and args.joints is None:
        raise InputError("give the joint log (--log LOG.mcap or --joints joints.csv), or --points for "
                         "posture-per-row files", source="--joints")
    for flag, value in (("--window", args.window), ("--tolerance", args.tolerance)):
        if not value > 0 or value != value or value == float("inf"):
            raise InputError(f"must be a positive number of seconds, got {value:g}", source=flag)
    if args.clock_offset != args.clock_offset or abs(args.clock_offset) == float("inf"):
        raise InputError("must be a finite number of seconds", source="--clock-offset")
    names = NamePattern.parse(args.names) if args.names is not None else None
    by = args.by or ("name" if names is not None else "time")
    if by == "name" and names is None:
        raise InputError("pairing by name needs the point-name pattern (--names 'P{pose}_L{load}_{marker}')",
                         source="--by")
    columns = parse_columns(args.columns)
    if columns is not None and args.layout not in ("auto", "csv"):
        raise InputError(f"--columns is for the generic CSV layout, not {args.layout}", source="--columns")
    inputs = [(p, "EXPORT") for p in args.exports] + [(args.log, "--log"), (args.joints, "--joints"),
                                                      (args.robot, "--robot")]
    outputs = Outputs(force=args.force, inputs=inputs)
    out = outputs.add(args.out, "--out")

    points = []
    for path in args.exports:
        points += read_points(path, layout=args.layout, unit=args.unit, columns=columns)
    robot = None
    if args.robot is not None:
        from elastocal.formats.robot_toml import load_robot

        robot = load_robot(args.robot)
    if args.log is not None:
        from elastocal.acquisition.export import robot_from_log
        from elastocal.acquisition.logreader import read_log

        contents = read_log(args.log)
        if robot is None:
            robot = robot_from_log(contents)
        markers = tuple(robot.marker_names)
        rows, unpaired = pair_with_log(points, contents, names=names, by=by, tolerance_s=args.tolerance,
                                       clock_offset_s=args.clock_offset, markers=markers)
        source = args.log
    else:
        joints = read_joint_csv(args.joints)
        markers = tuple(robot.marker_names) if robot is not None else None
        rows, unpaired = pair_with_joints(points, joints, names=names, by=by, window_s=args.window,
                                          clock_offset_s=args.clock_offset, markers=markers)
        source = args.joints
    result = build_table(rows, unpaired, source=source, robot=robot)
    with outputs:
        outputs.temp(out).write_text(format_static_table(result.table), encoding="utf-8")
    if args.json:
        print(json.dumps({"out": str(out), "rows": len(result.table), "points": len(points), "by": by,
                          "columns": [k for k, _ in result.table.extra],
                          "unpaired": [{"file": p.source, "line": p.line, "name": p.name,
                                        "reason": say(why, command_line=True)} for p, why in result.unpaired]}))
    else:
        print(f"wrote {out}: {len(result.table)} rows from {len(points)} points, paired by {by}")
    if result.unpaired:
        note(args, result.unpaired_line(command_line=True))
    return 0


def _run_postures(args: argparse.Namespace) -> int:
    """Posture-per-row files to an absolute-only static table (acquisition.postures)."""
    from elastocal.acquisition.postures import read_postures
    from elastocal.commands._outputs import Outputs
    from elastocal.errors import InputError
    from elastocal.formats.robot_toml import load_robot
    from elastocal.formats.tables import format_static_table

    for flag, given in (("--log", args.log is not None), ("--names", args.names is not None),
                        ("--columns", args.columns is not None), ("--by", args.by is not None),
                        ("--layout", args.layout != "auto")):
        if given:
            raise InputError("is for tracker exports paired with a joint log, not posture-per-row files "
                             "(--points)", source=flag)
    if args.robot is None:
        raise InputError("posture-per-row files need the robot (its joints and markers): give --robot robot.toml",
                         source="--robot")
    outputs = Outputs(force=args.force, inputs=[(p, "EXPORT") for p in args.exports] + [(args.robot, "--robot")])
    out = outputs.add(args.out, "--out")
    robot = load_robot(args.robot)
    table = read_postures(args.exports, robot, joints=args.joints, points=args.points, unit=args.unit or "m",
                          angles=args.angles, u95=args.u95, std=args.std)
    with outputs:
        outputs.temp(out).write_text(format_static_table(table), encoding="utf-8")
    postures = len(set(table.pose))
    if args.json:
        print(json.dumps({"out": str(out), "rows": len(table), "postures": postures,
                          "markers": sorted(set(table.marker)), "columns": [k for k, _ in table.extra]}))
    else:
        print(f"wrote {out}: {len(table)} rows, {postures} postures of {robot.name} "
              f"(markers {', '.join(sorted(set(table.marker)))}), an absolute-only table")
    return 0
