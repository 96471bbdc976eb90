"""Compensated joint trajectories (Yang §6, and exact).

Given a planned joint path ``q(s)`` and the process wrench ``W(s)`` on the load
point, find commands ``q_c(s)`` that put the tool where the plan puts it.

Which pose is "the plan" (``reference``):

* ``"unloaded"`` (default): the pose the robot reaches running ``q`` *without*
  the process load. The controller's own kinematics (or the teach-in, or a
  geometric calibration) is taken to be right at the unloaded state, gravity
  sag included; elastocal removes what the process load adds. The deflection
  to remove is the difference of the full static model between the
  process-loaded and the unloaded state: ``c ⊙ (tau(theta, W) - tau(theta_0, 0))``
  with ``tau = J^T W - g - M e2``.
* ``"rigid"``: the pose of the rigid kinematic model at ``q + offset``: gravity
  and compensator deflection are removed as well (a controller that knows
  nothing of its own sag).

Forms:

* ``"first-order"`` (Yang): ``q_c = q - dtheta`` with ``dtheta`` evaluated at
  the planned configuration, ``c ⊙ J(q)^T W`` (unloaded reference) or
  ``c ⊙ tau(q, W)`` (rigid reference).
* ``"exact"``: the command whose loaded equilibrium *is* the target
  configuration ``theta*`` (unloaded equilibrium at ``q``, found by fixed-point
  iteration, or ``q + offset``). With joint springs the pose matches exactly
  when the link angles do, so the command is explicit once ``theta*`` is known:
  ``q_c = theta* - offset - c ⊙ tau(theta*, W)``.

* ``"nominal"`` (a calibration with ``kinematic_errors``, RoboDK's "filter
  program"): the pose the drawing's robot gives the tool at ``q + offset``; the
  target is the configuration at which the *calibrated* robot's tool frame has
  that pose (Newton on SE(3)), and the command puts the loaded, calibrated
  robot there: geometry, gravity sag and process load all compensated. The
  default when the model carries a geometric calibration.

With the rigid reference both forms coincide for a joint-spring model.
:func:`predicted_residual` solves the loaded equilibrium at the commands to
check what is left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.compensation.model import CompensationModel, StaticKernel
from elastocal.errors import InputError
from elastocal.model.kinds import KinematicForm, expect

REFERENCES = ("unloaded", "rigid", "nominal")


@dataclass(frozen=True, eq=False)
class CompensatedPath:
    """A compensated joint path."""

    form: KinematicForm
    reference: str
    q_planned: np.ndarray       # (n, N) [rad; m for a prismatic joint]
    wrench: np.ndarray          # (n, 6) process wrench on the load point [N, N·m]
    q_command: np.ndarray       # (n, N) compensated commands [rad; m]
    theta_target: np.ndarray    # (n, N) link coordinates the plan asks for [rad; m]
    tcp_deflection: np.ndarray  # (n, 3) predicted load-point deflection before compensation [m]
    #: which joints are prismatic (their coordinates in metres); () for six revolute joints
    prismatic: tuple[bool, ...] = ()

    def __post_init__(self) -> None:
        expect(KinematicForm, self.form, "form")

    @property
    def dtheta(self) -> np.ndarray:
        """Correction ``q_planned - q_command`` (n, N) [rad; m]."""
        return self.q_planned - self.q_command

    def __len__(self) -> int:
        return len(self.q_planned)


def _check_inputs(model: CompensationModel, q: np.ndarray, wrench: np.ndarray, form: KinematicForm,
                  reference: str) -> tuple[np.ndarray, np.ndarray]:
    expect(KinematicForm, form, "form")
    if reference not in REFERENCES:
        raise InputError(f"reference must be one of {', '.join(REFERENCES)}, got {reference!r}",
                         argument="reference")
    q = np.asarray(q, dtype=float)
    n_joints = model.robot.n_joints
    if q.ndim != 2 or q.shape[1] != n_joints:
        raise ValueError(f"q must be (n, {n_joints})")
    w = np.asarray(wrench, dtype=float)
    if w.shape == (6,):
        w = np.tile(w, (len(q), 1))
    if w.shape != (len(q), 6):
        raise ValueError("wrench must be (6,) or (n, 6)")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(w))):
        raise InputError("path and wrench must be finite")
    return q, w


def _prismatic(model: CompensationModel) -> tuple[bool, ...]:
    flags = tuple(bool(p) for p in model.robot.prismatic)
    return flags if any(flags) else ()


def default_reference(model: CompensationModel) -> str:
    """``nominal`` for a geometrically calibrated model, else ``unloaded``."""
    return "nominal" if model.nominal is not None else "unloaded"


def compensate_path(model: CompensationModel, q: np.ndarray, wrench: np.ndarray, *,
                    form: KinematicForm = KinematicForm.EXACT, reference: str | None = None) -> CompensatedPath:
    """Compensated commands for the planned path ``q`` (n, 6) under ``wrench``
    ((6,) constant or (n, 6) per sample). The predicted deflection is the exact
    one (loaded equilibrium) for ``KinematicForm.EXACT`` and ``J dtheta`` for
    ``KinematicForm.FIRST_ORDER``."""
    reference = default_reference(model) if reference is None else reference
    q, w = _check_inputs(model, q, wrench, form, reference)
    k = StaticKernel(model)
    base = k.base_angles(q)               # cos/sin of the planned angles, once for the path
    plan = q + k.offsets
    if reference == "nominal":
        target = k.nominal_targets(q)
        # first order: the torques at the planned configuration (Yang); exact: at the target
        cmd = target - k.offsets - k.c * k.torque(plan if form == KinematicForm.FIRST_ORDER else target, w, base)
        theta_loaded = k.equilibrium(q, w, start=target + (q - cmd), base=base)
        deflection = k.positions(theta_loaded, base) - k.positions(target, base)
        return CompensatedPath(form=form, reference=reference, q_planned=q, wrench=w, q_command=cmd,
                               theta_target=target, tcp_deflection=deflection, prismatic=_prismatic(model))
    target = k.equilibrium(q, np.zeros_like(w), base=base) if reference == "unloaded" else plan
    if form == KinematicForm.FIRST_ORDER:
        # one pass at the planned angles: c ⊙ J^T W (unloaded) or c ⊙ tau(q, W) (rigid), and J_p dtheta
        dtheta, deflection = k.first_order(base, w, passive=reference == "rigid")
        cmd = q - dtheta
    else:
        tau, at_target = k.torque(target, w, base, with_positions=True)
        cmd = target - k.offsets - k.c * tau
        theta_loaded = k.equilibrium(q, w, start=target + (q - cmd), base=base)
        deflection = k.positions(theta_loaded, base) - at_target
    return CompensatedPath(form=form, reference=reference, q_planned=q, wrench=w, q_command=cmd,
                           theta_target=target, tcp_deflection=deflection, prismatic=_prismatic(model))


def predicted_residual(model: CompensationModel, path: CompensatedPath) -> np.ndarray:
    """Load-point deviation from the target (n, 3) [m] the model predicts when the
    compensated commands run under the process wrench."""
    k = StaticKernel(model)
    base = k.base_angles(path.q_command)
    theta = k.equilibrium(path.q_command, path.wrench, start=path.theta_target, base=base)
    return k.positions(theta, base) - k.positions(path.theta_target, base)
