"""backlash: lost motion when a joint's torque changes sign.

Parameters b1..b6 [rad], the total play of each joint. The play is taken up
over a small torque band: the joint angle gains (b/2) tanh(tau / TAU_BAND_NM).
Static data show it only where a load state reverses a joint's torque.
"""

from __future__ import annotations

import numpy as np

from elastocal.identify.effects.base import Effect, StaticBasis, StaticContext, diagonal_basis

#: torque over which the play is taken up [N·m]
TAU_BAND_NM = 20.0


def _basis(ctx: StaticContext) -> StaticBasis:
    return StaticBasis(theta=diagonal_basis(0.5 * np.tanh(ctx.tau / TAU_BAND_NM)))


EFFECT = Effect(
    name="backlash",
    parameters=tuple(f"b{j}" for j in range(1, 7)),
    units=("rad",) * 6,
    seen_in=("static", "runs"),
    explanation="a gear has play that shows as a jump when the torque on the joint reverses",
    evidence="a step in deflection when a load reverses the torque of a joint",
    static_basis=_basis,
)
