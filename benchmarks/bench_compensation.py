"""Compensation throughput on a 100,000-point path, as a ratio to one Pinocchio forward-kinematics call.

Run: python benchmarks/bench_compensation.py [--points N] [--repeat R]

The path is the Yang Table 8 line (tool point x 1.2 -> 1.8 m at z 0.116 m)
solved by inverse kinematics at 5 mm steps and interpolated in joint space to
N points; the process wrench is 1500 N. The model is the bundled HH-150 with
gravity and its hydro-pneumatic compensator; the last case adds a geometric
calibration (kinematic errors) and compensates to the drawing's poses.

The limit is one ``pinocchio.forwardKinematics`` call from Python on the
path's configurations, measured in the same run right before and after each
run of each case: each case prints its time per point in units of that call
(the run with the smallest ratio, and the median), which means the same on a
quiet and on a loaded machine. Times are the process's CPU time (the wall time
is printed too): on a machine shared with other work the wall time is mostly
the share of a core the scheduler gave, the CPU time what the code costs, and
the case and its FK limit are measured alike. points/s is points per CPU second. The
speed goals (150,000 points/s exact, 500,000 points/s first-order, with
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
from elastocal.identify import kinematics as kin
from elastocal.formats.robot_toml import bundled_robot
from elastocal.model.kinds import KinematicForm
from elastocal.sims.cell import CellTruth

#: the speed goals [points/s] and the forward-kinematics time they were set against [s]
GOAL_EXACT_POINTS_S = 150_000
GOAL_FIRST_ORDER_POINTS_S = 500_000
GOAL_FK_S = 0.48e-6


def dense_path(robot, n: int) -> np.ndarray:
    coarse = yang_path(robot)
    s = np.linspace(0.0, 1.0, len(coarse))
    s_new = np.linspace(0.0, 1.0, n)
    return np.column_stack([np.interp(s_new, s, coarse.q[:, j]) for j in range(6)])


def fk_time(robot, thetas: np.ndarray) -> float:
    """CPU time [s] of one ``forwardKinematics`` call: a sweep over the path's configurations."""
    model, data = robot.model, robot.model.createData()
    t0 = time.process_time_ns()
    for th in thetas:
        pin.forwardKinematics(model, data, th)
    return (time.process_time_ns() - t0) * 1e-9 / len(thetas)


def timed_against_fk(fn, robot, thetas: np.ndarray, repeat: int) -> tuple[float, float, float, float]:
    """``repeat`` runs of ``fn``, each between two FK sweeps: the smallest CPU and wall times of a
    run [s], and the smallest and the median ratio of a run's CPU time to the FK time around it."""
    cpu, wall, ratios = [], [], []
    after = fk_time(robot, thetas)
    for _ in range(repeat):
        before = after
        t0, w0 = time.process_time_ns(), time.perf_counter_ns()
        fn()
        cpu.append((time.process_time_ns() - t0) * 1e-9)
        wall.append((time.perf_counter_ns() - w0) * 1e-9)
        after = fk_time(robot, thetas)
        ratios.append(cpu[-1] / (0.5 * (before + after)))
    return min(cpu), min(wall), min(ratios), float(np.median(ratios))


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
    # a geometric calibration (kinematic_errors, 0.2 mm / 0.2 mrad scale): the nominal reference
    names = kin.parameter_names(robot, robot.marker_names)
    geometry = kin.corrected_robot(robot, names, np.random.default_rng(15).normal(size=len(names)) * 2e-4)
    calibrated = CompensationModel(geometry, truth.stiffness, truth.compensator, nominal=robot)
    result = compensate_path(model, q, wrench, form=KinematicForm.EXACT)
    cases = [
        ("exact, unloaded reference", exact_fk, lambda: compensate_path(model, q, wrench, form=KinematicForm.EXACT)),
        ("first-order, unloaded reference", first_fk,
         lambda: compensate_path(model, q, wrench, form=KinematicForm.FIRST_ORDER)),
        ("exact, rigid reference", exact_fk,
         lambda: compensate_path(model, q, wrench, form=KinematicForm.EXACT, reference="rigid")),
        ("first-order, rigid reference", first_fk,
         lambda: compensate_path(model, q, wrench, form=KinematicForm.FIRST_ORDER, reference="rigid")),
        ("predicted residual (check)", None, lambda: predicted_residual(model, result)),
        ("exact, nominal reference (geometry)", None,
         lambda: compensate_path(calibrated, q, wrench, form=KinematicForm.EXACT, reference="nominal")),
    ]
    rows = [(name, goal, *timed_against_fk(fn, robot, thetas, args.repeat)) for name, goal, fn in cases]
    fk_s = fk_time(robot, thetas)

    print(f"compensation of a {args.points:,}-point path, {robot.name}, 1500 N ({args.repeat} runs of each case, "
          f"each between two sweeps of {len(thetas):,} forwardKinematics calls; times are the process's CPU time)")
    print(f"{'case':<36} {'CPU [s]':>8} {'wall [s]':>9} {'points/s':>10} {'x one FK':>9} {'median':>7} "
          f"{'goal [x FK]':>12} {'/ goal':>7}")
    for name, goal, cpu, wall, ratio, median in rows:
        per = ratio / args.points
        tail = f"{goal:>12.1f} {per / goal:>7.2f}" if goal else f"{'':>12} {'':>7}"
        print(f"{name:<36} {cpu:>8.3f} {wall:>9.3f} {args.points / cpu:>10,.0f} {per:>9.1f} "
              f"{median / args.points:>7.1f} {tail}")
    print(f"one pinocchio.forwardKinematics: {fk_s * 1e6:.3f} us at the end of the run")
    print(f"goals: exact >= {GOAL_EXACT_POINTS_S:,} points/s, first-order >= {GOAL_FIRST_ORDER_POINTS_S:,} "
          f"points/s with one FK at {GOAL_FK_S * 1e6:.2f} us, i.e. <= {exact_fk:.1f} and <= {first_fk:.1f} FK "
          "per point ('x one FK': the run with the smallest ratio to the FK time around it)")


if __name__ == "__main__":
    main()
