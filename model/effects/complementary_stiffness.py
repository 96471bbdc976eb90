"""complementary_stiffness: a loaded chain whose geometry deflects (Y17-18).

``K_c = dJ_f^T/dtheta W``. No parameters: the model evaluates the force-based
torques at the deflected configuration. The exact form always does so, and
currents measure the torques directly, so only the force-based first-order
model can lack it.
"""

from __future__ import annotations

from elastocal.model.effects.base import Effect, StaticContext
from elastocal.model.kinds import KinematicForm, TorqueSource


def _refusal(ctx: StaticContext) -> str | None:
    if ctx.torque_source is not TorqueSource.FORCE:
        return ("currents measure the joint torques of the deflected robot directly; "
                "the current-based model does not need it")
    if ctx.form is KinematicForm.EXACT:
        return "the exact form already evaluates J_f^T W at the deflected configuration"
    return None


EFFECT = Effect(
    name="complementary_stiffness",
    parameters=(),
    units=(),
    seen_in=("static",),
    explanation="a heavily loaded arm's geometry shifts, so the same force gives other joint torques",
    evidence="force-based residual that grows with load outside the good (q2, q3) region",
    static_refusal=_refusal,
    torque_at_deflection=True,
    static_model="force-based torques J_f(theta)^T W - g(theta) evaluated at the deflected configuration "
                 "(first order: K = K_theta - K_c)",
    run_model="not in the torque model",
)
