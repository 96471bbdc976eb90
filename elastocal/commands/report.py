"""`elastocal report … --out report.html`: a self-contained page showing where the model fails."""

from __future__ import annotations

import argparse
import json

from elastocal.commands._inputs import (
    add_input_arguments,
    add_outlier_argument,
    add_tracker_arguments,
    input_paths,
    load_inputs,
    table_model,
    tracker_prior,
)
from elastocal.commands._outputs import Outputs
from elastocal.commands.diagnose import diagnose_inputs, identify_command
from elastocal.errors import InputError
from elastocal.model.effects import get_effect, parse_model
from elastocal.model.kinds import KinematicForm, TorqueSource


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    add_outlier_argument(parser)
    add_tracker_arguments(parser)
    parser.add_argument("--out", required=True, help="HTML file to write")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    parser.add_argument("--add", help="effect to show beside the model (default: the diagnosis' verdict)")


def run(args: argparse.Namespace) -> int:
    from elastocal.progress import long_work

    with long_work("report", 1, quiet=args.json) as progress:     # each effect's fit, on a large table
        return _run(args, progress)


def _run(args: argparse.Namespace, progress) -> int:
    outputs = Outputs(force=args.force, inputs=input_paths(args))
    out = outputs.add(args.out, "--out")
    model = parse_model(args.model)
    if args.add is not None:
        try:
            get_effect(args.add)
        except InputError as exc:
            raise InputError(exc.detail, source="--add") from None
        if args.add in model:
            raise InputError(f"{args.add} is already in the model", source="--add")
    inputs = load_inputs(args)
    model = table_model(args, inputs, model)
    static, runs = diagnose_inputs(inputs, model, TorqueSource(args.torque), KinematicForm(args.form),
                                   exclude_outliers=args.exclude_outliers, prior=tracker_prior(args, inputs),
                                   progress=progress)
    progress(0, "drawing the figures", total=1)
    from elastocal.diagnose.absolute_only import AbsoluteOnlyDiagnosis
    from elastocal.report.html import render_report

    if isinstance(static, AbsoluteOnlyDiagnosis):          # a table without loads: the absolute section alone
        from elastocal.report.absolute import absolute_only_page

        if args.add is not None:
            raise InputError("a table without loads shows its candidates in the absolute section; no --add",
                             source="--add")
        names = ([args.robot] if args.robot else []) + [str(f) for f in inputs.files]
        page = absolute_only_page(inputs.robot, static, names)
        progress.done()
        with outputs:
            outputs.temp(out).write_text(page, encoding="utf-8")
        if args.json:
            print(json.dumps({"out": str(out), "verdict": static.verdict, "bytes": len(page.encode("utf-8"))}))
        else:
            print(f"report written to {out} (verdict: {static.verdict or 'none'})")
        return 0
    add = args.add
    if add is not None and static is not None and add not in {c.effect for c in static.candidates}:
        reason = next((n.reason for n in static.not_testable if n.effect == add), "not a candidate")
        raise InputError(f"{add} cannot be shown: {reason}", source="--add")
    effect = add if add is not None else (static.verdict if static is not None else None)
    command = identify_command(args, (*model, effect)) if effect is not None else None
    names = ([args.robot] if args.robot else []) + [str(f) for f in inputs.files]
    from elastocal.commands.diagnose import open_effects, plan_command

    left = open_effects(static) if static is not None else ()
    page = render_report(inputs.robot, static, runs, add=add, inputs=names,
                         command=command, next_experiment=(left, plan_command(args, left)) if left else None)
    progress.done()
    with outputs:
        outputs.temp(out).write_text(page, encoding="utf-8")
    verdict = static.verdict if static is not None else (runs.verdict if runs is not None else None)
    if args.json:
        print(json.dumps({"out": str(out), "verdict": verdict, "bytes": len(page.encode("utf-8"))}))
    else:
        print(f"report written to {out} (verdict: {verdict or 'no missing effect found'})")
    return 0
