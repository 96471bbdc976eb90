"""Inverse kinematics of the rigid model: closed-loop IK with damped least squares (Pinocchio).

Used to turn a Cartesian process path (Yang Table 8: a straight line of the
tool point) into the planned joint path that compensation starts from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.robot import LOAD_FRAME, Robot


@dataclass(frozen=True, eq=False)
class PlannedPath:
    """A planned joint path: times, commands and the process wrench per sample."""

    t: np.ndarray        # (n,) [s]
    q: np.ndarray        # (n, 6) [rad]
    wrench: np.ndarray | None = None  # (n, 6) [N, N·m] or None when the path file has none
    line: np.ndarray | None = None    # (n,) line of each sample in the path file (header = 1)

    def __len__(self) -> int:
        return len(self.t)


#: the joints of a six-axis arm; a robot with more has auxiliary joints before it (a track)
ARM_JOINTS = 6


def auxiliary_joints(robot: Robot) -> int:
    """How many joints stand before the six-axis arm (a track's carriage: 1)."""
    return max(robot.n_joints - ARM_JOINTS, 0)


def arm_configuration(robot: Robot, q_arm) -> np.ndarray:
    """The robot's q for the arm's ``q_arm``: auxiliary joints at the middle of their limits."""
    n_aux = auxiliary_joints(robot)
    middle = (robot.lower[:n_aux] + robot.upper[:n_aux]) / 2
    return np.r_[middle, np.asarray(q_arm, dtype=float)]


def solve_ik(robot: Robot, target: pin.SE3, q_start: np.ndarray, *, frame: str = LOAD_FRAME,
             tol: float = 1e-11, max_iter: int = 500, damping: float = 1e-6) -> np.ndarray:
    """Joint coordinates ``q`` that put ``frame`` at ``target`` (base frame).

    CLIK: ``dtheta = J^T (J J^T + damping I)^-1 e`` with ``e = log6(oMf^-1 oMdes)``
    in the frame's local axes, until ``|e| < tol``; the auxiliary joints before a
    six-axis arm (a track) stay where ``q_start`` has them. Raises InputError when it
    does not converge or the solution leaves the joint limits.
    """
    moving = np.arange(auxiliary_joints(robot), robot.n_joints)
    model = robot.model
    data = model.createData()
    fid = robot.frame_id(frame)
    theta = robot.theta(np.asarray(q_start, dtype=float))
    for _ in range(max_iter):
        pin.forwardKinematics(model, data, theta)
        o_m_f = pin.updateFramePlacement(model, data, fid)
        err = pin.log6(o_m_f.actInv(target)).vector
        if np.linalg.norm(err) < tol:
            break
        jac = pin.computeFrameJacobian(model, data, theta, fid, pin.LOCAL)[:, moving]
        step = np.zeros(model.nv)
        step[moving] = jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(6), err)
        theta = pin.integrate(model, theta, step)
    else:
        raise InputError(f"inverse kinematics did not converge for the pose at {target.translation.round(4)}")
    q = theta - robot.offsets
    q_ref = np.asarray(q_start, dtype=float)
    revolute = ~np.asarray(robot.prismatic, dtype=bool)
    q = np.where(revolute, q_ref + (q - q_ref + np.pi) % (2 * np.pi) - np.pi, q)  # the turn nearest the start
    outside = np.flatnonzero((q < robot.lower) | (q > robot.upper))
    if outside.size:
        j = int(outside[0])
        raise InputError(f"the pose at {target.translation.round(4)} needs q{j + 1} = {q[j]:.4f} rad, outside "
                         f"the joint limits [{robot.lower[j]:.4f}, {robot.upper[j]:.4f}]")
    return q


