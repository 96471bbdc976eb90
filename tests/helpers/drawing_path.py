"""A loaded straight path planned on the drawing, compensated, and the tool's error along it as the
simulated cell's tracker sees it (tests of compensation with a geometric calibration)."""

from __future__ import annotations

import numpy as np

from elastocal.compensation.trajectory import compensate_path


def drawing_path(model):
    """25 poses from one posture to another under a 1.5 kN process load: (q, wrench, compensated path)."""
    s = np.linspace(0.0, 1.0, 25)[:, None]
    q = np.array([-0.4, 0.1, -0.3, 0.3, 0.9, -0.2]) * (1 - s) + np.array([0.5, 0.6, 0.1, -0.4, 1.4, 0.5]) * s
    wrench = np.array([300.0, -200.0, -1500.0, 0.0, 0.0, 0.0])
    return q, wrench, compensate_path(model, q, wrench)


def tracker_error(robot, cell, frame, q, commands, wrench) -> np.ndarray:
    """Distance [m] between where the cell puts marker R1 under ``commands`` and where the drawing's
    ``q`` means it, in the tracker's frame (``frame``: the calibration's)."""
    return np.array([np.linalg.norm(cell.tracker_positions(cell.equilibrium(qc, wrench), ["R1"])[0]
                                    - frame.apply(robot.positions(robot.theta(qn), ["R1"]))[0])
                     for qn, qc in zip(q, commands)])
