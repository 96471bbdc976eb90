"""`elastocal calibrate`: the guided calibration procedure (docs/cli.md, docs/calibrate.md)."""

from __future__ import annotations

import argparse
import json
import sys

from elastocal.errors import DeviceError, InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cell", required=True, help="cell.toml: the devices of the cell")
    parser.add_argument("--plan", help="plan.toml: poses, loads, markers, repeats, speeds (docs/plan-format.md); "
                                       "default: the plan of the --resume log, else `plan` in [cell] of cell.toml")
    parser.add_argument("--out", required=True, help="the MCAP log to write")
    parser.add_argument("--procedure", help="comma-separated procedures to run: static, friction, sweep, check "
                                            "(default: the plan's `procedures`)")
    parser.add_argument("--resume", metavar="LOG", help="an interrupted log of the same plan: copy its "
                                                        "completed steps into --out and run the rest")
    parser.add_argument("--sim", action="store_true",
                        help="serve the cell's simulated devices in this process (from [sim] of cell.toml)")
    parser.add_argument("--yes", action="store_true",
                        help="answer every prompt automatically (simulated devices only)")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def resolve_plan(plan_arg: str | None, config, resume: str | None):
    """The plan to run: ``--plan``, else the one recorded in the ``--resume``
    log, else the cell's (``[cell] plan``)."""
    from elastocal.acquisition.logreader import read_log
    from elastocal.formats.plan import load_plan, parse_plan

    if plan_arg:
        return load_plan(plan_arg)
    if resume:
        doc = read_log(resume).plan
        if doc is None:
            raise InputError("the log holds no plan; give --plan", source=resume)
        return parse_plan(doc.text, source=doc.path or f"{resume} (plan)")
    if config.plan is not None:
        with config.key_errors("plan", config.plan):
            return load_plan(config.plan)
    raise InputError("no plan: give --plan plan.toml or name one in [cell] of the cell config "
                     "(plan = \"plan.toml\"); `elastocal plan` makes one", source="--plan")


def run(args: argparse.Namespace) -> int:
    from elastocal.formats.plan import PROCEDURES
    from elastocal.acquisition.procedures import run_calibration
    from elastocal.acquisition.ui import AutoUI, TerminalUI
    from elastocal.drivers.config import load_cell_config

    from elastocal.commands._cell import check_answers, procedure_cell
    from elastocal.commands._outputs import Outputs

    # the folder and the name; an existing log is refused by the procedure unless --force
    Outputs(force=True, inputs=[(args.cell, "--cell"), (args.plan, "--plan"), (args.resume, "--resume")]
            ).add(args.out, "--out")
    config = load_cell_config(args.cell)
    plan = resolve_plan(args.plan, config, args.resume)
    procedures = None
    if args.procedure:
        procedures = tuple(p.strip() for p in args.procedure.split(",") if p.strip())
        for p in procedures:
            if p not in PROCEDURES:
                raise InputError(f"unknown procedure {p!r}; one of {', '.join(PROCEDURES)}", source="--procedure")
    check_answers(config, sim=args.sim, yes=args.yes)
    ui = AutoUI(sys.stderr, quiet=args.json, answered_by="--yes") if args.yes else TerminalUI(sys.stderr)
    try:
        with procedure_cell(config, sim=args.sim) as (cell, world):
            outcome = run_calibration(cell, plan, args.out, yes=args.yes, ui=ui, procedures=procedures,
                                      resume_from=args.resume, overwrite=args.force, world=world)
    except DeviceError as exc:
        outcome = getattr(exc, "outcome", None)
        if outcome is None:       # no log was started (a device could not be opened)
            raise
    if args.json:
        print(json.dumps({"log": outcome.path, "status": outcome.status, "steps": outcome.steps_total,
                          "steps_done": outcome.steps_done, "steps_resumed": outcome.steps_resumed,
                          "duration_s": outcome.duration_s}))
    else:
        print(f"log: {outcome.path} ({outcome.steps_done}/{outcome.steps_total} steps, {outcome.status})")
    if outcome.status != "completed":
        print(f"elastocal calibrate: {outcome.message}; resume with --resume {outcome.path} and a new --out",
              file=sys.stderr)
        return 1
    return 0
