"""tracker_frame: the registration of the tracker frame to the robot base.

Parameters rx, ry, rz [rad] (the rotation vector of R) and tx, ty, tz [m]:
``p_tracker = R p_base + t``, the tracker standing anywhere in the cell
(docs/formats.md §2). Every absolute comparison registers the tracker (a closed-form
rigid fit of the model's predictions, identify/registration.py); as an effect,
the registration is identified with the rest of the model by the absolute fit
(identify/absolute.py), with standard deviations. A translation cancels in
deflections and the rotation is turned back before the deflection fit, so the
deflection fit refuses it.
"""

from __future__ import annotations

from elastocal.model.effects.base import Compensation, Effect, StaticContext


def _refusal(ctx: StaticContext) -> str:
    return ("a rigid registration cancels in deflections; the absolute fit identifies it from the absolute "
            "positions")


EFFECT = Effect(
    name="tracker_frame",
    parameters=("rx", "ry", "rz", "tx", "ty", "tz"),
    units=("rad",) * 3 + ("m",) * 3,
    seen_in=("static", "runs"),
    absolute_only=True,
    explanation="the tracker's placement relative to the robot base, identified with the rest of the model",
    evidence="absolute positions off by a rigid motion",
    static_refusal=_refusal,
    static_model="absolute positions: p_tracker = R p_base + t; deflections: turned back by R",
    run_model="tracked absolute positions p = R p_model + t",
    registration=True,
    session=True,
    compensation=Compensation.NO_PATH_DEFLECTION,
)
