"""The simulated cell's own physics: joint torques, friction and the compensator, any N-joint robot.

The simulator is a witness of the identification only if it computes the physics
another way (docs/physics.md). It reads the robot description (the Pinocchio
models the bottom layer builds from it) and computes, here, with Pinocchio's own
algorithms and none of the physics methods the fits use:

* **gravity**: ``pin.rnea(model, data, theta, 0, 0)``, the effort that holds the
  links at rest (inverse dynamics at zero velocity and acceleration);
* **the external wrench** on the load point through the frame Jacobian,
  ``J(theta)^T W`` (``pin.computeFrameJacobian``, LOCAL_WORLD_ALIGNED: force and
  moment in base axes, about the load point);
* **the compensator** from its geometry: two pivots, one fixed to the parent
  link and one turning with the compensated joint, a tension ``F`` along the line
  between them (hydro-pneumatic ``F = C / (l_c - l)``, spring ``F = K_c (s - s0)``),
  and its torque about the joint axis as the cross product of the lever and the
  force (:func:`compensator_effort`);
* **friction** during motion from the motor's torque balance: the drive supplies
  it in the direction of motion, ``fc sign(dq) + fv dq + fl |tau_load| sign(dq)``
  (:func:`friction_effort`).

The load effort a joint carries at rest is ``tau_load = J^T W - g(theta) + Q_c``
(``Q_c`` the compensator's generalised force on its joint), the torque its gear
and spring hold: ``xi i = tau_load`` at rest, ``xi i = tau_load + friction`` in
motion. :func:`solve_equilibrium` finds the deflected configuration where each
spring's twist matches the torque it carries, by its own fixed-point iteration.
Every function takes the Pinocchio Data of its computation (each computation
owns its Data) or makes one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import pinocchio as pin

from elastocal.model.compensator import CompensatorSpec
from elastocal.model.kinds import CompensatorKind
from elastocal.model.robot import LOAD_FRAME, MARKER_PREFIX, Robot


def _frame(model: pin.Model, name: str) -> int:
    full = name if name in (LOAD_FRAME, "flange") else MARKER_PREFIX + name
    if not model.existFrame(full):
        raise ValueError(f"the robot has no frame {name!r}")
    return model.getFrameId(full)


# ------------------------------------------------------------------ efforts
def gravity_effort(model: pin.Model, data: pin.Data, theta: np.ndarray) -> np.ndarray:
    """Effort (nv,) that holds the links against gravity at rest: inverse dynamics at zero
    velocity and acceleration, ``pin.rnea(theta, 0, 0)``."""
    zero = np.zeros(model.nv)
    return np.array(pin.rnea(model, data, np.asarray(theta, dtype=float), zero, zero))


def external_effort(model: pin.Model, data: pin.Data, theta: np.ndarray, wrench: np.ndarray,
                    frame: str = LOAD_FRAME) -> np.ndarray:
    """Generalised force (nv,) of the wrench ``(fx, fy, fz, mx, my, mz)`` [N, N·m], base axes,
    acting at ``frame``'s origin: ``J^T W`` with the frame Jacobian in LOCAL_WORLD_ALIGNED."""
    w = np.asarray(wrench, dtype=float)
    if not np.any(w):
        return np.zeros(model.nv)
    fid = _frame(model, frame)
    jac = pin.computeFrameJacobian(model, data, np.asarray(theta, dtype=float), fid, pin.LOCAL_WORLD_ALIGNED)
    return jac.T @ w


@dataclass(frozen=True)
class Pivots:
    """The compensator's two pivots in the plane normal to its joint's axis, origin on
    the axis [m]: ``fixed`` on the parent link, ``moving`` at joint coordinate 0 (it turns
    with the joint)."""

    fixed: np.ndarray
    moving: np.ndarray

    def at(self, q: float) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(q), math.sin(q)
        return self.fixed, np.array([c * self.moving[0] - s * self.moving[1], s * self.moving[0] + c * self.moving[1]])


