"""Online compensation on the simulated cell against the calibration's own validation error.

``python benchmarks/stream_acceptance.py [--seeds N] [--speed X] [--out FILE.json]``

For each seed: a calibration identified from a simulated static dataset (``elastocal sim
static --seed s``, ``identify``) and its validation error on another dataset (``validate``,
seed s + 1000: the calibrated model's deflection error, per component, times sqrt(3) for a
3-D error); then Yang's path (1.2 -> 1.8 m, 10 mm/s, 60 s, ``--speed`` times faster) with a
process force rising from 500 to 1500 N along it (after building up over the first second)
is streamed through the simulated EGM and RSI controllers with the wrench from the simulated
Net F/T and from the motor currents, and judged by the simulated cell's physics: the load
point's error against the unloaded plan (rms and max over the path, and after the first
second's engagement), next to the path run uncompensated and the offline program
compensated for the mean force (``elastocal compensate --wrench 0,0,1000``). Prints one
table per seed and the ratio stream / (2 x validation) over the seeds.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import pathlib
import tempfile

import numpy as np

from elastocal.acquisition.ui import AutoUI
from elastocal.cli import main as cli
from elastocal.commands.stream import simulated_stream_cell
from elastocal.compensation.ik import yang_path
from elastocal.errors import DeviceError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.guided_cell import GuidedCellSpec
from elastocal.stream.evaluate import ErrorStats, offline_commands, path_errors, stream_errors
from elastocal.stream.session import StreamOptions, run_online
from elastocal.stream.sources import ForceSourceKind

START = (0.0, 0.0, 500.0, 0.0, 0.0, 0.0)
END = (0.0, 0.0, 1500.0, 0.0, 0.0, 0.0)
ENGAGE_S = 1.0
#: runs the watchdog stopped (the loaded machine stalled the stream) are run again this many times
RETRIES = 2
RUNS = (("egm", ForceSourceKind.SENSOR), ("egm", ForceSourceKind.CURRENTS),
        ("rsi", ForceSourceKind.SENSOR), ("rsi", ForceSourceKind.CURRENTS))


def _json(argv: list[str]) -> dict:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        code = cli(argv)
    if code != 0:
        raise RuntimeError(f"elastocal {' '.join(argv)}: exit {code}")
    return json.loads(buf.getvalue())


def calibration(tmp: pathlib.Path, seed: int) -> tuple[pathlib.Path, float]:
    """cal.json from a simulated static dataset, and its 3-D validation error [m]."""
    fit, val = tmp / f"fit{seed}", tmp / f"val{seed}"
    _json(["sim", "static", "--seed", str(seed), "--out", str(fit), "--json"])
    _json(["sim", "static", "--seed", str(seed + 1000), "--out", str(val), "--json"])
    cal = tmp / f"cal{seed}.json"
    _json(["identify", "--robot", str(fit / "robot.toml"), "--static", str(fit / "static.csv"), "--out", str(cal),
           "--json"])
    v = _json(["validate", "--robot", str(fit / "robot.toml"), "--calibration", str(cal), "--static",
               str(val / "static.csv"), "--json"])
    return cal, float(v["deflection"]["calibrated"]["rms"]) * np.sqrt(3.0)


def _after(records, errors, every: int) -> ErrorStats:
    t = np.array([r.t_path_s for r in list(records)[::every]])
    return ErrorStats.of(errors[t >= ENGAGE_S])


def one_seed(tmp: pathlib.Path, seed: int, speed: float) -> dict:
    robot = bundled_robot()
    cal, validation = calibration(tmp, seed)
    path = yang_path(robot)
    csv = tmp / f"path{seed}.csv"
    lines = ["t," + ",".join(f"q{j}" for j in range(1, 7))]
    lines += [",".join(repr(float(v)) for v in (ti, *qi)) for ti, qi in zip(path.t, path.q)]
    csv.write_text("\n".join(lines) + "\n")
    duration = float(path.t[-1]) / speed
    spec = GuidedCellSpec(start_wrench=START, end_wrench=END, duration_s=duration, engage_s=ENGAGE_S, seed=seed)
    rows = {}
    outcome = None
    for kind, source in RUNS:
        stops = []
        for attempt in range(1 + RETRIES):
            try:
                outcome = run_online(simulated_stream_cell(kind), str(cal), str(csv),
                                     StreamOptions(out=tmp / f"{seed}-{kind}-{source.value}-{attempt}.mcap",
                                                   source=source, simulate=spec, time_scale=speed),
                                     AutoUI(quiet=True))
                break
            except DeviceError as exc:        # a stall of the loaded machine: the watchdog stopped it
                stops.append(f"{type(exc).__name__} after {len(exc.outcome.records)} cycles: {exc}")
        else:
            rows[f"{kind} + {source.value}"] = {"stopped": stops}
            continue
        recs = outcome.records
        every = max(1, len(recs) // 1500)
        err = stream_errors(outcome.sim.cell, outcome.sim.load, recs, every=every)
        rows[f"{kind} + {source.value}"] = {
            "status": outcome.status, "late": sum(r.late is not None for r in recs),
            "lost": sum(r.lost_before for r in recs), "cycles": len(recs), "stopped": stops,
            "all": ErrorStats.of(err).to_json(), "after_engagement": _after(recs, err, every).to_json()}
    sim, plan = outcome.sim, outcome.plan
    plain = path_errors(sim.cell, sim.load, plan.t, plan.q, plan.q)
    mean = 0.5 * (np.asarray(START) + np.asarray(END))
    offline = path_errors(sim.cell, sim.load, plan.t, plan.q, offline_commands(outcome.model, plan.q, mean))
    engaged = plan.t >= ENGAGE_S
    for name, err in (("uncompensated", plain), ("offline, mean force", offline)):
        rows[name] = {"all": ErrorStats.of(err).to_json(), "after_engagement": ErrorStats.of(err[engaged]).to_json()}
    return {"seed": seed, "validation_3d_rms": validation, "rows": rows}


def _print(result: dict) -> None:
    v = result["validation_3d_rms"]
    print(f"seed {result['seed']}: validation error (3-D rms) {v * 1e6:.1f} um, 2x = {2 * v * 1e6:.1f} um")
    print(f"  {'':<22} {'rms':>9} {'max':>9} {'rms>1s':>9} {'max>1s':>9}  [um]   late lost")
    for name, row in result["rows"].items():
        if "all" not in row:
            print(f"  {name:<22} stopped every time: {row['stopped'][-1]}")
            continue
        a, b = row["all"], row["after_engagement"]
        extra = f"   {row['late']:4d} {row['lost']:4d}" if "late" in row else ""
        if row.get("stopped"):
            extra += f"   (after {len(row['stopped'])} run(s) the watchdog stopped)"
        print(f"  {name:<22} {a['rms'] * 1e6:9.1f} {a['max'] * 1e6:9.1f} {b['rms'] * 1e6:9.1f} "
              f"{b['max'] * 1e6:9.1f}{extra}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--speed", type=float, default=1.0)
    parser.add_argument("--out", help="also write the results as JSON")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}; Yang's path at {args.speed:g}x its speed")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            results.append(one_seed(pathlib.Path(tmp), seed, args.speed))
            _print(results[-1])
    print("stream rms over the whole path / (2 x validation), over the seeds (median, max):")
    for name in results[0]["rows"]:
        if "+" not in name:
            continue
        r = np.array([res["rows"][name]["all"]["rms"] / (2 * res["validation_3d_rms"]) for res in results
                      if "all" in res["rows"][name]])
        stopped = sum(len(res["rows"][name].get("stopped", [])) for res in results)
        print(f"  {name:<18} {np.median(r):.3f}  {np.max(r):.3f}   ({len(r)} runs; {stopped} stopped by the "
              "watchdog and run again)")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
