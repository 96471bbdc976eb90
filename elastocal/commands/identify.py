"""`elastocal identify`: fit the model to tables or a log (docs/cli.md)."""

from __future__ import annotations

import argparse
import json

from elastocal.commands._inputs import (
    add_input_arguments,
    add_outlier_argument,
    add_tracker_arguments,
    input_paths,
    load_inputs,
    prior_line,
    table_model,
    tracker_prior,
)
from elastocal.commands._outputs import Outputs
from elastocal.commands._format import format_fit
from elastocal.errors import InputError
from elastocal.formats.calibration import write_calibration
from elastocal.model.effects import parse_model
from elastocal.diagnose.pipeline import Identification, identify_data
from elastocal.model.kinds import KinematicForm, TorqueSource


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    add_outlier_argument(parser)
    parser.add_argument("--out", help="write the calibration JSON (docs/formats.md §4) here")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    add_tracker_arguments(parser)


def identify_inputs(inputs, model: tuple[str, ...], torque: TorqueSource, form: KinematicForm, *,
                    exclude_outliers: bool = False, prior=None, progress=None) -> Identification:
    """What identify finds in the inputs (:func:`elastocal.diagnose.pipeline.identify_data`);
    ``prior``: the cell's tracker position (commands/_inputs.py's tracker_prior); ``progress``
    told of each fit (elastocal/progress.py)."""
    return identify_data(inputs.robot, inputs.static, inputs.runs, model, torque, form,
                         exclude_outliers=exclude_outliers,
                         tracker_prior=None if prior is None else prior.base_p_tracker,
                         prior_source=None if prior is None else prior.source, progress=progress)


def run(args: argparse.Namespace) -> int:
    from elastocal.progress import long_work

    with long_work("identify", 1, quiet=args.json) as progress:     # reading a long log, then each fit
        progress(0, "reading the inputs")
        return _run(args, progress)


def _run(args: argparse.Namespace, progress) -> int:
    outputs = Outputs(force=args.force, inputs=[*input_paths(args), (args.cell, "--cell")])
    if args.out:
        outputs.add(args.out, "--out")
    model = parse_model(args.model)
    inputs = load_inputs(args)
    if inputs.static is None and inputs.runs is None:
        raise InputError("the log holds neither a static experiment nor runs", source=args.log or "--static")
    model = table_model(args, inputs, model)
    prior = tracker_prior(args, inputs)
    result = identify_inputs(inputs, model, TorqueSource(args.torque), KinematicForm(args.form),
                             exclude_outliers=args.exclude_outliers, prior=prior, progress=progress)
    progress.done()
    obj = result.to_json()
    if args.out:
        calibration = result.calibration(inputs.robot.name, inputs.files, robot_description=inputs.robot.to_toml())
        bad = calibration.undetermined()
        if bad:   # a stiffness the data do not determine is written marked, never as a finding
            args.notes.append(f"elastocal identify: note: {', '.join(bad)} not determined by these data, marked "
                              f"\"determined\": false in {args.out}: not a calibration of "
                              f"{'these joints' if len(bad) > 1 else 'this joint'} (add poses and loads that load "
                              f"{'them' if len(bad) > 1 else 'it'}: elastocal plan)")
        with outputs:
            write_calibration(outputs.temp(args.out), calibration)
    if args.json:
        print(json.dumps(obj))
    else:
        how = (f"({obj['torque']}-based, {obj['form']} form)" if "form" in obj
               else f"(run data: joint-{inputs.robot.sweep_joint} sweeps and UV/VU runs)")
        print(format_fit(obj, title=f"{inputs.robot.name}: {', '.join(obj['model'])} {how}"))
        line = prior_line(prior, obj.get("registration"))
        if line:
            print(line)
        if args.out:
            print(f"calibration written to {args.out}")
    return 0
