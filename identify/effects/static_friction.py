"""static_friction: friction in a resting gear takes part of a load change.

An elastocal extension of the effect table of cli.md (the simulator's
``--hidden static_friction``; Y Table 6 shows it as a force-based stiffness that
comes out too high). When a load is hung on a robot at rest, friction in the
gears and bearings holds up to ``fs_j`` of the change of each joint's torque;
the spring twists only under the rest. Currents measure the torque the gear
actually carries after friction took its share, so the current-based model does
not need it: only a force-based model (``--torque force``) can lack it.

Parameters us1..us6 [rad]: the deflection each joint's static friction holds
back, ``us_j = fs_j / k_j`` (so ``fs_j = k_j us_j`` [N·m]). The static model is
linear in them: a loaded state's joint angle gains ``-us_j sign(dtau_j)``,
``dtau`` the force-based change of the joint torque from the reference. This is
exact when every load change exceeds the friction torque, which the loads of a
calibration (hundreds of N·m) do; a joint whose torque does not change
(``dtau_j = 0``, joint 1 under a hung weight) gains nothing.
"""

from __future__ import annotations

import numpy as np

from elastocal.identify.effects.base import Effect, StaticBasis, StaticContext, diagonal_basis

#: a torque change below this is taken as no change [N·m]
ZERO_TORQUE_NM = 1e-6


def _basis(ctx: StaticContext) -> StaticBasis:
    sign = np.where(np.abs(ctx.delta_tau) > ZERO_TORQUE_NM, np.sign(ctx.delta_tau), 0.0)
    sign[ctx.state_is_reference] = 0.0
    return StaticBasis(theta=diagonal_basis(-sign))


def _refusal(ctx: StaticContext) -> str | None:
    if ctx.torque_source != "force":
        return ("currents measure the torque the gears carry after static friction took its share; "
                "the current-based model does not need it (compare with --torque force)")
    return None


EFFECT = Effect(
    name="static_friction",
    parameters=tuple(f"us{j}" for j in range(1, 7)),
    units=("rad",) * 6,
    seen_in=("static",),
    explanation="friction in the resting gears holds part of each load, so the arm sags less than the "
                "force on it says",
    evidence="force-based deflection short of the load by a constant amount per joint; stiffness too high",
    static_basis=_basis,
    static_refusal=_refusal,
    static_model="each loaded state's joint angle gains -us_j sign(dtau_j) (force-based torques only)",
    run_model="during motion friction is coulomb_friction, viscous_friction and load_dependent_friction",
)
