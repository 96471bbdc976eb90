"""`elastocal compensate`: compensated joint trajectory for a planned path (docs/cli.md)."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from elastocal.errors import InputError
from elastocal.model.kinds import CompensatorKind, KinematicForm


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robot", required=True, help="robot description (robot.toml)")
    parser.add_argument("--calibration", required=True, help="calibration JSON (docs/formats.md §4)")
    parser.add_argument("--path", required=True, help="planned path CSV: t,q1..q6 and optionally fx..mz")
    parser.add_argument("--out", required=True, help="compensated path CSV to write")
    parser.add_argument("--wrench", metavar="FX,FY,FZ[,MX,MY,MZ]",
                        help="constant process wrench on the load point [N, N*m, base axes]; the moments 0 when "
                             "left out")
    parser.add_argument("--form", default="exact", choices=[f.value for f in KinematicForm],
                        help="exact (default): the loaded robot reaches the plan; first-order: q - dtheta (Yang)")
    parser.add_argument("--reference", default=None, choices=("unloaded", "rigid", "nominal"),
                        help="what the plan means: the pose the robot reaches without the process load "
                             "(default without a geometric calibration), the rigid kinematic pose (removes "
                             "gravity sag too), or the pose the drawing's robot gives the tool (default with "
                             "kinematic_errors in the calibration: geometry, sag and load compensated)")
    parser.add_argument("--tool", default=None, metavar="MARKER",
                        help="the point the path positions: the load point (default) or a marker of the tool "
                             "(a point the calibration measured)")
    parser.add_argument("--without", metavar="EFFECTS",
                        help="comma-separated effects of the calibration to leave out knowingly: compensation "
                             "models the joint springs, gravity, the compensator and the geometry, and refuses a "
                             "calibration holding other static effects (link_compliance, backlash, ...) unless "
                             "they are named here (their deflection then stays uncorrected)")
    parser.add_argument("--krl", metavar="FILE", help="also write a KUKA KRL program (.src)")
    parser.add_argument("--rapid", metavar="FILE", help="also write an ABB RAPID module (.mod)")
    parser.add_argument("--validate", action="store_true",
                        help="run the planned and compensated paths on the simulated cell made of the "
                             "calibrated robot (its stiffness, geometry and every effect it holds) and report "
                             "the tool-point errors")
    parser.add_argument("--force", action="store_true", help="overwrite --out, --krl and --rapid if they exist")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _parse_wrench(text: str) -> np.ndarray:
    from elastocal.commands._flags import parse_wrench

    return np.array(parse_wrench(text, "--wrench"))


def _not_converged(exc, planned, wrench: np.ndarray, args: argparse.Namespace) -> InputError:
    """The sample the static model has no equilibrium for, by file, line and its largest wrench column."""
    i = exc.sample
    w = wrench[i]
    col = ("fx", "fy", "fz", "mx", "my", "mz")[int(np.argmax(np.abs(w)))]
    what = (f"the static model does not converge under the wrench {', '.join(f'{v:g}' for v in w)} "
            "(stiffness too low for so large a load?)")
    if planned.wrench is None:
        return InputError(f"{what}, at sample {i + 1} of {args.path}", source="--wrench")
    line = int(planned.line[i]) if planned.line is not None else i + 2
    return InputError(what, source=args.path, row=line, column=col)


def calibrated_truth(robot, cal, default):
    """The simulated cell's truth made of what the calibration holds (``default``, the
    simulator's own truth, for the rest: no hidden effect, its tracker), and the names of
    the effects taken from the calibration. --validate then runs the compensation on the
    robot the calibration describes, not on the simulator's default one."""
    import dataclasses

    from elastocal.identify.kinematics import parameter_names
    from elastocal.model.effects import having

    changes: dict = {"stiffness": np.array([cal.value(f"k{j}") for j in range(1, robot.n_joints + 1)])}
    holds = ["joint_stiffness"]
    spec = robot.compensator
    if spec is not None and all(cal.has(n) for n in spec.parameter_names):
        changes["compensator"] = tuple(cal.value(n) for n in spec.parameter_names)
        holds.append("compensator")
    if having("geometry", cal.model):        # a DH table's errors, or a URDF robot's joint origins
        changes["kinematic_errors"] = tuple((n, cal.value(n)) for n in parameter_names(robot, robot.marker_names)
                                            if cal.has(n))
        holds.append("kinematic_errors")
    springs = robot.link_spring_names
    if springs and all(cal.has(n) for n in springs):     # the link springs' compliances
        changes["link_compliance"] = np.array([cal.value(n) for n in springs])
        holds.append("link_compliance")
    plays = [f"b{j}" for j in range(1, robot.n_joints + 1)]
    if all(cal.has(n) for n in plays):                   # each joint's play
        changes["backlash"] = np.array([cal.value(n) for n in plays])
        holds.append("backlash")
    return dataclasses.replace(default, **changes), tuple(holds)


