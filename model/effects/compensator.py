"""compensator: the gravity compensator on joint 2 (Y5-12, K4-9).

Parameters ``C`` [N·m] and ``l_c`` [m] for a hydro-pneumatic compensator, or
``K_c`` [N/m] and ``s0`` [m] for a spring one (robot.toml ``[compensator]``).
Run model: joint 2 carries ``xi2 i2 = tau2_load - M(q2)``, the balancing torque
M of the compensator's geometry, identified from joint-2 currents over a slow
sweep run forward and backward (friction cancels in the mean); its
:class:`SweepTerm` is ``M(q2; C, l_c)`` with its analytic derivatives, the
description's nominal values being the model's compensator when it is not
fitted (identify/sweepfit.py). Static before/after-load differences cannot
separate it: its torque cancels between the two readings and its stiffness
``k_b = dM/dq2`` is small next to k2.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Compensation, Effect, StaticContext, SweepContext, SweepTerm, wrong_sign
from elastocal.model.kinds import CompensatorKind

#: l_c - max(cylinder length) scanned for the hydro-pneumatic start [m]
_GAP_SCAN_M = np.geomspace(1e-3, 5.0, 400)


def _refusal(ctx: StaticContext) -> str:
    spec = ctx.robot.compensator if ctx.robot is not None else None
    j = spec.joint if spec is not None else 2           # the joint the compensator names
    return (f"static differences do not separate the compensator from k{j}; identify C, l_c "
            f"(or K_c, s0) from a joint-{j} sweep in the run table")


def _start(spec, q2: np.ndarray):
    """Starting parameters: exact linear least squares for the spring; a scan of l_c
    with C linear for the hydro-pneumatic compensator (with the other linear columns)."""

    def start(y: np.ndarray, other: np.ndarray) -> np.ndarray:
        if spec.kind is CompensatorKind.SPRING:
            a, big_l, alpha = spec.geo("a"), spec.geo("L"), spec.geo("alpha")
            g = a * big_l * np.sin(alpha - q2)
            x = np.column_stack([-g, g / spec.spring_length(q2), -other])
            beta, *_ = np.linalg.lstsq(x, y, rcond=None)
            kc = beta[0]
            return np.array([kc, beta[1] / kc if kc != 0 else 0.0])
        l_max = float(np.max(spec.hydro_length(q2)))
        best = (np.inf, None)
        for gap in _GAP_SCAN_M:
            x = np.column_stack([-spec.torque(q2, (1.0, l_max + gap)), -other])
            beta, *_ = np.linalg.lstsq(x, y, rcond=None)
            rss = float(np.sum((y - x @ beta) ** 2))
            if rss < best[0]:
                best = (rss, np.array([beta[0], l_max + gap]))
        return best[1]

    return start


def _sweep_term(ctx: SweepContext) -> SweepTerm | str:
    spec = ctx.robot.compensator
    if spec is None:
        return "the robot description has no [compensator]"
    if spec.index != ctx.joint:
        return (f"the sweeps move joint {ctx.joint + 1}; the compensator acts on joint {spec.joint} "
                f"(sweep joint {spec.joint})")
    q2 = np.asarray(ctx.q2, dtype=float)
    lower = np.full(2, -np.inf)
    if spec.kind is CompensatorKind.HYDROPNEUMATIC:       # the cylinder's gas volume: l_c beyond its longest stroke
        lower[1] = float(np.max(spec.hydro_length(q2))) + 1e-6
    return SweepTerm(names=spec.parameter_names, units=tuple(spec.parameter_units[n] for n in spec.parameter_names),
                     torque=lambda p: spec.torque(q2, p), jacobian=lambda p: spec.torque_derivatives(q2, p),
                     start=_start(spec, q2), lower=lower, nominal=spec.nominal_parameters())


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
    sweep_term=_sweep_term,
    plausibility=lambda names, values, stds: wrong_sign(names, values, stds, "a compensator force or length"),
    compensation=Compensation.MODELLED,
)
