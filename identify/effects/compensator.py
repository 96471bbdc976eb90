"""compensator: the gravity compensator on joint 2 (Y5-12, K4-9).

Parameters ``C`` [N·m] and ``l_c`` [m] for a hydro-pneumatic compensator, or
``K_c`` [N/m] and ``s0`` [m] for a spring one (robot.toml ``[compensator]``).
Run model: joint 2 carries ``xi2 i2 = tau2_load - M(q2)``, the balancing torque
M of the compensator's geometry, identified from joint-2 currents over a slow
sweep run forward and backward (friction cancels in the mean); see
identify/compensator.py. Static before/after-load differences cannot separate
it: its torque cancels between the two readings and its stiffness
``k_b = dM/dq2`` is small next to k2.
"""

from __future__ import annotations

from elastocal.identify.effects.base import Effect, StaticContext


def _refusal(ctx: StaticContext) -> str:
    return ("static differences do not separate the compensator from k2; identify C, l_c "
            "(or K_c, s0) from a joint-2 sweep in the run table")


EFFECT = Effect(
    name="compensator",
    parameters=("C", "l_c"),
    units=("N*m", "m"),
    seen_in=("runs",),
    explanation="the gravity compensator on joint 2 pushes with a force that changes with q2",
    evidence="joint-2 torque residual that follows q2",
    static_refusal=_refusal,
    static_model="none: its torque cancels in before/after-load differences",
    run_model="xi2 i2 = tau2_load - M(q2; C, l_c) over a joint-2 sweep, UV and VU averaged",
    run_part="sweep",
)
