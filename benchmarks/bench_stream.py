"""The stream's cycle: compute time per cycle against its budget, and the loop's jitter.

``python benchmarks/bench_stream.py [--cycles N] [--seconds S]``

1. *Compute*: what a cycle does between taking up the controller's message and sending the
   answer (locate the path time, the wrench from the source, the correction, its limits, the
   answer's encoding: EGM protobuf, RSI XML), ``--cycles`` times for each source, without
   sockets. p50/p99/max in microseconds, against the 4 ms cycle, the 0.5 ms target, and as a
   ratio to one forward kinematics (Pinocchio, ``benchmarks/fk_limit.py``) measured in the same
   run, so that figures from a loaded machine compare.
2. *Jitter*: the whole stream on the simulated EGM cell (controller and Net F/T in their own
   process, ``--seconds`` of Yang's path at its own 10 mm/s): cycles, late and lost ones, the
   period's deviation from 4 ms, message-to-answer times; with the machine's load average.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))

from fk_limit import fk_batches_s  # noqa: E402

from elastocal.compensation.ik import yang_path  # noqa: E402
from elastocal.compensation.model import CompensationModel  # noqa: E402
from elastocal.drivers.force import WrenchSample  # noqa: E402
from elastocal.drivers.guidance import ControllerState  # noqa: E402
from elastocal.formats.robot_toml import bundled_robot  # noqa: E402
from elastocal.sims.cell import CellTruth  # noqa: E402
from elastocal.stream.correction import Limits, limit, model_correction  # noqa: E402
from elastocal.stream.plan import build_plan  # noqa: E402
from elastocal.stream.sources import CurrentsSource, PathSource, SensorSource  # noqa: E402

BUDGET_US = 4000.0
TARGET_P99_US = 500.0


class _Sensor:
    """A sensor whose latest sample is always fresh (the cycle's own work is what is timed)."""

    def __init__(self) -> None:
        self.sample = WrenchSample(t_ns=0, sequence=1, wrench=np.array([1.0, 2.0, 900.0, 0.1, 0.2, 0.3]))

    def latest(self):
        return self.sample


def _encoders(n: int):
    from elastocal.drivers.egm import EgmGuidance
    from elastocal.drivers.rsi import RsiGuidance
    from elastocal.drivers.urls import parse_device_url

    egm = EgmGuidance(parse_device_url("egm://127.0.0.1:0"), n_joints=n)
    rsi = RsiGuidance(parse_device_url("rsi://127.0.0.1:0"), n_joints=n)
    rsi._reference_deg = np.zeros(n)
    return egm, rsi


def compute_times(cycles: int) -> dict[str, np.ndarray]:
    robot = bundled_robot()
    truth = CellTruth()
    model = CompensationModel(robot=robot, stiffness=truth.stiffness, compensator=truth.compensator)
    path = yang_path(robot)
    plan = build_plan(model, path.t, path.q)
    n = plan.n_joints
    limits = Limits()
    egm, rsi = _encoders(n)
    sources = {"sensor": SensorSource(_Sensor(), plan, max_age_s=1e9),
               "currents": CurrentsSource(plan, filter_s=0.1, cycle_s=0.004),
               "path": PathSource(plan, np.array([0.0, 0.0, 1500.0, 0.0, 0.0, 0.0]))}
    currents = plan.tau_unloaded[0] / plan.torque_constants
    out = {}
    for name, source in sources.items():
        for encoder in (egm, rsi):
            times = np.empty(cycles, dtype=np.int64)
            previous = np.zeros(n)
            for k in range(cycles):
                if k % 500 == 0:
                    # a stream sleeps between its cycles; a loop that never does is throttled by the kernel
                    # (real-time tasks get at most sched_rt_runtime_us of each second: a 50 ms stall)
                    time.sleep(0.005)
                t_path = (k * 0.004) % plan.duration_s
                state = ControllerState(t_ns=0, sequence=k, q=plan.q[0], currents_a=currents, controller_time_ms=4 * k)
                t0 = time.perf_counter_ns()
                i, w = plan.locate(t_path)
                q_plan = plan.at(plan.q, i, w)
                reading = source.read(state, i, w, 0)
                corr = limit(model_correction(plan, i, w, reading.wrench), previous, limits, 0.004)
                encoder._encode(q_plan + corr.sent, state)
                times[k] = time.perf_counter_ns() - t0
                previous = corr.sent
            out[f"{name}/{encoder.kind.value}"] = times
    egm.close()
    rsi.close()
    return out


def jitter(seconds: float) -> dict:
    from elastocal.acquisition.ui import AutoUI
    from elastocal.commands.stream import simulated_stream_cell
    from elastocal.sims.guided_cell import GuidedCellSpec
    from elastocal.stream.session import StreamOptions, run_online

    robot = bundled_robot()
    path = yang_path(robot)
    scale = path.t[-1] / seconds
    with tempfile.TemporaryDirectory() as tmp:
        csv = pathlib.Path(tmp) / "path.csv"
        lines = ["t," + ",".join(f"q{j}" for j in range(1, 7))]
        lines += [",".join(repr(float(v)) for v in (ti / scale, *qi)) for ti, qi in zip(path.t, path.q)]
        csv.write_text("\n".join(lines) + "\n")
        cal = pathlib.Path(tmp) / "cal.json"
        import json

        k = CellTruth().stiffness
        cal.write_text(json.dumps({"format": "elastocal.calibration/1", "robot": robot.name, "created": "",
                                   "model": ["joint_stiffness"], "torque": "current",
                                   "parameters": {f"k{j}": {"value": float(v), "unit": "N*m/rad"}
                                                  for j, v in enumerate(k, 1)},
                                   "residual": {}, "data": []}))
        spec = GuidedCellSpec(start_wrench=(0, 0, 500, 0, 0, 0), end_wrench=(0, 0, 1500, 0, 0, 0), duration_s=seconds)
        load_before = os.getloadavg()
        outcome = run_online(simulated_stream_cell("egm"), str(cal), str(csv),
                             StreamOptions(out=pathlib.Path(tmp) / "jitter.mcap", simulate=spec), AutoUI(quiet=True))
        load_after = os.getloadavg()
    recs = outcome.records
    period = np.array([r.period_ns for r in recs[1:]]) * 1e-3
    response = np.array([r.response_ns for r in recs]) * 1e-3
    return {"status": outcome.status, "cycles": len(recs), "late": sum(r.late is not None for r in recs),
            "lost": sum(r.lost_before for r in recs), "scheduling": outcome.scheduling,
            "period_dev_us": np.abs(period - 4000.0), "response_us": response,
            "load": (load_before[0], load_after[0])}


def _pct(v: np.ndarray) -> str:
    return f"p50 {np.percentile(v, 50):7.1f}  p99 {np.percentile(v, 99):7.1f}  max {np.max(v):8.1f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=20000)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--no-jitter", action="store_true")
    args = parser.parse_args()
    fk = fk_batches_s(bundled_robot())
    fk_us = float(np.median(fk)) * 1e6
    from elastocal.stream.realtime import realtime

    with realtime() as scheduling:          # as the stream runs its cycle
        times = compute_times(args.cycles)
    fk_after_us = float(np.median(fk_batches_s(bundled_robot()))) * 1e6
    fk_us = 0.5 * (fk_us + fk_after_us)
    print(f"load average {os.getloadavg()[0]:.2f}; one FK (median of the run) {fk_us:.2f} us, fastest batch "
          f"{min(fk) * 1e6:.2f} us")
    print(f"compute per cycle [us] ({scheduling}; budget {BUDGET_US:.0f}, target p99 < {TARGET_P99_US:.0f}):")
    for name, t in times.items():
        us = t * 1e-3
        p99 = np.percentile(us, 99)
        print(f"  {name:<15} {_pct(us)}   p99/FK {p99 / fk_us:6.1f}   p99/target {p99 / TARGET_P99_US:5.3f}   "
              f"p99/budget {p99 / BUDGET_US:5.3f}")
    if not args.no_jitter:
        j = jitter(args.seconds)
        print(f"stream on the simulated EGM cell, {args.seconds:g} s at 250 Hz ({j['scheduling']}; load average "
              f"{j['load'][0]:.2f} -> {j['load'][1]:.2f}): {j['status']}, {j['cycles']} cycles, late {j['late']}, "
              f"lost {j['lost']}")
        print(f"  |period - 4 ms| [us]     {_pct(j['period_dev_us'])}")
        print(f"  message to answer [us]   {_pct(j['response_us'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
