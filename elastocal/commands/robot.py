"""`elastocal robot`: the calibrated robot description for other tools (issue 12, part 6).

``--calibration cal.json --out calibrated.toml [--urdf calibrated.urdf]``: the
robot.toml of the nominal description (``--robot``, or the one the calibration
carries) with the calibration's kinematic errors in its DH table (``a``,
``alpha``, ``d``, ``offset``, Hayati's ``beta``) and marker positions, and
optionally the URDF whose joint origins carry the same corrections. elastocal
loads either back to the same forward kinematics.
"""

from __future__ import annotations

import argparse
import json

from elastocal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--calibration", required=True, help="calibration JSON with kinematic_errors")
    parser.add_argument("--robot", help="the nominal robot.toml (default: the description the calibration holds)")
    parser.add_argument("--out", required=True, help="write the calibrated robot.toml here")
    parser.add_argument("--urdf", help="also write the calibrated robot as URDF here")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.commands._outputs import Outputs
    from elastocal.identify.accuracy import calibrated_robot
    from elastocal.formats.calibration import read_calibration
    from elastocal.formats.robot_toml import load_robot, parse_robot

    outputs = Outputs(force=args.force, inputs=[(args.calibration, "--calibration"), (args.robot, "--robot")])
    outputs.add(args.out, "--out")
    if args.urdf:
        outputs.add(args.urdf, "--urdf")
    calibration = read_calibration(args.calibration)
    if args.robot:
        robot = load_robot(args.robot)
    elif calibration.robot_description:
        robot = parse_robot(calibration.robot_description, source=f"{args.calibration} (robot_description)")
    else:
        raise InputError("the calibration holds no robot description; give the nominal one with --robot",
                         source="--robot")
    if robot.name != calibration.robot:
        raise InputError(f"the calibration is of robot {calibration.robot!r}, not {robot.name!r}", source="--robot")
    if "kinematic_errors" not in calibration.model:
        raise InputError("the calibration holds no kinematic_errors; identify with --model "
                         "...,kinematic_errors,tracker_frame", source="--calibration")
    if robot.urdf is not None:
        raise InputError("kinematic corrections are written to a modified-DH robot; this one is a URDF robot",
                         source="--robot")
    calibrated = calibrated_robot(robot, calibration)
    written = {"robot": args.out}
    with outputs:
        outputs.temp(args.out).write_text(
            f"# {robot.name} calibrated by {args.calibration} (elastocal robot): DH table and markers corrected\n"
            + calibrated.to_toml(), encoding="utf-8")
        if args.urdf:
            outputs.temp(args.urdf).write_text(calibrated.to_urdf(), encoding="utf-8")
            written["urdf"] = args.urdf
    if args.json:
        print(json.dumps(written))
    else:
        for kind, path in written.items():
            print(f"wrote {kind:<5} {path}")
    return 0