def compensator_pivots(spec: CompensatorSpec) -> Pivots:
    """Where the pivots are, from the description's geometry.

    Hydro-pneumatic (Yang Fig. 2): the cylinder's fixed pivot at ``(h, a)`` from the
    joint axis — distance ``sqrt(a^2 + h^2)`` at angle ``alpha = atan(a/h)`` — and the rod's
    pivot on the arm at distance ``b``, along the arm's normal at q = 0. Spring (Klimchik
    Fig. 3): the fixed pivot at distance ``a``, the moving one at ``L``, ``alpha`` apart
    at q = 0 measured from the far side. Each places the pivots so that the pivot
    distance is the length the papers write (Y6, K4)."""
    if spec.kind is CompensatorKind.HYDROPNEUMATIC:
        a, b, h = spec.geo("a"), spec.geo("b"), spec.geo("h")
        r = math.hypot(a, h)
        alpha = math.atan2(a, h)
        phi = math.pi / 2.0 - alpha          # angle of the moving pivot from the fixed one at q = 0
        return Pivots(np.array([r, 0.0]), b * np.array([math.cos(phi), math.sin(phi)]))
    a, big_l, alpha = spec.geo("a"), spec.geo("L"), spec.geo("alpha")
    phi = math.pi - alpha
    return Pivots(np.array([a, 0.0]), big_l * np.array([math.cos(phi), math.sin(phi)]))


def compensator_tension(spec: CompensatorSpec, length_m: float, params: Sequence[float]) -> float:
    """Tension [N] between the pivots at pivot distance ``length_m``: the pull-type
    hydro-pneumatic balancer's gas, compressed as the rod comes out, ``C / (l_c - l)``;
    the spring's ``K_c (s - s0)``."""
    p0, p1 = float(params[0]), float(params[1])
    if spec.kind is CompensatorKind.HYDROPNEUMATIC:
        return p0 / (p1 - length_m)
    return p0 * (length_m - p1)


def compensator_effort(spec: CompensatorSpec, q: float, params: Sequence[float]) -> float:
    """Torque [N·m] the compensator puts on its joint, in the joint's positive sense, at
    joint coordinate ``q`` (without offset): the moment about the axis of the tension
    acting on the moving pivot, ``(B x F_B)_z`` with ``F_B = -F (B - A) / |B - A|``."""
    fixed, moving = compensator_pivots(spec).at(float(q))
    d = moving - fixed
    length = float(np.hypot(d[0], d[1]))
    force = -compensator_tension(spec, length, params) * d / length
    return float(moving[0] * force[1] - moving[1] * force[0])


def friction_effort(dq: np.ndarray, load_torque: np.ndarray, coulomb: np.ndarray, viscous: np.ndarray,
                    load_dependent: np.ndarray) -> np.ndarray:
    """Friction torque the drive supplies on top of the load during a motion at ``dq``:
    friction resists the motion, so the motor overcomes it in the direction of motion,
    ``fc sign(dq) + fv dq + fl |tau_load| sign(dq)`` (all coefficients >= 0)."""
    dq = np.asarray(dq, dtype=float)
    s = np.sign(dq)
    return np.asarray(coulomb) * s + np.asarray(viscous) * dq + np.asarray(load_dependent) * np.abs(load_torque) * s


# ------------------------------------------------------------------ statics
@dataclass(frozen=True, eq=False)
class Loads:
    """What loads a robot's link model at rest: the wrench on the load point and the
    compensator's parameters (None: none fitted to this robot)."""

    wrench: np.ndarray
    compensator: tuple[float, float] | None = None


