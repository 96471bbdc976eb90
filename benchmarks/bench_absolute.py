"""Absolute fit time: geometry, registration and every static effect together (issue 12).

    python benchmarks/bench_absolute.py [--poses 60] [--repeat 3]

A simulated cell with kinematic errors, link compliance and thermal drift, the
tracker 3.7 m away and turned; the fit is ``joint_stiffness, link_compliance,
thermal_drift, backlash, kinematic_errors, tracker_frame`` on 60 poses x 4
states x 3 markers x 3 repeats. Prints the median wall time, its ratio to the
5 s limit of the issue, and its ratio to one Pinocchio forward kinematics
measured in the same run (the unit the fit's cost is made of), with the
absolute rms against its noise floor so speed and accuracy are read together.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from elastocal.identify.absolute import identify_absolute
from elastocal.identify.robot import bundled_robot
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

LIMIT_S = 5.0
MODEL = ("joint_stiffness", "link_compliance", "thermal_drift", "backlash", "kinematic_errors", "tracker_frame")


def one_fk_s(robot, n: int = 2000) -> float:
    q = np.zeros(6)
    t0 = time.perf_counter()
    for _ in range(n):
        robot.positions(robot.theta(q), ["R1"])
    return (time.perf_counter() - t0) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    robot = bundled_robot()
    truth = CellTruth().with_hidden("kinematic_errors,link_compliance,thermal_drift")
    table = simulate_static(robot, truth, seed=5, plan=StaticPlan(n_poses=args.poses))
    fk = one_fk_s(robot)
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        fit = identify_absolute(robot, table, model=MODEL)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    print(f"{args.poses} poses, {len(table)} readings, model {','.join(MODEL)}")
    print(f"  absolute fit: median {med:.2f} s over {args.repeat}; {med / LIMIT_S:.2f} of the {LIMIT_S:.0f} s limit; "
          f"{med / fk:.0f} x one forward kinematics ({fk * 1e6:.1f} µs)")
    print(f"  absolute rms {fit.rms * 1e6:.2f} µm, floor {fit.noise_floor * 1e6:.2f} µm "
          f"({fit.rms / fit.noise_floor:.2f}x); {fit.n_params} parameters, {fit.iterations} evaluations")


if __name__ == "__main__":
    main()
