"""The friction laws of a slow motion, made by one factory (coulomb_friction,
viscous_friction, load_dependent_friction).

Run model (docs/physics.md, Y §6): during a slow motion the drive supplies the
load torque and the friction in the direction of motion (friction resists the
motion; the motor's torque balance), ``xi i = tau_load + friction``; each law adds
its part, a per-joint parameter times its column of the friction regression.
UV/VU runs (the same path forward and backward) show it: friction changes sign
with the direction, load and gravity do not, ``i_f = (i_UV - i_VU)/2`` (Y48).
It is identified from the run table (identify/friction.py). Static data hold no
motion, so they cannot show it.

Not a module of the effect table (its name starts with an underscore): each law is
its own module that calls :func:`friction_law`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from elastocal.model.effects.base import Compensation, Effect, StaticContext, wrong_sign
from elastocal.model.effects.base import joint_names, joint_units


def friction_law(*, name: str, prefix: str, units: tuple[str, str], explanation: str, evidence: str,
                 part: str, column: Callable[[np.ndarray, np.ndarray], np.ndarray], needs: str, use: str,
                 words: str) -> Callable[[object], Effect]:
    """``make(robot)`` of a friction law: parameters ``prefix1..prefixN`` in ``units`` (a revolute
    joint's, a prismatic joint's); ``part`` its term of the run model in words (``fc_j sign(dq_j)``);
    ``column(speed, load)`` its column of the per-joint friction regression per unit parameter;
    ``needs`` the runs that separate it from the laws before it and ``use`` the runs that show it
    (in words, for the refusals); ``words`` what it is called when its sign is wrong."""

    def refusal(ctx: StaticContext) -> str:
        return f"friction acts during motion; static data hold no motion (use {use})"

    def make(robot=None) -> Effect:
        """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
        return Effect(
            name=name,
            parameters=joint_names(prefix, robot),
            units=joint_units(*units, robot),
            seen_in=("runs",),
            explanation=explanation,
            evidence=evidence,
            static_refusal=refusal,
            static_model="none: static readings are taken at rest",
            run_model=f"xi i = tau_load + {part}",
            run_part="uv/vu",
            plausibility=lambda names, values, stds: wrong_sign(names, values, stds, words),
            run_column=column,
            sized=make,
            run_needs=needs,
            compensation=Compensation.NO_PATH_DEFLECTION,
        )

    return make
