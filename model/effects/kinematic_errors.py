"""kinematic_errors: the real link lengths, twists and joint zeros differ from the drawing.

Parameters (identify/kinematics.py): per joint the zero ``dq<i>`` [rad], the
length ``da<i>`` and offset ``dd<i>`` [m], the twist ``dalpha<i>`` [rad], and
Hayati's tilt ``dbeta<i>`` [rad] where axes ``i-1`` and ``i`` are parallel, the
error ``dtheta<i>`` [rad] of a prismatic joint's fixed theta (a turn about its axis); the
marker positions ``dx_<m>, dy_<m>, dz_<m>`` [m]. The fit keeps the identifiable
set (a QR of the stacked regressor) and reports the rest as absorbed.

They move absolute positions by millimetres but change a deflection only by the
same small fraction as the geometry, so the deflection fit (identify/static.py)
refuses them and the absolute fit (identify/absolute.py) identifies them, with
the tracker registration and the elastic model.
"""

from __future__ import annotations

from elastocal.model.effects.base import Compensation, Effect, StaticContext


def _refusal(ctx: StaticContext) -> str:
    return ("deflections barely show geometric errors; the absolute fit identifies them from the absolute "
            "positions (a model with kinematic_errors and tracker_frame)")


EFFECT = Effect(
    name="kinematic_errors",
    parameters=(),
    units=(),
    seen_in=("static", "runs"),
    absolute_only=True,
    explanation="joint zeros, link lengths and twists differ from the drawing",
    evidence="absolute position errors of millimetres that follow the pose while the deflections fit",
    static_refusal=_refusal,
    static_model="absolute positions: FK on the robot rebuilt from the corrected DH table; deflections: none "
                 "(first order in the geometry, below the noise)",
    run_model="tracked absolute positions from the corrected DH table",
    geometry=True,
    fitted_with=("tracker_frame",),
    absolute_only_refusal=lambda robot, ds: None,
    compensation=Compensation.MODELLED,
)
