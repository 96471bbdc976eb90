"""kinematic_errors: joint offsets and link lengths differ from the drawing.

Parameters: joint offsets [rad] and link lengths [m] of the DH table (geometric
calibration). They change absolute positions by millimetres but deflections only
by the same small fraction as the geometry, so only runs with absolute
positions show them.
"""

from __future__ import annotations

from elastocal.identify.effects.base import Effect, StaticContext


def _refusal(ctx: StaticContext) -> str:
    return "geometric errors barely change deflections; they need absolute positions"


EFFECT = Effect(
    name="kinematic_errors",
    parameters=("joint offsets", "link lengths"),
    units=("rad", "m"),
    seen_in=("runs",),
    explanation="the real link lengths and joint zeros differ from the drawing",
    evidence="absolute position errors that follow the pose",
    static_refusal=_refusal,
    static_model="none: first order in the deflection, below the noise",
    run_model="tracked absolute positions from the DH table with corrected offsets and lengths",
)
