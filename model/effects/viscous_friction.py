"""viscous_friction: friction grows with speed.

Parameters fv1..fv6 [N*m*s/rad]. Run model (docs/physics.md, Y §6): during a slow
motion the drive supplies the load torque and the friction in the direction
of motion (friction resists the motion; the motor's torque balance),
``xi i = tau_load + friction``, with this effect's part ``fv_j dq_j``.
UV/VU runs (the same path forward and backward) show it: friction changes sign
with the direction, load and gravity do not, ``i_f = (i_UV - i_VU)/2`` (Y48).
It is identified from the run table (identify/friction.py). Static data hold
no motion, so they cannot show it.
"""

from __future__ import annotations

from elastocal.model.effects.base import Effect, StaticContext, wrong_sign
from elastocal.model.effects.base import joint_names, joint_units


def _refusal(ctx: StaticContext) -> str:
    return "friction acts during motion; static data hold no motion (use runs at two speeds)"


def make(robot=None) -> Effect:
    """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
    return Effect(
        name="viscous_friction",
        parameters=joint_names("fv", robot),
        units=joint_units("N*m*s/rad", "N*s/m", robot),
        seen_in=("runs",),
        explanation="friction grows with speed",
        evidence="the UV/VU current difference grows with speed",
        static_refusal=_refusal,
        static_model="none: static readings are taken at rest",
        run_model="xi i = tau_load + fv_j dq_j",
        run_part="uv/vu",
        plausibility=lambda names, values, stds: wrong_sign(names, values, stds, "viscous friction"),
        run_column=lambda speed, load: speed,
        sized=make,
        run_needs="runs at two or more speeds",
    )


EFFECT = make()
