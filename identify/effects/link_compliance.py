"""link_compliance: torsion and bending at the distal ends of links 2 and 3.

Parameters cl2x, cl2y, cl3x, cl3y [rad/(N·m)]: rotations about x and y of the
frame at the distal end of link 2 (the joint-3 axis frame) and of link 3 (the
wrist centre), proportional to the moment the load puts there. The moments come
from the external wrench; with currents the wrench is recovered from the joint
torques, W = J_f^{-T} Gamma (docs/physics.md), so both torque sources can show it.
"""

from __future__ import annotations

import numpy as np

from elastocal.identify.effects.base import (
    Effect,
    StaticBasis,
    StaticContext,
    diagonal_basis,
    strongest,
    wrong_sign,
)
from elastocal.identify.robot import LINK_SPRINGS


def _basis(ctx: StaticContext) -> StaticBasis:
    return StaticBasis(links=diagonal_basis(ctx.delta_link_moment))


_WORDS = {"cl2x": "torsion load on link 2", "cl2y": "bending load on link 2",
          "cl3x": "torsion load on link 3", "cl3y": "bending load on link 3"}


def _describe(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str:
    k = strongest(names, values, stds)
    return (f"lateral deflection follows the {_WORDS.get(names[k], names[k])} "
            f"({names[k]} = {values[k]:.3g} rad/(N*m), {abs(values[k]) / stds[k]:.0f} std)")


def _plausibility(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str | None:
    return wrong_sign(names, values, stds, "a compliance")


EFFECT = Effect(
    name="link_compliance",
    parameters=LINK_SPRINGS,
    units=("rad/(N*m)",) * 4,
    seen_in=("static",),
    explanation="the arm links bend and twist, which no joint spring can mimic",
    evidence="lateral deflection follows the torsion and bending moments on links 2 and 3",
    static_basis=_basis,
    describe=_describe,
    plausibility=_plausibility,
    static_model="two extra rotations (about x and y) at the ends of links 2 and 3, "
                 "cl times the moment of the load change there",
    run_model="not in the torque model: link springs change positions, not joint torques",
)
