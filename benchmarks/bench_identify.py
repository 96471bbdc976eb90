"""Static identification time for 12, 60 and 300 poses (3 loads, 3 markers, 3 repeats).

    python benchmarks/bench_identify.py [--repeat N] [--sizes 12,60,300]

Prints, per size and form, the median wall and CPU time of identify_static, the wall time in
units of one Pinocchio forward-kinematics call measured in the same run (so the figure means
the same on a loaded machine), and the recovered stiffness error, so speed and accuracy are
read together; then the time of averaging the table alone (build_dataset: one grouped numpy
pass over the rows) and of reading the same table from CSV; last, the speed goal (300
poses, exact, current, under 0.5 s on a quiet machine whose FK takes 0.48 us: one million FK)
as the ratio of this run's figure to it.

(The fit runs its linear algebra on one BLAS thread itself: identify/blas.py.)
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import tempfile
import time

import numpy as np
import pinocchio as pin

from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import build_dataset, identify_static
from elastocal.formats.tables import read_static_table, write_static_table
from elastocal.sims.cell import CellTruth
from elastocal.model.kinds import KinematicForm, TorqueSource
from elastocal.sims.static import StaticPlan, simulate_static


def one_fk_s(robot, n: int = 50_000) -> float:
    data = robot.model.createData()
    theta = robot.theta(np.array([0.1, 0.3, 0.2, 0.0, 0.5, 0.0]))
    t0 = time.perf_counter_ns()
    for _ in range(n):
        pin.forwardKinematics(robot.model, data, theta)
    return (time.perf_counter_ns() - t0) * 1e-9 / n


#: the speed goal: identify, 300 poses, exact, current, under 0.5 s where one FK takes 0.48 us
GOAL_S, GOAL_FK_S = 0.5, 0.48e-6


def median_s(fn, repeat: int) -> float:
    return median_wall_cpu_s(fn, repeat)[0]


def median_wall_cpu_s(fn, repeat: int) -> tuple[float, float]:
    """Median wall and CPU (this process) seconds of ``fn()``."""
    walls, cpus = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sizes", default="12,60,300")
    args = parser.parse_args()
    robot = bundled_robot()
    truth = CellTruth()
    fk_s = one_fk_s(robot)
    print(f"one pinocchio.forwardKinematics: {fk_s * 1e6:.3f} us (measured in this run)")
    print(f"{'poses':>6} {'rows':>7} {'form':<12} {'torque':<8} {'median s':>9} {'cpu s':>7} {'x one FK':>10} "
          f"{'max |k err| %':>14}")
    goal = None
    for n in (int(s) for s in args.sizes.split(",")):
        table = simulate_static(robot, truth, seed=n, plan=StaticPlan(n_poses=n))
        for form, torque in ((KinematicForm.FIRST_ORDER, TorqueSource.CURRENT),
                             (KinematicForm.EXACT, TorqueSource.CURRENT), (KinematicForm.EXACT, TorqueSource.FORCE)):
            fits = []
            t, cpu = median_wall_cpu_s(lambda: fits.append(identify_static(robot, table, form=form, torque=torque)),
                                       args.repeat)
            err = np.max(np.abs(fits[-1].values([f"k{j}" for j in range(1, 7)]) / truth.stiffness - 1)) * 100
            print(f"{n:>6} {len(table):>7} {form:<12} {torque:<8} {t:>9.3f} {cpu:>7.3f} {t / fk_s:>10,.0f} "
                  f"{err:>14.2f}")
            if n == 300 and (form, torque) == (KinematicForm.EXACT, TorqueSource.CURRENT):
                goal = t / fk_s
        t = median_s(lambda: build_dataset(table), args.repeat)
        with tempfile.TemporaryDirectory() as tmp:
            path = pathlib.Path(tmp) / "static.csv"
            write_static_table(path, table)
            t_read = median_s(lambda: read_static_table(path, robot), args.repeat)
        print(f"{'':>6} {'':>7} averaging the table alone: {t:.4f} s = {t / fk_s:,.0f} FK; "
              f"reading its CSV: {t_read:.3f} s = {t_read / fk_s:,.0f} FK")
    if goal is not None:
        limit = GOAL_S / GOAL_FK_S
        print(f"goal: 300 poses, exact, current < {GOAL_S} s at a {GOAL_FK_S * 1e6:.2f} us FK = {limit:,.0f} FK; "
              f"this run {goal:,.0f} FK = {goal / limit:.2f} x the goal ({'met' if goal <= limit else 'not met'})")


if __name__ == "__main__":
    main()
