"""static_friction: friction in a resting gear takes part of a load change.

An elastocal extension of the effect table of docs/cli.md (the simulator's
``--hidden static_friction``; Y Table 6 shows it as a force-based stiffness that
comes out too high). When a load is hung on a robot at rest, friction in the
gears and bearings holds up to ``fs_j`` of the change of each joint's torque;
the spring twists only under the rest. Currents measure the torque the gear
actually carries after friction took its share, so the current-based model does
not need it: only a force-based model (``--torque force``) can lack it.

Parameters us1..us6 [rad]: the deflection each joint's static friction holds
back, ``us_j = fs_j / k_j`` (so ``fs_j = k_j us_j`` [N·m]). A loaded state's
joint angle gains ``-c_j clip(dtau_j, -fs_j, fs_j) = -us_j w_j sign(dtau_j)``,
``dtau`` the force-based change of the joint torque from the reference and
``w_j = min(1, |dtau_j| / fs_j)``: a load change smaller than the friction is
held entirely. The fit starts from ``w = 1`` (every load change exceeds the
friction, as the loads of a calibration mostly do) and rebuilds ``w`` from the
current estimate of ``fs = us / c`` at every iteration (``Effect.iterative``);
a joint whose torque does not change (joint 1 under a hung weight) gains
nothing.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Effect, StaticBasis, StaticContext, diagonal_basis, strongest
from elastocal.model.effects.base import joint_names, joint_units
from elastocal.model.kinds import TorqueSource

#: a torque change below this is taken as no change [N·m]
ZERO_TORQUE_NM = 1e-6


def _basis(ctx: StaticContext) -> StaticBasis:
    dtau = ctx.delta_tau
    sign = np.where(np.abs(dtau) > ZERO_TORQUE_NM, np.sign(dtau), 0.0)
    sign[ctx.state_is_reference] = 0.0
    weight = np.ones_like(dtau)
    for j in range(dtau.shape[1]):
        us, c = ctx.estimated(f"us{j + 1}"), ctx.estimated(f"c{j + 1}")
        if us is not None and c is not None and us > 0.0 and c > 0.0:
            weight[:, j] = np.minimum(1.0, np.abs(dtau[:, j]) * c / us)
    return StaticBasis(theta=diagonal_basis(-sign * weight))


def _refusal(ctx: StaticContext) -> str | None:
    if ctx.torque_source is not TorqueSource.FORCE:
        return ("currents measure the torque the gears carry after static friction took its share; "
                "the current-based model does not need it (only a force-based model can lack it)")
    return None


def _describe(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str:
    k = strongest(names, values, stds)
    return (f"the arm sags less than the force-based torques say, by a constant amount per joint "
            f"(joint {names[k][2:]} holds back {values[k] * 1e6:.0f} µrad)")


def make(robot=None) -> Effect:
    """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
    return Effect(
        name="static_friction",
        parameters=joint_names("us", robot),
        units=joint_units("rad", "m", robot),
        seen_in=("static",),
        explanation="friction in the resting gears holds part of each load, so the arm sags less than the "
                    "force on it says",
        evidence="force-based deflection short of the load by a constant amount per joint; stiffness too high",
        static_basis=_basis,
        static_refusal=_refusal,
        iterative=True,
        describe=_describe,
        sized=make,
        static_model="each loaded state's joint angle gains -c_j clip(dtau_j, +-fs_j), fs_j = us_j / c_j "
                     "(force-based torques only)",
        run_model="during motion friction is coulomb_friction, viscous_friction and load_dependent_friction",
    )


EFFECT = make()
