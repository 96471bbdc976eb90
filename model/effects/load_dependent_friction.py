"""load_dependent_friction: friction grows with the load the gear carries.

Parameters fl1..fl6 [1]. Run model (docs/physics.md, Y §6): during a slow
motion the motor current carries the load torque less the friction,
``xi i = tau_load - friction``, with this effect's part ``fl_j abs(tau_load_j) sign(dq_j)``.
UV/VU runs (the same path forward and backward) show it: friction changes sign
with the direction, load and gravity do not, ``i_f = (i_UV - i_VU)/2`` (Y48).
It is identified from the run table (identify/friction.py). Static data hold
no motion, so they cannot show it.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Effect, StaticContext, wrong_sign


def _refusal(ctx: StaticContext) -> str:
    return "friction acts during motion; static data hold no motion (use runs at two loads)"


EFFECT = Effect(
    name="load_dependent_friction",
    parameters=tuple(f"fl{j}" for j in range(1, 7)),
    units=("1",) * 6,
    seen_in=("runs",),
    explanation="friction grows with the load the gear carries",
    evidence="the UV/VU current difference grows with the load",
    static_refusal=_refusal,
    static_model="none: static readings are taken at rest",
    run_model="xi i = tau_load - fl_j abs(tau_load_j) sign(dq_j)",
    run_part="uv/vu",
    plausibility=lambda names, values, stds: wrong_sign(names, values, stds, "load-dependent friction"),
    run_column=lambda speed, load: np.abs(load),
    run_needs="runs under two or more loads",
)
