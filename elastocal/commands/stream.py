"""`elastocal stream`: online compensation through the controller's guidance channel (docs/stream.md)."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from elastocal.errors import InputError

#: the simulated process force when --sim-wrench is not given: Yang's 1500 N pushing the tool up,
#: rising from a third of it (500 -> 1500 N along the path)
DEFAULT_SIM_WRENCH = "0,0,500:0,0,1500"
#: at most this many cycles are judged against the simulated cell's truth (evenly spread)
TRUTH_POINTS = 400
#: the library's arguments as this command's flags (errors name the flag)
ARGUMENT_FLAGS = {"max_rad": "--max-correction-deg", "max_rate_rad_s": "--max-rate-deg-s",
                  "current_filter_s": "--current-filter-s", "wrench": "--wrench", "source": "--source",
                  "time_scale": "--sim-speed", "path": "--path", "sim_realtime": "--sim-realtime"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cell", help="cell.toml with a [guidance] table (and [force_sensor]); with --sim it may be "
                                       "left out: the simulated HH-150 with --sim-guidance and a Net F/T")
    parser.add_argument("--calibration", required=True, help="calibration JSON (docs/formats.md §4)")
    parser.add_argument("--path", required=True, help="planned path CSV: t,q1..qn and optionally fx..mz")
    parser.add_argument("--out", required=True, help="the MCAP log to write")
    parser.add_argument("--without", metavar="EFFECTS",
                        help="comma-separated effects of the calibration to leave out knowingly (as compensate: a "
                             "calibration holding static effects compensation does not model is refused)")
    parser.add_argument("--source", choices=("sensor", "currents", "path"),
                        help="where the process wrench comes from (default: the cell's [force_sensor], else the "
                             "path's fx..mz or --wrench)")
    parser.add_argument("--wrench", help="constant process wrench fx,fy,fz[,mx,my,mz] on the load point [N, N*m, base "
                                         "axes] (the path source)")
    parser.add_argument("--current-filter-s", type=float, default=0.1,
                        help="time constant of the low-pass on the wrench from currents [s] (default 0.1)")
    parser.add_argument("--max-correction-deg", type=float, help="per-joint limit of the correction [deg] "
                                                                 "(default: [guidance] of the cell, else 0.2)")
    parser.add_argument("--max-rate-deg-s", type=float, help="per-joint limit of its rate of change [deg/s] "
                                                             "(default: [guidance] of the cell, else 0.5)")
    parser.add_argument("--sim", action="store_true",
                        help="serve a simulated controller of the [guidance] kind (and a simulated Net F/T) in this "
                             "process, on 127.0.0.1")
    parser.add_argument("--sim-realtime", action="store_true",
                        help="with --sim: run the simulated controller on this computer's wall clock, so that a busy "
                             "computer makes late cycles as with a real robot (default: in lockstep on simulated "
                             "time: each cycle waits for the stream's answer, so a rehearsal does not fault "
                             "because the computer is busy; late cycles come only from injected faults)")
    parser.add_argument("--sim-guidance", choices=("egm", "rsi"), default="egm",
                        help="with --sim and no --cell: the simulated controller's channel (default egm)")
    parser.add_argument("--sim-speed", type=float, default=1.0,
                        help="with --sim: run the path this many times faster than its t column (a rehearsal: "
                             "the statics do not depend on the speed; default 1)")
    parser.add_argument("--sim-wrench", default=DEFAULT_SIM_WRENCH, metavar="START:END",
                        help="with --sim: the true process wrench at the path's start and end, fx,fy,fz[,mx,my,mz] "
                             f"each, changing linearly along the path (default {DEFAULT_SIM_WRENCH})")
    parser.add_argument("--sim-engage-s", type=float, default=1.0,
                        help="with --sim: the process force builds up from zero over this time as the tool enters "
                             "the workpiece [s] (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="with --sim: the random seed (default 0)")
    parser.add_argument("--yes", action="store_true", help="answer the prompt automatically (with --sim only)")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _wrench(text: str, source: str) -> np.ndarray:
    from elastocal.commands._flags import parse_wrench

    return np.array(parse_wrench(text, source))


def simulated_stream_cell(kind: str):
    """The simulated HH-150 with a ``kind`` guidance channel and a Net F/T (``--sim`` without ``--cell``)."""
    from elastocal.drivers.config import CellConfig
    from elastocal.drivers.guidance_config import ForceSensorConfig, GuidanceConfig
    from elastocal.drivers.urls import parse_device_url

    return CellConfig(name="simulated stream cell", robot="hh150", drives=(),
                      guidance=GuidanceConfig(url=parse_device_url(f"{kind}://127.0.0.1:0")),
                      force_sensor=ForceSensorConfig(url=parse_device_url("netft://127.0.0.1:0")),
                      source="the simulated stream cell")


def _stats_us(values_ns: np.ndarray) -> dict:
    if values_ns.size == 0:
        return {"p50": None, "p99": None, "max": None, "unit": "us"}
    v = values_ns * 1e-3
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "max": float(np.max(v)),
            "unit": "us"}


def _truth(outcome, sim_wrench) -> dict:
    from elastocal.stream.evaluate import ErrorStats, offline_commands, path_errors, stream_errors

    sim, plan = outcome.sim, outcome.plan
    every = max(1, len(outcome.records) // TRUTH_POINTS)
    streamed = ErrorStats.of(stream_errors(sim.cell, sim.load, outcome.records, every=every))
    t = plan.t
    plain = ErrorStats.of(path_errors(sim.cell, sim.load, t, plan.q, plan.q))
    mean = 0.5 * (sim_wrench[0] + sim_wrench[1])
    offline = ErrorStats.of(path_errors(sim.cell, sim.load, t, plan.q, offline_commands(outcome.model, plan.q, mean)))
    return {"uncompensated": plain.to_json(), "offline_mean_wrench": offline.to_json(),
            "stream": streamed.to_json(), "mean_wrench": mean.tolist()}


def run(args: argparse.Namespace) -> int:
    from elastocal.acquisition.ui import AutoUI, TerminalUI
    from elastocal.commands._outputs import Outputs
    from elastocal.drivers.config import load_cell_config
    from elastocal.stream.correction import Limits
    from elastocal.stream.loop import StreamSettings
    from elastocal.stream.session import StreamOptions, run_online
    from elastocal.stream.sources import ForceSourceKind

    Outputs(force=True, inputs=[(args.cell, "--cell"), (args.calibration, "--calibration"), (args.path, "--path")]
            ).add(args.out, "--out")
    if args.cell is None and not args.sim:
        raise InputError("give the cell config (or --sim for a simulated cell)", source="--cell")
    if not (args.sim_speed > 0 and np.isfinite(args.sim_speed)):
        raise InputError(f"must be a positive number, got {args.sim_speed!r}", source="--sim-speed")
    if args.sim_speed != 1.0 and not args.sim:
        raise InputError("a real robot runs the path at its own speed; --sim-speed is for a simulated cell",
                         source="--sim-speed")
    if pathlib.Path(args.out).exists() and not args.force:
        raise InputError("already exists; choose another --out, or --force to overwrite it", source=args.out)
    if args.sim_realtime and not args.sim:
        raise InputError("a real controller runs on its own clock; --sim-realtime is for a simulated cell",
                         source="--sim-realtime")
    if args.yes and not args.sim:
        raise InputError("--yes answers the prompt of a simulated cell only; add --sim, or let a person answer",
                         source="--yes")
    from elastocal.compensation.model import refuse_unmodelled
    from elastocal.formats.calibration import read_calibration

    refuse_unmodelled(read_calibration(args.calibration), args.without, source=args.calibration)
    wrench = _wrench(args.wrench, "--wrench") if args.wrench else None
    sim_wrench = None
    spec = None
    config = load_cell_config(args.cell) if args.cell else simulated_stream_cell(args.sim_guidance)
    if args.sim:
        from elastocal.compensation.files import read_path
        from elastocal.sims.guided_cell import GuidedCellSpec

        parts = args.sim_wrench.split(":")
        if len(parts) != 2:
            raise InputError("expected START:END, two wrenches fx,fy,fz[,mx,my,mz]", source="--sim-wrench")
        sim_wrench = (_wrench(parts[0], "--sim-wrench"), _wrench(parts[1], "--sim-wrench"))
        duration = float(read_path(args.path, config.load_robot()).t[-1]) / args.sim_speed
        spec = GuidedCellSpec(start_wrench=tuple(sim_wrench[0]), end_wrench=tuple(sim_wrench[1]),
                              duration_s=max(duration, 1e-3), engage_s=args.sim_engage_s, seed=args.seed)
    for flag, value in (("--max-correction-deg", args.max_correction_deg), ("--max-rate-deg-s", args.max_rate_deg_s),
                        ("--current-filter-s", args.current_filter_s)):
        allowed = value is None or (np.isfinite(value) and (value > 0 or (value == 0 and flag == "--current-filter-s")))
        if not allowed:
            raise InputError(f"must be a positive number, got {value!r}", source=flag)
    limits = Limits()
    if args.max_correction_deg is not None or args.max_rate_deg_s is not None:
        g = config.guidance
        limits = Limits(max_rad=float(np.radians(args.max_correction_deg or (g and g.max_correction_deg) or
                                                 np.degrees(Limits().max_rad))),
                        max_rate_rad_s=float(np.radians(args.max_rate_deg_s or (g and g.max_rate_deg_s) or
                                                        np.degrees(Limits().max_rate_rad_s))))
    options = StreamOptions(out=pathlib.Path(args.out), source=ForceSourceKind(args.source) if args.source else None,
                            wrench=wrench, settings=StreamSettings(limits=limits),
                            current_filter_s=args.current_filter_s, overwrite=args.force, simulate=spec,
                            time_scale=args.sim_speed, sim_realtime=args.sim_realtime)
    ui = AutoUI(sys.stderr, quiet=args.json, answered_by="--yes") if args.yes else TerminalUI(sys.stderr)
    try:
        outcome = run_online(config, args.calibration, args.path, options, ui)
    finally:
        ui.close()
    obj = _summary(outcome)
    if spec is not None and outcome.status == "completed":
        obj["truth"] = _truth(outcome, sim_wrench)
    if args.json:
        print(json.dumps(obj))
    else:
        _print(obj)
    return 0 if outcome.status == "completed" else 1


def _summary(outcome) -> dict:
    recs = outcome.records
    period = np.array([r.period_ns for r in recs[1:]], dtype=np.int64)
    cycle_s = outcome.result.cycle_s if outcome.result is not None else None
    jitter = None
    if period.size and cycle_s:
        dev = np.abs(period * 1e-9 - cycle_s) * 1e6
        jitter = {"p50": float(np.percentile(dev, 50)), "p99": float(np.percentile(dev, 99)),
                  "max": float(np.max(dev)), "unit": "us"}
    return {"log": outcome.log, "status": outcome.status, "message": outcome.message,
            "guidance": outcome.guidance.value, "source": outcome.source.value, "cycles": len(recs),
            "late_cycles": sum(r.late is not None for r in recs),
            "lost_messages": sum(r.lost_before for r in recs),
            "limited_cycles": sum(r.limited for r in recs),
            "compute": _stats_us(np.array([r.compute_ns for r in recs], dtype=np.int64)),
            "response": _stats_us(np.array([r.response_ns for r in recs], dtype=np.int64)),
            "period_jitter": jitter, "cycle_s": cycle_s, "scheduling": outcome.scheduling}


def _print(obj: dict) -> None:
    print(f"log: {obj['log']} ({obj['status']}): {obj['cycles']} cycles of {obj['guidance']}, wrench from "
          f"{obj['source']}; late {obj['late_cycles']}, lost {obj['lost_messages']}, at the limit "
          f"{obj['limited_cycles']} ({obj['scheduling']})")
    c, r = obj["compute"], obj["response"]
    if c["p50"] is not None:
        print(f"  compute per cycle: p50 {c['p50']:.0f} us, p99 {c['p99']:.0f} us, max {c['max']:.0f} us; "
              f"message to answer: p99 {r['p99']:.0f} us, max {r['max']:.0f} us")
    if obj["period_jitter"]:
        j = obj["period_jitter"]
        print(f"  period jitter (|period - {obj['cycle_s'] * 1e3:g} ms|): p50 {j['p50']:.0f} us, "
              f"p99 {j['p99']:.0f} us, "
              f"max {j['max']:.0f} us")
    if "truth" in obj:
        t = obj["truth"]
        print("simulated cell, load-point error along the path (against the unloaded plan):")
        for key, label in (("uncompensated", "uncompensated"), ("offline_mean_wrench", "offline, mean wrench"),
                           ("stream", "stream")):
            print(f"  {label:<22} rms {t[key]['rms'] * 1e6:9.1f} um   max {t[key]['max'] * 1e6:9.1f} um")
