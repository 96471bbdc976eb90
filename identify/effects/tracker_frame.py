"""tracker_frame: error in the registration of the tracker frame to the base.

Parameters rx, ry, rz [rad] and tx, ty, tz [m]: a small rigid motion between
the tracker's measurement frame and the robot base frame. It moves absolute
positions; a translation cancels in deflections and a rotation of a few
milliradians turns a deflection by as little, so only runs with absolute
positions show it.
"""

from __future__ import annotations

from elastocal.identify.effects.base import Effect, StaticContext


def _refusal(ctx: StaticContext) -> str:
    return "a rigid registration error cancels in deflections; it needs absolute positions"


EFFECT = Effect(
    name="tracker_frame",
    parameters=("rx", "ry", "rz", "tx", "ty", "tz"),
    units=("rad",) * 3 + ("m",) * 3,
    seen_in=("runs",),
    explanation="the tracker frame is registered to the robot base with an error",
    evidence="absolute positions off by a rigid motion",
    static_refusal=_refusal,
    static_model="none: cancels in deflections",
    run_model="tracked absolute positions p = R(r) p_model + t",
)
