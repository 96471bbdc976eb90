"""Compensation throughput on a 100,000-point path, as a ratio to one Pinocchio forward-kinematics call.

Run: python benchmarks/bench_compensation.py [--points N] [--repeat R]

The path is the Yang Table 8 line (tool point x 1.2 -> 1.8 m at z 0.116 m)
solved by inverse kinematics at 5 mm steps and interpolated in joint space to
N points; the process wrench is 1500 N. The model is the bundled HH-150 with
gravity and its hydro-pneumatic compensator.

The limit is one ``pinocchio.forwardKinematics`` call from Python on the
path's configurations, measured in the same run between the cases (the
fastest of those measurements): each case prints its time per point in units
of that call, which means the same on a quiet and on a loaded machine. The
goals of issue 15 (150,000 points/s exact, 500,000 points/s first-order, with
one forward kinematics at 0.48 us) are 13.9 and 4.2 forward kinematics per
point; the last column is the measured figure over the goal (<= 1 meets it).
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

#: issue 15's goals [points/s] and the forward-kinematics time they were set against [s]
GOAL_EXACT_POINTS_S = 150_000
GOAL_FIRST_ORDER_POINTS_S = 500_000
GOAL_FK_S = 0.48e-6


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


def fk_time(robot, thetas: np.ndarray) -> float:
    """One ``forwardKinematics`` call [s], the fastest of 3 sweeps over ``thetas``."""
    model, data = robot.model, robot.model.createData()

    def sweep() -> None:
        for th in thetas:
            pin.forwardKinematics(model, data, th)

    return best_of(sweep, 3) / len(thetas)


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
    thetas = robot.theta(q[:: max(1, len(q) // 20_000)])

    exact_fk = 1.0 / (GOAL_EXACT_POINTS_S * GOAL_FK_S)
    first_fk = 1.0 / (GOAL_FIRST_ORDER_POINTS_S * GOAL_FK_S)
    result = compensate_path(model, q, wrench, form="exact")
    cases = [
        ("exact, unloaded reference", exact_fk, lambda: compensate_path(model, q, wrench, form="exact")),
        ("first-order, unloaded reference", first_fk,
         lambda: compensate_path(model, q, wrench, form="first-order")),
        ("exact, rigid reference", exact_fk,
         lambda: compensate_path(model, q, wrench, form="exact", reference="rigid")),
        ("first-order, rigid reference", first_fk,
         lambda: compensate_path(model, q, wrench, form="first-order", reference="rigid")),
        ("predicted residual (check)", None, lambda: predicted_residual(model, result)),
    ]
    rows, fks = [], [fk_time(robot, thetas)]
    for name, goal, fn in cases:
        rows.append((name, goal, best_of(fn, args.repeat)))
        fks.append(fk_time(robot, thetas))
    fk_s = min(fks)

    print(f"compensation of a {args.points:,}-point path, {robot.name}, 1500 N (best of {args.repeat}); "
          f"one forwardKinematics {fk_s * 1e6:.3f} us (fastest of {len(fks)} measurements in this run, "
          f"slowest {max(fks) * 1e6:.3f} us)")
    print(f"{'case':<34} {'total [s]':>10} {'points/s':>12} {'per point [us]':>15} {'x one FK':>9} "
          f"{'goal [x FK]':>12} {'/ goal':>7}")
    for name, goal, total in rows:
        per = total / args.points
        ratio = per / fk_s
        tail = f"{goal:>12.1f} {ratio / goal:>7.2f}" if goal else f"{'':>12} {'':>7}"
        print(f"{name:<34} {total:>10.3f} {args.points / total:>12,.0f} {per * 1e6:>15.2f} {ratio:>9.1f} {tail}")
    print(f"{'one pinocchio.forwardKinematics':<34} {'':>10} {1 / fk_s:>12,.0f} {fk_s * 1e6:>15.3f} {1:>9.1f}")
    print(f"goals: exact >= {GOAL_EXACT_POINTS_S:,} points/s, first-order >= {GOAL_FIRST_ORDER_POINTS_S:,} "
          f"points/s with one FK at {GOAL_FK_S * 1e6:.2f} us, i.e. <= {exact_fk:.1f} and <= {first_fk:.1f} FK "
          f"per point; here that is >= {1 / (exact_fk * fk_s):,.0f} and >= {1 / (first_fk * fk_s):,.0f} points/s")


if __name__ == "__main__":
    main()
