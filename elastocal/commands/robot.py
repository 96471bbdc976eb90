"""`elastocal robot`: the calibrated robot description for other tools.

``--calibration cal.json --out calibrated.toml [--urdf calibrated.urdf]``: the
robot.toml of the nominal description (``--robot``, or the one the calibration
carries) with the calibration's kinematic errors in its DH table (``a``,
``alpha``, ``d``, ``offset``, Hayati's ``beta``) and marker positions, and
optionally the URDF whose joint origins carry the same corrections, with the
controller's q as joint variable (the offsets and calibrated joint zeros in the
origins), flange, load-point and marker frames and the description's limits
(:mod:`elastocal.model.urdf_export`). elastocal loads either back to the same
forward kinematics; other URDF readers give it at the controller's angles.
"""

from __future__ import annotations

import argparse
import json

from elastocal.commands._inputs import calibration_robot
from elastocal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--calibration", required=True, help="calibration JSON with kinematic_errors")
    parser.add_argument("--robot", help="the nominal robot.toml (default: the description the calibration holds)")
    parser.add_argument("--out", required=True, help="write the calibrated robot.toml here")
    parser.add_argument("--urdf", help="also write the calibrated robot as URDF here (joint variable: the "
                                       "controller's q; docs/robots.md)")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.commands._outputs import Outputs
    from elastocal.identify.accuracy import calibrated_robot
    from elastocal.model.effects import having
    from elastocal.formats.calibration import read_calibration
    from elastocal.model.urdf_export import controller_urdf_robot

    outputs = Outputs(force=args.force, inputs=[(args.calibration, "--calibration"), (args.robot, "--robot")])
    outputs.add(args.out, "--out")
    if args.urdf:
        outputs.add(args.urdf, "--urdf")
    calibration = read_calibration(args.calibration)
    robot = calibration_robot(args, calibration)
    if robot.name != calibration.robot:
        raise InputError(f"the calibration is of robot {calibration.robot!r}, not {robot.name!r}", source="--robot")
    if not having("geometry", calibration.model):
        raise InputError("the calibration holds no kinematic_errors; identify with --model "
                         "...,kinematic_errors,tracker_frame", source="--calibration")
    calibrated = calibrated_robot(robot, calibration)
    if robot.urdf is None:
        what, text = "DH table and markers corrected", calibrated.to_toml()
    else:       # a URDF robot: its corrections live in the chain, written as the URDF at controller angles
        what, text = "URDF at controller angles, markers corrected", controller_urdf_robot(calibrated).to_toml()
    urdf_text = calibrated.to_urdf() if args.urdf else ""   # refused before anything is written
    written = {"robot": args.out}
    with outputs:
        outputs.temp(args.out).write_text(
            f"# {robot.name} calibrated by {args.calibration} (elastocal robot): {what}\n" + text, encoding="utf-8")
        if args.urdf:
            outputs.temp(args.urdf).write_text(urdf_text, encoding="utf-8")
            written["urdf"] = args.urdf
    if args.json:
        print(json.dumps(written))
    else:
        for kind, path in written.items():
            print(f"wrote {kind:<5} {path}")
    return 0
