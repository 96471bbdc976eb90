"""load_dependent_friction: friction grows with the load the gear carries.

Parameters fl1..fl6 [1]; this law's part of the run model is
``fl_j abs(tau_load_j) sign(dq_j)`` (the friction laws' common model:
model/effects/_friction.py).
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects._friction import friction_law

make = friction_law(
    name="load_dependent_friction", prefix="fl", units=("1", "1"),
    explanation="friction grows with the load the gear carries",
    evidence="the UV/VU current difference grows with the load",
    part="fl_j abs(tau_load_j) sign(dq_j)", column=lambda speed, load: np.abs(load),
    needs="runs under two or more loads", use="runs at two loads",
    words="load-dependent friction",
)

EFFECT = make()