def _stats(d: np.ndarray) -> dict:
    n = np.linalg.norm(d, axis=1)
    return {"rms": float(np.sqrt(np.mean(n ** 2))), "max": float(np.max(n)), "unit": "m"}


def _within_limits(result, robot, path: str) -> None:
    """Refuse a compensated command beyond a joint's limits, naming the path's row."""
    outside = (result.q_command < robot.lower) | (result.q_command > robot.upper)
    if np.any(outside):
        i, j = (int(v) for v in np.argwhere(outside)[0])
        raise InputError(f"the compensated q{j + 1} = {result.q_command[i, j]:.5f} {robot.joints[j].unit} leaves "
                         "the joint limits",
                         source=path, row=i + 2, column=f"q{j + 1}")


def run(args: argparse.Namespace) -> int:
    from elastocal.compensation.files import read_path, write_compensated_csv, write_krl, write_rapid
    from elastocal.compensation.model import CompensationModel, NotConverged, refuse_unmodelled
    from elastocal.commands._outputs import note
    from elastocal.compensation.trajectory import compensate_path, predicted_residual
    from elastocal.formats.calibration import read_calibration
    from elastocal.commands._outputs import Outputs
    from elastocal.formats.robot_toml import load_robot

    outputs = Outputs(force=args.force, inputs=[(args.robot, "--robot"), (args.calibration, "--calibration"),
                                                (args.path, "--path")])
    outputs.add(args.out, "--out")
    if args.krl:
        outputs.add(args.krl, "--krl")
    if args.rapid:
        outputs.add(args.rapid, "--rapid")
    fixed = _parse_wrench(args.wrench) if args.wrench is not None else None
    robot = load_robot(args.robot)
    cal = read_calibration(args.calibration)
    unmodelled = refuse_unmodelled(cal, args.without, source=args.calibration)   # before anything is computed
    model = CompensationModel.from_calibration(robot, cal, source=args.calibration)
    if args.tool:
        if args.tool not in robot.marker_names:
            raise InputError(f"unknown marker {args.tool!r}; the robot has {', '.join(robot.marker_names)}",
                             source="--tool")
        model = model.with_tool(args.tool)
    if args.reference == "nominal" and model.nominal is None:
        raise InputError("the nominal reference needs a calibration with kinematic_errors", source="--reference")
    planned = read_path(args.path, robot)
    if args.wrench is not None and planned.wrench is not None:
        raise InputError("the path has wrench columns fx..mz; give the wrench there or with --wrench, not both",
                         source="--wrench")
    if args.wrench is None and planned.wrench is None:
        raise InputError("no process wrench: add fx..mz columns to the path or give --wrench "
                         "(0,0,0,0,0,0 for none)", source=args.path)
    wrench = planned.wrench if planned.wrench is not None else np.tile(fixed, (len(planned), 1))
    from elastocal.compensation.trajectory import default_reference

    reference = args.reference or default_reference(model)
    try:
        result = compensate_path(model, planned.q, wrench, form=KinematicForm(args.form), reference=reference)
        residual = predicted_residual(model, result)
    except NotConverged as exc:
        raise _not_converged(exc, planned, wrench, args) from None
    _within_limits(result, robot, args.path)
    with outputs:
        write_compensated_csv(outputs.temp(args.out), planned.t, result)
        # the program is named after the file the user asked for, not the temporary one
        if args.krl:
            write_krl(outputs.temp(args.krl), planned.t, result, name_from=args.krl)
        if args.rapid:
            write_rapid(outputs.temp(args.rapid), planned.t, result, name_from=args.rapid)
    for effect, params in unmodelled.items():
        note(args, f"note: compensate does not model {effect} ({', '.join(params) or 'no parameters'} in "
                   f"{args.calibration}): the compensated path leaves its deflection uncorrected")
    shaky = cal.undetermined()     # marked by identify: not a result (identify/evidence.py)
    if shaky:
        note(args, f"note: {', '.join(shaky)} in {args.calibration} not determined by the calibration's data "
                   f"(\"determined\": false): the compensation of {'these joints' if len(shaky) > 1 else 'this joint'} "
                   f"is not a result; recalibrate with loads that load {'them' if len(shaky) > 1 else 'it'}")
    obj = {"n": len(result), "form": result.form, "reference": result.reference, "out": args.out,
           "unmodelled": unmodelled,
           "deflection": _stats(result.tcp_deflection), "residual": _stats(residual),
           "dtheta_max": {f"q{j + 1}": float(v) for j, v in enumerate(np.max(np.abs(result.dtheta), axis=0))},
           "uses_gravity": model.uses_gravity, "uses_compensator": model.uses_compensator}
    if args.krl:
        obj["krl"] = args.krl
    if args.rapid:
        obj["rapid"] = args.rapid
    if args.validate:
        obj["validation"] = _validation(args, robot, cal, model, planned, wrench, reference)
    if args.json:
        print(json.dumps(obj))
        return 0
    _print_text(args, obj, result, robot, model)
    return 0


