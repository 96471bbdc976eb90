"""viscous_friction: friction grows with speed.

Parameters fv1..fv6 [N*m*s/rad]; this law's part of the run model is ``fv_j dq_j``
(the friction laws' common model: model/effects/_friction.py).
"""

from __future__ import annotations

from elastocal.model.effects._friction import friction_law

make = friction_law(
    name="viscous_friction", prefix="fv", units=("N*m*s/rad", "N*s/m"),
    explanation="friction grows with speed",
    evidence="the UV/VU current difference grows with speed",
    part="fv_j dq_j", column=lambda speed, load: speed,
    needs="runs at two or more speeds", use="runs at two speeds",
    words="viscous friction",
)

EFFECT = make()
