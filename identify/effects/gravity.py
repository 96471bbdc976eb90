"""gravity: corrections to the links' mass moments in the joint torques.

The run model always holds the gravity of the links from the robot
description's masses; this effect identifies corrections to the mass moments
``m_i c_i`` [kg·m] of links 2..6 from joint torques over many postures (a
linear regressor from Pinocchio's gravity). Static before/after-load
differences cancel gravity, so static data cannot show it.
"""

from __future__ import annotations

from elastocal.identify.effects.base import Effect, StaticContext


def _refusal(ctx: StaticContext) -> str:
    return "gravity cancels in before/after-load differences; it shows in run torques"


EFFECT = Effect(
    name="gravity",
    parameters=("mass moments",),
    units=("kg*m",),
    seen_in=("runs",),
    explanation="the weight of the links loads the joints",
    evidence="torque residual that follows the arm's posture",
    static_refusal=_refusal,
    static_model="none: gravity cancels in before/after-load differences",
    run_model="xi i gains -dg(q): the gravity torque of corrected link mass moments",
    run_part="sweep",
)
