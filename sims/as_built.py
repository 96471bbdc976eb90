"""The simulated robot as built: the errors its real geometry has against the drawing.

``--hidden kinematic_errors`` puts them in a simulated cell: the HH-150's table
(:data:`KINEMATIC_ERRORS`), and for any chain the same sizes joint by joint, each
joint's zero error of its own kind (:func:`default_kinematic_errors`), a tilt where
consecutive axes are parallel, found from the robot's own kinematics
(:func:`parallel_axes`, Pinocchio's joint Jacobian: the simulator does not ask the
fit which parameters it has). :func:`as_built` applies them to the drawing.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np

from elastocal.model.robot import Robot

#: ``--hidden kinematic_errors``: the real DH table differs from the drawing by
#: 0.02-0.05 deg in joint zeros and twists, 0.1-0.5 mm in lengths and offsets,
#: 0.03 deg of Hayati tilt on the parallel axes 2-3, markers 0.1-0.3 mm off
#: (typical of a heavy robot after assembly; RoboDK and FIGAROH report errors
#: of this size before calibration). The HH-150's; :func:`default_kinematic_errors`
#: sizes the same for any chain.
KINEMATIC_ERRORS = tuple(
    [(f"dq{i}", math.radians(v)) for i, v in enumerate((0.03, -0.04, 0.05, -0.02, 0.035, -0.045), start=1)]
    + [(f"da{i}", v * 1e-3) for i, v in enumerate((0.2, -0.3, 0.45, -0.15, 0.25, 0.1), start=1)]
    + [(f"dd{i}", v * 1e-3) for i, v in enumerate((0.3, -0.2, 0.25, -0.4, 0.12, 0.3), start=1)]
    + [(f"dalpha{i}", math.radians(v)) for i, v in enumerate((0.02, -0.03, 0.04, -0.025, 0.03, -0.035), start=1)]
    + [("dbeta3", math.radians(0.03))]
    + [("dx_R1", 0.2e-3), ("dy_R1", -0.1e-3), ("dz_R1", 0.3e-3), ("dx_R2", -0.15e-3), ("dy_R2", 0.25e-3),
       ("dz_R2", 0.1e-3), ("dx_R3", 0.1e-3), ("dy_R3", -0.2e-3), ("dz_R3", -0.15e-3)])
#: the HH-150's axes: joint 3's parallel to joint 2's (alpha2 = 0), no other pair
HH150_PARALLEL = (False, False, True, False, False, False)
#: the six-axis arm's errors of :data:`KINEMATIC_ERRORS` by kind, one per revolute joint in
#: order (repeated from the first beyond six): zero [deg], a, d [mm], alpha [deg]
_ARM_ERRORS = {"dq": (0.03, -0.04, 0.05, -0.02, 0.035, -0.045), "da": (0.2, -0.3, 0.45, -0.15, 0.25, 0.1),
               "dd": (0.3, -0.2, 0.25, -0.4, 0.12, 0.3), "dalpha": (0.02, -0.03, 0.04, -0.025, 0.03, -0.035)}
#: a prismatic joint's (a linear track's carriage), repeated for more: its zero along the axis [mm]
#: (a homing switch's repeatability and mounting), a, alpha of the link before it [mm, deg]; no
#: error in d (a prismatic joint's d is its coordinate: an error in it is one in its zero)
_PRISMATIC_ERRORS = {"dq": (0.4, -0.3), "da": (0.15, -0.2), "dalpha": (0.02, -0.015)}
_BETA_DEG = 0.03


def default_kinematic_errors(prismatic: Sequence[bool], parallel: Sequence[bool]) -> tuple[tuple[str, float], ...]:
    """``--hidden kinematic_errors`` for a chain with these joints (``prismatic[i]``; ``parallel[i]``: joint
    i+1's axis parallel to joint i's): each joint its zero error of its own kind (an angle on a revolute
    joint, a length on a prismatic one), every joint with errors in a, d (revolute) and alpha, a Hayati tilt
    beta on each axis parallel to the one before, the markers' errors of :data:`KINEMATIC_ERRORS`. The
    revolute joints take the six-axis arm's values in order, so a six-axis arm is the HH-150's exactly."""
    per_kind: dict[str, list[tuple[str, float]]] = {k: [] for k in ("dq", "da", "dd", "dalpha")}
    revolute = slide = 0
    for i, p in enumerate(prismatic, start=1):
        table, k = (_PRISMATIC_ERRORS, slide) if p else (_ARM_ERRORS, revolute)
        for kind, values in table.items():
            v = values[k % len(values)]
            per_kind[kind].append((f"{kind}{i}", v * 1e-3 if kind in ("da", "dd") or (p and kind == "dq")
                                   else math.radians(v)))
        slide, revolute = slide + bool(p), revolute + (not p)
    beta = [(f"dbeta{i}", math.radians(_BETA_DEG)) for i, par in enumerate(parallel, start=1) if par and i >= 2]
    markers = [(n, v) for n, v in KINEMATIC_ERRORS if n.startswith(("dx_", "dy_", "dz_"))]
    return tuple(e for kind in per_kind.values() for e in kind) + tuple(beta) + tuple(markers)


def parallel_axes(robot: Robot, tol: float = 1e-6) -> tuple[bool, ...]:
    """Which joints' axes are parallel to the previous joint's, from the robot's own kinematics
    (Pinocchio's joint Jacobian at the zero configuration: a revolute joint's axis is its column's
    rotation, a prismatic one's its translation); the first joint's is False."""
    import pinocchio as pin

    model = robot.model
    jac = pin.computeJointJacobians(model, model.createData(), pin.neutral(model))
    axes = []
    for col in np.asarray(jac).T[: robot.n_joints]:
        axis = col[3:] if np.linalg.norm(col[3:]) > 0.5 else col[:3]
        axes.append(axis / np.linalg.norm(axis))
    return (False,) + tuple(bool(np.linalg.norm(np.cross(a, b)) < tol) for a, b in zip(axes, axes[1:]))


def error_unit(name: str, prismatic: Sequence[bool] = ()) -> str:
    """Unit of a kinematic error: joint zeros and twists in rad, lengths, markers and the zero of a
    prismatic joint (``prismatic[i]``) in m."""
    kind = name.rstrip("0123456789")
    if kind == "dq" and int(name[2:]) <= len(prismatic) and prismatic[int(name[2:]) - 1]:
        return "m"
    return "rad" if kind in ("dq", "dalpha", "dbeta") else "m"


def as_built(robot: Robot, errors: Sequence[tuple[str, float]]) -> Robot:
    """The robot as built: the drawing's DH table and markers with the truth's errors
    (``dq<i>``, ``da<i>``, ``dd<i>``, ``dalpha<i>``, ``dbeta<i>`` on joint i, ``dx_<m>``..
    on marker m); errors naming a joint or marker the robot does not have are ignored."""
    if not errors:
        return robot
    if robot.urdf is not None:
        raise ValueError("kinematic errors are simulated on a modified-DH robot")
    field_of = {"dq": "offset", "da": "a", "dd": "d", "dalpha": "alpha", "dbeta": "beta"}
    joints = list(robot.joints)
    markers = {m: np.array(p, dtype=float) for m, p in robot.tool.flange_p_markers}
    for name, value in errors:
        if name.startswith(("dx_", "dy_", "dz_")):
            if name[3:] in markers:
                markers[name[3:]]["xyz".index(name[1])] += value
            continue
        kind = name.rstrip("0123456789")
        i = int(name[len(kind):]) - 1
        if kind in field_of and 0 <= i < len(joints):
            key = field_of[kind]
            joints[i] = replace(joints[i], **{key: getattr(joints[i], key) + value})
    tool = replace(robot.tool, flange_p_markers=tuple((m, tuple(float(x) for x in markers[m]))
                                                      for m, _ in robot.tool.flange_p_markers))
    return replace(robot, joints=tuple(joints), tool=tool)