def load_effort(robot: Robot, data: pin.Data, theta_links: np.ndarray, loads: Loads) -> np.ndarray:
    """Load effort (link_model.nv,) each joint of ``robot.link_model`` carries at rest,
    ``J^T W - g(theta) + Q_c`` (module docstring)."""
    model = robot.link_model
    theta_links = np.asarray(theta_links, dtype=float)
    tau = external_effort(model, data, theta_links, loads.wrench) - gravity_effort(model, data, theta_links)
    spec = robot.compensator
    if spec is not None and loads.compensator is not None:
        idx = int(robot.actuated_in_link_model[spec.index])
        tau[idx] += compensator_effort(spec, theta_links[idx] - robot.joints[spec.index].offset, loads.compensator)
    return tau


@dataclass(frozen=True, eq=False)
class Springs:
    """The springs of a simulated robot: ``twist(torque)`` of the N joint springs [rad, m]
    and the compliance of the link model's passive springs [rad/(N·m)]."""

    twist: Callable[[np.ndarray], np.ndarray]
    link_compliance: np.ndarray


def linear_springs(stiffness: Sequence[float], link_compliance: Sequence[float] | None = None,
                   n_link_springs: int = 0) -> Springs:
    """Joint springs ``tau / k`` and link springs of the given compliance (zero when None)."""
    k = np.asarray(stiffness, dtype=float)
    cl = np.zeros(n_link_springs) if link_compliance is None else np.asarray(link_compliance, dtype=float)
    return Springs(twist=lambda tau: np.asarray(tau) / k, link_compliance=cl)


@dataclass(frozen=True)
class Statics:
    """A solved equilibrium: the link model's configuration and what the springs carry."""

    theta_links: np.ndarray     # (link_model.nq,) the deflected configuration
    theta: np.ndarray           # (N,) link-side joint variables
    link_angles: np.ndarray     # the passive springs' angles
    load: np.ndarray            # (link_model.nv,) load effort at the solution
    gear_torque: np.ndarray     # (N,) torque each joint's gear and spring carry (xi i at rest)
    iterations: int


def solve_equilibrium(robot: Robot, theta_rigid: np.ndarray, loads: Loads, springs: Springs, *,
                      absorbed: np.ndarray | None = None, data: pin.Data | None = None,
                      tol_rad: float = 1e-13, max_iter: int = 200) -> Statics:
    """Deflected configuration at the rigid joint variables ``theta_rigid`` (N,): each
    joint spring twists by ``springs.twist(tau_gear)``, each passive link spring by
    ``c * tau``, with ``tau`` the load effort at the deflected configuration (fixed point,
    a contraction while the deflections are small next to the lever arms). ``absorbed``
    (N,) is torque that does not reach the gear (static friction), subtracted first."""
    data = robot.link_model.createData() if data is None else data
    act = robot.actuated_in_link_model
    springs_idx = robot.springs_in_link_model
    theta_rigid = np.asarray(theta_rigid, dtype=float)
    held = np.zeros(len(act)) if absorbed is None else np.asarray(absorbed, dtype=float)
    th = np.zeros(robot.link_model.nq)
    th[act] = theta_rigid
    k = 0
    for k in range(1, max_iter + 1):
        load = load_effort(robot, data, th, loads)
        new = th.copy()
        new[act] = theta_rigid + springs.twist(load[act] - held)
        if len(springs_idx):
            new[springs_idx] = springs.link_compliance * load[springs_idx]
        step = float(np.max(np.abs(new - th)))
        th = new
        if step < tol_rad:
            break
    load = load_effort(robot, data, th, loads)
    return Statics(theta_links=th, theta=th[act].copy(), link_angles=th[springs_idx].copy(), load=load,
                   gear_torque=load[act] - held, iterations=k)


def frame_positions(robot: Robot, data: pin.Data, theta_links: np.ndarray, frames: Sequence[str]) -> np.ndarray:
    """Base-frame positions (len(frames), 3) of markers or the load point on the link model."""
    model = robot.link_model
    pin.framesForwardKinematics(model, data, np.asarray(theta_links, dtype=float))
    return np.array([data.oMf[_frame(model, f)].translation for f in frames])
