"""The limit the fit benchmarks measure in their own run: one forward kinematics.

``python benchmarks/bench_absolute.py`` and ``bench_diagnose.py`` time FK batches
between their fits: the fastest batch is the machine's unloaded speed, the
median against it the load factor of that run.
"""

from __future__ import annotations

import time

import numpy as np
import pinocchio as pin


def fk_batches_s(robot, batches: int = 10, n: int = 50_000) -> list[float]:
    """Seconds per forward kinematics (one Data reused) of each of ``batches`` batches of ``n``."""
    data = robot.model.createData()
    theta = robot.theta(np.array([0.1, 0.3, 0.2, 0.0, 0.5, 0.0]))
    out = []
    for _ in range(batches):
        t0 = time.perf_counter_ns()
        for _ in range(n):
            pin.forwardKinematics(robot.model, data, theta)
        out.append((time.perf_counter_ns() - t0) * 1e-9 / n)
    return out