def _validation(args: argparse.Namespace, robot, cal, model, planned, wrench: np.ndarray, reference: str) -> dict:
    """--validate: the compensated path on the simulated cell made from the calibrated robot."""
    from elastocal.compensation.ik import PlannedPath
    from elastocal.compensation.validate import validate_on_sim
    from elastocal.sims.cell import CellTruth, SimCell

    if robot.compensator is not None and robot.compensator.kind != CompensatorKind.HYDROPNEUMATIC:
        raise InputError("--validate simulates the HH-150 cell (hydro-pneumatic compensator); this robot's "
                         "compensator is a spring", source="--validate")
    truth, holds = calibrated_truth(robot, cal, CellTruth.for_robot(robot))
    cell = SimCell(robot, truth)
    check = validate_on_sim(cell, model, PlannedPath(t=planned.t, q=planned.q), wrench, reference=reference)
    summary = check.summary()
    summary["truth"] = f"the calibrated robot of {args.calibration}: {', '.join(holds)}"
    return summary


def _print_text(args: argparse.Namespace, obj: dict, result, robot, model) -> None:
    """The text the command prints without --json, made from its --json object."""
    mm = 1e3
    print(f"{len(result)} points, {result.form} compensation, reference: {result.reference} pose")
    print(f"  predicted tool deflection before compensation: max {obj['deflection']['max'] * mm:.3f} mm, "
          f"rms {obj['deflection']['rms'] * mm:.3f} mm")
    print(f"  predicted after compensation:                  max {obj['residual']['max'] * mm:.4f} mm")
    print("  largest correction: " + ", ".join(
        f"{k} {v * 1e3:.4f} mm" if robot.joints[j].unit == "m" else f"{k} {math.degrees(v):.4f} deg"
        for j, (k, v) in enumerate(obj["dtheta_max"].items())))
    if not model.uses_gravity:
        print("  (the robot description has no link masses: gravity and compensator left out of the model)")
    print(f"wrote {args.out}" + (f", {args.krl}" if args.krl else "") + (f", {args.rapid}" if args.rapid else ""))
    if args.validate:
        v = obj["validation"]
        print(f"simulated cell as {v['truth']}; tool-point error along the path:")
        for key, label in (("uncompensated", "planned path"), ("first_order", "first-order"), ("exact", "exact")):
            print(f"  {label:<14} max {v[key]['max'] * mm:9.4f} mm   rms {v[key]['rms'] * mm:9.4f} mm")
