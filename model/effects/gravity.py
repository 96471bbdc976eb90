"""gravity: corrections to the links' mass moments in the joint torques.

The run model always holds the gravity of the links from the robot
description's masses; this effect identifies corrections to them from the
joint-2 torque over the sweeps: ``g2(theta) = Y2(theta) pi`` is linear in the
links' inertial parameters (Pinocchio's joint-torque regressor at rest), and
only the combinations the sweeps excite are kept (an SVD of the stacked rows):
one sweep excites two (the distal body's mass moment about axis 2), sweeps at
two or more q3 separate link 2's from link 3's. A description without link
masses makes it required: the sweep fit then identifies the whole gravity with
the compensator. Static before/after-load differences cancel gravity, so
static data cannot show it.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from elastocal.model.effects.base import Compensation, Effect, StaticContext, SweepContext, SweepTerm

#: relative singular value below which a gravity combination counts as not excited
GRAVITY_RANK_TOL = 1e-8


def _refusal(ctx: StaticContext) -> str:
    return "gravity cancels in before/after-load differences; it shows in run torques"


def joint_regressor(robot, theta: np.ndarray, joint: int = 1) -> np.ndarray:
    """The swept joint's rows (0-based ``joint``; 1 is joint 2) of Pinocchio's joint-torque
    regressor at rest: g_j = Y_j pi."""
    model = robot.model
    data = model.createData()
    zero = np.zeros(model.nv)
    return np.array([pin.computeJointTorqueRegressor(model, data, th, zero, zero)[joint].copy() for th in theta])


def excited_basis(regressor: np.ndarray) -> np.ndarray:
    """(n_inertial, r) orthonormal basis of the inertial-parameter combinations the rows excite."""
    used = np.linalg.norm(regressor, axis=0) > 0
    basis = np.zeros((regressor.shape[1], 0))
    if not np.any(used):
        return basis
    _, s, vt = np.linalg.svd(regressor[:, used], full_matrices=False)
    rank = int(np.sum(s > GRAVITY_RANK_TOL * s[0])) if s.size and s[0] > 0 else 0
    # a singular vector's sign is the LAPACK kernel's choice (it differs between CPUs): fix it so
    # that the identified g_k mean the same combination everywhere. The first entry of at least
    # half the largest magnitude is made positive (not the largest: two entries of equal size,
    # a mass moment's x and y, would let the last bits choose)
    vectors = vt[:rank].T
    lead = np.argmax(np.abs(vectors) >= 0.5 * np.abs(vectors).max(axis=0), axis=0)
    vectors = vectors * np.where(vectors[lead, np.arange(rank)] < 0, -1.0, 1.0)
    basis = np.zeros((regressor.shape[1], rank))
    basis[used] = vectors
    return basis


def _sweep_term(ctx: SweepContext) -> SweepTerm | str:
    reg = joint_regressor(ctx.robot, np.asarray(ctx.theta, dtype=float), ctx.joint)
    phi = reg @ excited_basis(reg)
    rank = phi.shape[1]
    if rank == 0 or len(phi) <= rank + 1:
        return "the sweeps excite no gravity parameter"
    required = None if ctx.robot.has_masses else \
        "the robot description gives no link masses: the sweeps identify the gravity too"
    return SweepTerm(names=tuple(f"g{k + 1}" for k in range(rank)), units=("N*m",) * rank,
                     torque=lambda p: phi @ p, jacobian=lambda p: phi, linear=True, required=required)


EFFECT = Effect(
    name="gravity",
    parameters=("mass moments",),
    units=("kg*m",),
    seen_in=("runs",),
    explanation="the weight of the links loads the joints",
    evidence="torque residual that follows the arm's posture",
    static_refusal=_refusal,
    static_model="none: gravity cancels in before/after-load differences",
    run_model="xi i gains -dg(q): the gravity torque of corrected link mass moments",
    run_part="sweep",
    sweep_term=_sweep_term,
    compensation=Compensation.MODELLED,
)
