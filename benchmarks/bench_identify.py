"""Static identification time for 12, 60 and 300 poses (3 loads, 3 markers, 3 repeats).

    python benchmarks/bench_identify.py [--repeat N]

Prints, per size and form, the median wall time of identify_static and the
recovered stiffness error, so speed and accuracy are read together.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from elastocal.identify.robot import bundled_robot
from elastocal.identify.static import build_dataset, identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    robot = bundled_robot()
    truth = CellTruth()
    print(f"{'poses':>6} {'rows':>7} {'form':<12} {'torque':<8} {'median s':>9} {'max |k err| %':>14}")
    for n in (12, 60, 300):
        table = simulate_static(robot, truth, seed=n, plan=StaticPlan(n_poses=n))
        for form, torque in (("first-order", "current"), ("exact", "current"), ("exact", "force")):
            times = []
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                fit = identify_static(robot, table, form=form, torque=torque)
                times.append(time.perf_counter() - t0)
            err = np.max(np.abs(fit.values([f"k{j}" for j in range(1, 7)]) / truth.stiffness - 1)) * 100
            print(f"{n:>6} {len(table):>7} {form:<12} {torque:<8} {statistics.median(times):>9.3f} {err:>14.2f}")
        t0 = time.perf_counter()
        build_dataset(table)
        print(f"{'':>6} {'':>7} (averaging the table alone: {time.perf_counter() - t0:.3f} s)")


if __name__ == "__main__":
    main()
