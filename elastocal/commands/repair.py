"""`elastocal repair LOG.mcap [--out COPY.mcap]`: a readable copy of a killed log, with a summary."""

from __future__ import annotations

import argparse
import json
import pathlib


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="an MCAP log a killed `elastocal calibrate` or `check` left")
    parser.add_argument("--out", help="the copy to write (default: LOG.repaired.mcap beside the log)")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.acquisition.logreader import read_log
    from elastocal.acquisition.repair import repair_log
    from elastocal.commands._outputs import Outputs

    log = pathlib.Path(args.log)
    out = pathlib.Path(args.out) if args.out else log.with_name(f"{log.stem}.repaired{log.suffix or '.mcap'}")
    outputs = Outputs(force=args.force, inputs=[(args.log, "the log")])
    outputs.add(out, "--out")
    with outputs:
        repaired = repair_log(log, outputs.temp(out))
    contents = read_log(out)
    events = contents.events
    last = next((e for e in reversed(events) if e["kind"] in ("procedure_end", "step_done", "step_start")), None)
    span_s = (events[-1]["t_ns"] - events[0]["t_ns"]) * 1e-9 if len(events) > 1 else 0.0
    summary = {
        "log": str(log), "out": str(out), "messages": repaired.messages, "was_complete": repaired.was_complete,
        "bytes_lost": repaired.bytes_lost, "drive_samples": sum(len(d.t_ns) for d in contents.drives),
        "events": len(events), "span_s": span_s, "completed_steps": list(contents.completed_steps),
        "incomplete_steps": list(contents.incomplete_steps),
        "ended": None if last is None or last["kind"] != "procedure_end" else last.get("status"),
    }
    if args.json:
        print(json.dumps(summary))
        return 0
    state = ("it was complete already" if repaired.was_complete else
             f"it ended without its summary ({repaired.bytes_lost} bytes of a cut record dropped)")
    print(f"wrote {out}: {repaired.messages} messages of {log} ({state})")
    print(f"  {summary['drive_samples']} drive samples, {len(events)} events over {span_s:.1f} s; "
          f"steps completed: {', '.join(contents.completed_steps) or 'none'}"
          + (f"; cut short in: {', '.join(contents.incomplete_steps)}" if contents.incomplete_steps else ""))
    print("  the procedure " + (f"ended {summary['ended']}" if summary["ended"] else
                                "was killed (no procedure_end); resume it with `elastocal calibrate --resume "
                                f"{log} --out NEW.mcap`"))
    return 0
