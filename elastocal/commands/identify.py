"""`elastocal identify`: fit the model to tables or a log (cli.md)."""

from __future__ import annotations

import argparse
import json

from elastocal.commands._inputs import add_input_arguments, add_outlier_argument, input_paths, load_inputs
from elastocal.commands._outputs import Outputs
from elastocal.commands._format import format_fit
from elastocal.errors import InputError
from elastocal.identify.calibration import calibration_from_fit, write_calibration
from elastocal.identify.effects import parse_model


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    add_outlier_argument(parser)
    parser.add_argument("--out", help="write the calibration JSON (formats.md §4) here")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")


def identify_inputs(inputs, model: tuple[str, ...], torque: str, form: str, *,
                    exclude_outliers: bool = False) -> tuple[dict, object | None]:
    """The identify --json object for the inputs, and the static fit if any.
    ``outliers`` lists the static readings far off their repeats (identify/outliers.py);
    with ``exclude_outliers`` the fit leaves them out."""
    from elastocal.identify.outliers import without_outliers
    from elastocal.identify.static import identify_static

    if inputs.static is None:
        from elastocal.identify import runs as run_ident  # run data: compensator, friction

        result = run_ident.identify_runs(inputs.robot, inputs.runs, model=model)
        return result.to_json(), None
    from elastocal.identify.runs import RUN_EFFECTS

    run_model = tuple(m for m in model if m in RUN_EFFECTS)
    static_model = tuple(m for m in model if m not in RUN_EFFECTS or inputs.runs is None)
    table, excluded = without_outliers(inputs.static) if exclude_outliers else (inputs.static, ())
    fit = identify_static(inputs.robot, table, model=static_model, torque=torque, form=form)
    obj = fit.to_json()
    obj["model"] = list(model)
    obj["outliers"] = [o.to_json() for o in (*excluded, *fit.dataset.outliers)]
    if inputs.runs is not None:
        from elastocal.identify import runs as run_ident

        if run_model:
            result = run_ident.identify_runs(inputs.robot, inputs.runs, model=("joint_stiffness", *run_model))
            rj = result.to_json()
            obj["parameters"].update(rj["parameters"])
            obj["torque_residual"] = rj["residual"]
    return obj, fit


def run(args: argparse.Namespace) -> int:
    outputs = Outputs(force=args.force, inputs=input_paths(args))
    if args.out:
        outputs.add(args.out, "--out")
    model = parse_model(args.model)
    inputs = load_inputs(args)
    if inputs.static is None and inputs.runs is None:
        raise InputError("the log holds neither a static experiment nor runs", source=args.log or "--static")
    obj, fit = identify_inputs(inputs, model, args.torque, args.form, exclude_outliers=args.exclude_outliers)
    if args.out:
        with outputs:
            write_calibration(outputs.temp(args.out), calibration_from_fit(inputs.robot.name, obj, inputs.files))
    if args.json:
        print(json.dumps(obj))
    else:
        how = (f"({obj['torque']}-based, {obj['form']} form)" if "form" in obj
               else "(run data: joint-2 sweeps and UV/VU runs)")
        print(format_fit(obj, title=f"{inputs.robot.name}: {', '.join(obj['model'])} {how}"))
        if args.out:
            print(f"calibration written to {args.out}")
    return 0
