"""A joint-2 sweep with markers on the gravity compensator (data for ``elastocal geometry``).

The hydropneumatic compensator of robot.toml (docs/physics.md) in the plane of
joint 2: its fixed pivot P0 on link 1 at distance ``b`` from the joint-2 axis
P2, its moving pivot P1 on link 2 at ``r = hypot(a, h)`` from P2, so that
``|P1 - P0|`` is the compensator length ``hydro_length(q2)`` of the model. A
marker ``P1`` sits on the moving pivot; two markers ``P01``, ``P02`` on the
cylinder, which turns about P0 as the compensator extends. Positions in the
robot's base frame (the tracker's), with the tracker's noise. Klimchik's
measurement (K §IV), simulated.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from elastocal.model.robot import Robot
from elastocal.model.kinds import CompensatorKind
from elastocal.formats.tables import RunTable, run_table_from_arrays

PIVOT = "P1"
CYLINDER = ("P01", "P02")
#: the cylinder markers: distance from P0 [m] and angle off the cylinder's axis [rad]
CYLINDER_MARKS = ((0.15, 0.35), (0.17, -0.45))


def compensator_truth(robot: Robot) -> dict:
    """What ``geometry`` identifies, from the compensator of ``robot``: ``L`` (P2 to P1) and
    ``a`` (P2 to P0) [m]."""
    c = robot.compensator
    if c is None or c.kind != CompensatorKind.HYDROPNEUMATIC:
        raise ValueError("the robot has no hydropneumatic compensator")
    return {"L": math.hypot(c.geo("a"), c.geo("h")), "a": c.geo("b")}


def _plane_frame(robot: Robot, q: np.ndarray) -> pin.SE3:
    """The compensated joint's frame (joint 2 of a six-axis arm) at its zero (fixed to the link
    before it)."""
    j = robot.compensator.joint
    q = np.array(q, dtype=float)
    q[j - 1] = 0.0
    model = robot.model
    data = model.createData()
    pin.forwardKinematics(model, data, robot.theta(q))
    return data.oMi[model.getJointId(f"joint{j}")]


def marker_positions(robot: Robot, q: np.ndarray) -> dict[str, np.ndarray]:
    """Base-frame positions of P1, P01, P02 at joint values ``q`` (n, N)."""
    c = robot.compensator
    a, b, h = c.geo("a"), c.geo("b"), c.geo("h")
    r, alpha = math.hypot(a, h), math.atan2(a, h)
    q = np.atleast_2d(q)
    out = {name: [] for name in (PIVOT, *CYLINDER)}
    for row in q:
        frame = _plane_frame(robot, row)
        p0 = np.array([b, 0.0, 0.0])
        phi = math.pi / 2 - alpha + row[c.joint - 1]
        p1 = r * np.array([math.cos(phi), math.sin(phi), 0.0])
        beta = math.atan2(p1[1] - p0[1], p1[0] - p0[0])
        out[PIVOT].append(frame.act(p1))
        for name, (rho, delta) in zip(CYLINDER, CYLINDER_MARKS):
            out[name].append(frame.act(p0 + rho * np.array([math.cos(beta + delta), math.sin(beta + delta), 0.0])))
    return {k: np.array(v) for k, v in out.items()}


def compensator_sweep(robot: Robot, rng: np.random.Generator, *, q2_start: float = -0.6, q2_end: float = 1.7,
                      steps: int = 47, noise_m: float = 10e-6, source: str = "<compensator sweep>") -> RunTable:
    """Run table of a slow sweep of the compensated joint (joint 2 of a six-axis arm) at rest
    points, one row per marker reading; the other joints as :class:`~elastocal.sims.runs.SweepPlan`
    holds them (a prismatic joint mid-travel)."""
    from elastocal.sims.runs import SweepPlan

    q = np.tile(SweepPlan.for_robot(robot).q_base, (steps, 1))
    q[:, robot.compensator.joint - 1] = np.linspace(q2_start, q2_end, steps)
    pos = marker_positions(robot, q)
    rows = {k: [] for k in ("run", "direction", "load", "t", "q", "marker", "xyz")}
    for n in range(steps):
        for name in (PIVOT, *CYLINDER):
            rows["run"].append("compensator-sweep")
            rows["direction"].append("+")
            rows["load"].append("0")
            rows["t"].append(10.0 * n)
            rows["q"].append(q[n])
            rows["marker"].append(name)
            rows["xyz"].append(pos[name][n] + rng.normal(0.0, noise_m, 3))
    return run_table_from_arrays(run=rows["run"], direction=rows["direction"], load=rows["load"], t=rows["t"],
                                 q=rows["q"], marker=rows["marker"], xyz=rows["xyz"], source=source)
