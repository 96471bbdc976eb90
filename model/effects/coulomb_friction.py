"""coulomb_friction: friction of constant size opposes every motion.

Parameters fc1..fc6 [N*m]; this law's part of the run model is ``fc_j sign(dq_j)``
(the friction laws' common model: model/effects/_friction.py).
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects._friction import friction_law

make = friction_law(
    name="coulomb_friction", prefix="fc", units=("N*m", "N"),
    explanation="friction of constant size opposes every motion",
    evidence="UV and VU currents differ by a constant",
    part="fc_j sign(dq_j)", column=lambda speed, load: np.ones_like(speed),
    needs="UV/VU runs", use="UV/VU runs",
    words="friction",
)

EFFECT = make()
