"""Compensation throughput on a 100,000-point path, next to one Pinocchio forward-kinematics call.

Run: python benchmarks/bench_compensation.py [--points N] [--repeat R]

The path is the Yang Table 8 line (tool point x 1.2 -> 1.8 m at z 0.116 m)
solved by inverse kinematics at 5 mm steps and interpolated in joint space to
N points; the process wrench is 1500 N. The model is the bundled HH-150 with
gravity and its hydro-pneumatic compensator.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pinocchio as pin

from elastocal.compensation.ik import yang_path
from elastocal.compensation.model import CompensationModel
from elastocal.compensation.trajectory import compensate_path, predicted_residual
from elastocal.compensation.validate import YANG_WRENCH
from elastocal.identify.robot import bundled_robot
from elastocal.sims.cell import CellTruth


def dense_path(robot, n: int) -> np.ndarray:
    coarse = yang_path(robot)
    s = np.linspace(0.0, 1.0, len(coarse))
    s_new = np.linspace(0.0, 1.0, n)
    return np.column_stack([np.interp(s_new, s, coarse.q[:, j]) for j in range(6)])


def best_of(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return min(times) * 1e-9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    robot = bundled_robot()
    truth = CellTruth()
    model = CompensationModel(robot, truth.stiffness, truth.compensator)
    q = dense_path(robot, args.points)
    wrench = np.array(YANG_WRENCH)

    data = robot.model.createData()
    theta = robot.theta(q[0])
    n_fk = 100_000
    t0 = time.perf_counter_ns()
    for _ in range(n_fk):
        pin.forwardKinematics(robot.model, data, theta)
    fk_s = (time.perf_counter_ns() - t0) * 1e-9 / n_fk

    print(f"compensation of a {args.points:,}-point path, {robot.name}, 1500 N (best of {args.repeat})")
    print(f"{'case':<34} {'total [s]':>10} {'points/s':>12} {'per point [us]':>15} {'x one FK':>9}")
    cases = [
        ("exact, unloaded reference", lambda: compensate_path(model, q, wrench, form="exact")),
        ("first-order, unloaded reference", lambda: compensate_path(model, q, wrench, form="first-order")),
        ("exact, rigid reference", lambda: compensate_path(model, q, wrench, form="exact", reference="rigid")),
        ("first-order, rigid reference",
         lambda: compensate_path(model, q, wrench, form="first-order", reference="rigid")),
    ]
    result = compensate_path(model, q, wrench, form="exact")
    cases.append(("predicted residual (check)", lambda: predicted_residual(model, result)))
    for name, fn in cases:
        total = best_of(fn, args.repeat)
        per = total / args.points
        print(f"{name:<34} {total:>10.3f} {args.points / total:>12,.0f} {per * 1e6:>15.2f} {per / fk_s:>9.0f}")
    print(f"{'one pinocchio.forwardKinematics':<34} {'':>10} {1 / fk_s:>12,.0f} {fk_s * 1e6:>15.3f} {1:>9}")


if __name__ == "__main__":
    main()
