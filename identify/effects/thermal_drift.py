"""thermal_drift: tracker readings drift linearly with time.

Parameters vx, vy, vz [m/s]; deflection d gains v * (t_loaded - t_reference).
Needs the time column of the static table.
"""

from __future__ import annotations

import numpy as np

from elastocal.identify.effects.base import Effect, StaticBasis, StaticContext


def _basis(ctx: StaticContext) -> StaticBasis:
    add = np.zeros((ctx.n_deflections, 3, 3))
    for axis in range(3):
        add[:, axis, axis] = ctx.deflection_dt
    return StaticBasis(add=add)


def _refusal(ctx: StaticContext) -> str | None:
    if not np.all(np.isfinite(ctx.deflection_dt)):
        return "the static table has no times (column t), so a drift with time cannot be seen"
    if np.ptp(ctx.deflection_dt) == 0.0 and np.all(ctx.deflection_dt == 0.0):
        return "loaded and reference readings were taken at the same times"
    return None


EFFECT = Effect(
    name="thermal_drift",
    parameters=("vx", "vy", "vz"),
    units=("m/s",) * 3,
    seen_in=("static", "runs"),
    explanation="the tracker's readings creep with time as the room or the robot warms up",
    evidence="deflections grow with the time between the reference and the loaded readings",
    static_basis=_basis,
    static_refusal=_refusal,
)
