"""`elastocal calibrate`: the guided calibration procedure (cli.md, docs/calibrate.md)."""

from __future__ import annotations

import argparse
import json
import sys

from elastocal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cell", required=True, help="cell.toml: the devices of the cell")
    parser.add_argument("--plan", required=True, help="plan.toml: poses, loads, markers, repeats, speeds "
                                                      "(docs/plan-format.md)")
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


def run(args: argparse.Namespace) -> int:
    from elastocal.acquisition.plan import PROCEDURES, load_plan
    from elastocal.acquisition.procedures import run_calibration
    from elastocal.acquisition.ui import AutoUI, TerminalUI
    from elastocal.drivers.config import load_cell_config

    config = load_cell_config(args.cell)
    plan = load_plan(args.plan)
    procedures = None
    if args.procedure:
        procedures = tuple(p.strip() for p in args.procedure.split(",") if p.strip())
        for p in procedures:
            if p not in PROCEDURES:
                raise InputError(f"unknown procedure {p!r}; one of {', '.join(PROCEDURES)}", source="--procedure")
    if args.yes and not args.sim:
        raise InputError("--yes answers the prompts of simulated devices only; add --sim, or let a person "
                         "answer", source="--yes")
    ui = AutoUI(sys.stderr, quiet=args.json) if args.yes else TerminalUI(sys.stderr)
    outcome = run_calibration(config, plan, args.out, yes=args.yes, ui=ui, procedures=procedures,
                              resume_from=args.resume, overwrite=args.force, simulate=args.sim)
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
