"""coulomb_friction: friction of constant size opposes every motion.

Parameters fc1..fc6 [N*m]. Run model (docs/physics.md, Y §6): during a slow
motion the drive supplies the load torque and the friction in the direction
of motion (friction resists the motion; the motor's torque balance),
``xi i = tau_load + friction``, with this effect's part ``fc_j sign(dq_j)``.
UV/VU runs (the same path forward and backward) show it: friction changes sign
with the direction, load and gravity do not, ``i_f = (i_UV - i_VU)/2`` (Y48).
It is identified from the run table (identify/friction.py). Static data hold
no motion, so they cannot show it.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Effect, StaticContext, wrong_sign
from elastocal.model.effects.base import joint_names, joint_units


def _refusal(ctx: StaticContext) -> str:
    return "friction acts during motion; static data hold no motion (use UV/VU runs)"


def make(robot=None) -> Effect:
    """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
    return Effect(
        name="coulomb_friction",
        parameters=joint_names("fc", robot),
        units=joint_units("N*m", "N", robot),
        seen_in=("runs",),
        explanation="friction of constant size opposes every motion",
        evidence="UV and VU currents differ by a constant",
        static_refusal=_refusal,
        static_model="none: static readings are taken at rest",
        run_model="xi i = tau_load + fc_j sign(dq_j)",
        run_part="uv/vu",
        plausibility=lambda names, values, stds: wrong_sign(names, values, stds, "friction"),
        run_column=lambda speed, load: np.ones_like(speed),
        sized=make,
        run_needs="UV/VU runs",
    )


EFFECT = make()
