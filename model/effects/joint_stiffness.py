"""joint_stiffness: one torsion spring per joint (always in the model).

Parameters k1..k6 [N·m/rad]; the fit works in compliance c = 1/k, in which the
model is linear: dtheta_j = c_j tau_j (Y39-42 with currents, Y35 with forces).
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Compensation, Effect, StaticBasis, StaticContext, diagonal_basis
from elastocal.model.effects.base import joint_names, joint_units


def _basis(ctx: StaticContext) -> StaticBasis:
    return StaticBasis(theta=diagonal_basis(ctx.tau))


def _report(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return 1.0 / c, -1.0 / c**2


def _absolute_only_refusal(robot, ds) -> str | None:
    """A table without loads shows the twist under the robot's own weight: its torques need the masses."""
    if not robot.has_masses:
        return "needs the link masses (mass and com per [[joint]]): the torques are the robot's own weight"
    return None


def make(robot=None) -> Effect:
    """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
    return Effect(
        name="joint_stiffness",
        parameters=joint_names("c", robot),
        units=joint_units("rad/(N*m)", "m/N", robot),
        seen_in=("static", "runs"),
        explanation="each joint twists like a torsion spring under the torque it carries",
        evidence="deflection proportional to the joint torques",
        static_basis=_basis,
        report=_report,
        report_units=joint_units("N*m/rad", "N/m", robot),
        static_model="each joint angle gains c_j tau_j, tau from the currents (xi i) or from J_f^T W",
        sized=make,
        run_model="the joint torques of a slow motion are the load torques the springs carry; "
                  "k enters the run model only through the deflected configuration",
        report_names=joint_names("k", robot),
        self_weight=True,
        absolute_only_refusal=_absolute_only_refusal,
        compensation=Compensation.MODELLED,
    )


EFFECT = make()