def tool_down_rotation(robot: Robot) -> np.ndarray:
    """Orientation of the load-point frame with the tool pointing down.

    At q = 0 the HH-150's tool points along -x; q5 = -90 degrees turns it to -z.
    """
    q = arm_configuration(robot, [0.0, 0.0, 0.0, 0.0, -np.pi / 2, 0.0])
    model = robot.model
    data = model.createData()
    pin.framesForwardKinematics(model, data, robot.theta(q))
    return data.oMf[robot.frame_id(LOAD_FRAME)].rotation.copy()


def line_path(robot: Robot, start_m, end_m, *, speed_m_s: float, step_m: float,
              rotation: np.ndarray | None = None, q_start: np.ndarray | None = None) -> PlannedPath:
    """Joint path moving the load point along a straight line at constant speed
    and constant orientation (default: tool down)."""
    p0 = np.asarray(start_m, dtype=float)
    p1 = np.asarray(end_m, dtype=float)
    length = float(np.linalg.norm(p1 - p0))
    if length <= 0 or speed_m_s <= 0 or step_m <= 0:
        raise ValueError("the line needs a length, a positive speed and a positive step")
    n = int(np.ceil(length / step_m - 1e-9)) + 1
    s = np.linspace(0.0, 1.0, n)
    rot = tool_down_rotation(robot) if rotation is None else np.asarray(rotation, dtype=float)
    q = arm_configuration(robot, [0.0, 0.5, -0.5, 0.0, -np.pi / 2, 0.0]) if q_start is None \
        else np.asarray(q_start, dtype=float)
    out = np.empty((n, robot.n_joints))
    for i, si in enumerate(s):
        q = solve_ik(robot, pin.SE3(rot, p0 + si * (p1 - p0)), q)
        out[i] = q
    return PlannedPath(t=s * length / speed_m_s, q=out)


#: tilt of the tool from straight down in the Yang validation path [deg]
YANG_TOOL_TILT_DEG = 60.0


def yang_tool_rotation(robot: Robot, tilt_deg: float = YANG_TOOL_TILT_DEG) -> np.ndarray:
    """Tool orientation of the Yang validation path: the tool axis in the x-z
    plane, ``tilt_deg`` from straight down, leaning back toward the robot.

    Straight down is out of reach along that line for the HH-150 model: at
    x = 1.2 m the forearm points almost straight down and, since the tool
    points back along the forearm at q5 = 0, it would need |q5| of about 180
    degrees (limit 120). 60 degrees is the smallest tilt that keeps every joint
    at least 5 degrees inside its limits along the whole line.
    """
    return pin.utils.rotate("y", np.radians(tilt_deg)) @ tool_down_rotation(robot)


def yang_path(robot: Robot, *, step_m: float = 0.005, tilt_deg: float = YANG_TOOL_TILT_DEG) -> PlannedPath:
    """Yang Table 8: the tool point from (1.2, 0, 0.116) m to (1.8, 0, 0.116) m
    at 10 mm/s, constant tool orientation (:func:`yang_tool_rotation`). An arm on auxiliary
    joints (a track) holds them at the middle of their limits, the line moved with its base."""
    start = arm_configuration(robot, np.radians([0.0, 52.0, 29.0, 180.0, 110.0, 180.0]))
    shift = _arm_base_shift(robot, start)
    return line_path(robot, shift + (1.2, 0.0, 0.116), shift + (1.8, 0.0, 0.116), speed_m_s=0.010, step_m=step_m,
                     rotation=yang_tool_rotation(robot, tilt_deg), q_start=start)


def _arm_base_shift(robot: Robot, q: np.ndarray) -> np.ndarray:
    """How far the auxiliary joints at ``q`` carry the arm from where they are at zero [m]."""
    n_aux = auxiliary_joints(robot)
    if n_aux == 0:
        return np.zeros(3)
    model = robot.model
    data = model.createData()
    at = []
    for q_aux in (np.asarray(q[:n_aux], dtype=float), np.zeros(n_aux)):
        pin.forwardKinematics(model, data, robot.theta(np.r_[q_aux, q[n_aux:]]))
        at.append(np.array(data.oMi[n_aux].translation))
    return at[0] - at[1]
