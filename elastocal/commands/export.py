"""`elastocal export LOG.mcap --out DIR`: the log as robot.toml and the CSV tables (docs/cli.md)."""

from __future__ import annotations

import argparse
import json


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="an MCAP log written by `elastocal calibrate`")
    parser.add_argument("--out", required=True, help="folder for robot.toml, static.csv, runs.csv "
                                                     "(and the recorded cell.toml and plan.toml)")
    parser.add_argument("--force", action="store_true",
                        help="overwrite the files of an earlier export in --out, and remove those this log "
                             "does not have (e.g. a static.csv when the log holds runs only)")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.acquisition.export import export_files, write_export_file
    from elastocal.acquisition.logreader import read_log
    from elastocal.commands._outputs import Outputs, check_folder, log_note, note

    out = check_folder(args.out, "--out")
    contents = read_log(args.log)
    writes = export_files(contents)
    outputs = Outputs(force=args.force, inputs=[(args.log, "the log")])
    for name, what in writes.items():
        if what is not None:
            outputs.add(out / name, "--out", in_folder=True)
        else:
            outputs.stale(out / name, "--out", f"not in {args.log}, so this export would leave it from another log")
    outputs.make_folder(out)
    files = []
    with outputs:
        for name, what in writes.items():
            if what is None:
                continue
            write_export_file(outputs.temp(out / name), what)
            files.append(str(out / name))
    removed = [str(p) for p in outputs.remove]
    static_rows = 0 if writes["static.csv"] is None else len(writes["static.csv"])
    run_rows = 0 if writes["runs.csv"] is None else len(writes["runs.csv"])
    if args.json:
        print(json.dumps({"files": files, "static_rows": static_rows, "run_rows": run_rows,
                          "complete": contents.complete, "truncated": contents.truncated,
                          "incomplete_steps": list(contents.incomplete_steps), "removed": removed}))
    else:
        for path in files:
            print(f"wrote {path}")
        for path in removed:
            print(f"removed {path} (not in this log)")
        print(f"{static_rows} static rows, {run_rows} run rows")
    text = log_note(args.log, contents)
    if text:
        note(args, text)
    if contents.incomplete_steps:
        note(args, f"note: step(s) {', '.join(contents.incomplete_steps)} did not finish and were left out")
    return 0
