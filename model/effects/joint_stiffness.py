"""joint_stiffness: one torsion spring per joint (always in the model).

Parameters k1..k6 [N·m/rad]; the fit works in compliance c = 1/k, in which the
model is linear: dtheta_j = c_j tau_j (Y39-42 with currents, Y35 with forces).
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Effect, StaticBasis, StaticContext, diagonal_basis


def _basis(ctx: StaticContext) -> StaticBasis:
    return StaticBasis(theta=diagonal_basis(ctx.tau))


def _report(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return 1.0 / c, -1.0 / c**2


EFFECT = Effect(
    name="joint_stiffness",
    parameters=tuple(f"c{j}" for j in range(1, 7)),
    units=("rad/(N*m)",) * 6,
    seen_in=("static", "runs"),
    explanation="each joint twists like a torsion spring under the torque it carries",
    evidence="deflection proportional to the joint torques",
    static_basis=_basis,
    report=_report,
    report_units=("N*m/rad",) * 6,
    static_model="each joint angle gains c_j tau_j, tau from the currents (xi i) or from J_f^T W",
    run_model="the joint torques of a slow motion are the load torques the springs carry; "
              "k enters the run model only through the deflected configuration",
)
