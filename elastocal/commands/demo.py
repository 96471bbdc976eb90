"""`elastocal demo`: the whole chain on the embedded simulated cell.

Builds the bundled HH-150, runs a static before/after-load experiment on the
simulated cell, identifies the joint stiffness from motor currents and from
forces, and prints identified against true values and the residual against
the noise floor.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile
import time

import numpy as np

from elastocal.commands._format import format_parameters, verdict_line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=1, help="random seed of the simulated cell (default 1)")
    parser.add_argument("--out", help="directory for the files the demo writes (default: a temporary one)")
    parser.add_argument("--hidden", default="link_compliance",
                        help="effect the simulated cell hides for the diagnosis step (default link_compliance)")


class _Say:
    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.step = 0

    def __call__(self, text: str) -> None:
        self.step += 1
        print(f"\n[{self.step}] {text}  (t = {time.perf_counter() - self.t0:.1f} s)")


def run(args: argparse.Namespace) -> int:
    from elastocal.identify.calibration import calibration_from_fit, write_calibration
    from elastocal.identify.robot import bundled_robot
    from elastocal.identify.static import identify_static
    from elastocal.identify.tables import write_static_table
    from elastocal.sims.cell import CellTruth
    from elastocal.sims.static import StaticPlan, simulate_static

    out = pathlib.Path(args.out) if args.out else pathlib.Path(tempfile.mkdtemp(prefix="elastocal-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    say = _Say()
    robot = bundled_robot()
    truth = CellTruth()
    say(f"Built the {robot.name} from its modified-DH table with Pinocchio: 6 joints, markers "
        f"{', '.join(robot.marker_names)}, hydro-pneumatic compensator on joint 2.")
    (out / "robot.toml").write_text(robot.to_toml(), encoding="utf-8")
    plan = StaticPlan(n_poses=12, n_loads=3, repeats=3)
    table = simulate_static(robot, truth, seed=args.seed, plan=plan)
    write_static_table(out / "static.csv", table)
    say(f"Ran a static before/after-load experiment on the simulated cell: {plan.n_poses} poses, "
        f"unloaded + {plan.n_loads} loads, {len(robot.marker_names)} markers, {plan.repeats} readings each "
        f"(tracker noise 10 µm, current noise 0.02 A) -> {out / 'static.csv'}")
    truth_params = truth.parameters(robot)
    for torque in ("current", "force"):
        fit = identify_static(robot, table, torque=torque, form="exact")
        obj = fit.to_json()
        say(f"Identified the joint stiffness from {'motor currents (Y39-42)' if torque == 'current' else 'the applied forces (Y35)'}, "
            "exact (secant) form:")
        print(format_parameters(obj["parameters"], truth_params))
        print("  " + verdict_line(fit.rms, fit.noise_floor))
        if torque == "current":
            write_calibration(out / "cal.json", calibration_from_fit(robot.name, obj, [out / "static.csv"]))
            current_fit = fit
    err = np.abs(current_fit.values([f"k{j}" for j in range(1, 7)]) / truth.stiffness - 1) * 100
    say("Summary")
    print(f"  current-based stiffness: worst error {err.max():.2f} % against the simulator's truth; "
          f"residual {current_fit.rms * 1e6:.1f} µm rms at a noise floor of {current_fit.noise_floor * 1e6:.1f} µm.")
    print(f"  calibration written to {out / 'cal.json'}; files in {out}")
    (out / "demo.json").write_text(json.dumps({"stiffness_error_percent": err.tolist(),
                                               "rms": current_fit.rms, "noise_floor": current_fit.noise_floor}))
    return 0
