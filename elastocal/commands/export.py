"""`elastocal export LOG.mcap --out DIR`: the log as robot.toml and the CSV tables (cli.md)."""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="an MCAP log written by `elastocal calibrate`")
    parser.add_argument("--out", required=True, help="folder for robot.toml, static.csv, runs.csv "
                                                     "(and the recorded cell.toml and plan.toml)")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.acquisition.export import export_log

    result = export_log(args.log, args.out)
    if args.json:
        print(json.dumps({"files": list(result.files), "static_rows": result.static_rows,
                          "run_rows": result.run_rows, "complete": result.complete,
                          "truncated": result.truncated, "incomplete_steps": list(result.incomplete_steps)}))
        return 0
    for path in result.files:
        print(f"wrote {path}")
    print(f"{result.static_rows} static rows, {result.run_rows} run rows")
    if not result.complete:
        print(f"note: {args.log} ends without its MCAP summary (the recorder was killed or is still "
              f"writing); everything up to its last complete chunk was read", file=sys.stderr)
    if result.incomplete_steps:
        print(f"note: step(s) {', '.join(result.incomplete_steps)} did not finish and were left out",
              file=sys.stderr)
    return 0
