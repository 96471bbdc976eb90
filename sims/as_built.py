"""The simulated robot as built: the errors its real geometry has against the drawing.

``--hidden kinematic_errors`` puts them in a simulated cell: the HH-150's table
(:data:`KINEMATIC_ERRORS`), and for any chain the same sizes joint by joint, each
joint's zero error of its own kind (:func:`default_kinematic_errors`), a tilt where
consecutive axes are parallel, found from the robot's own kinematics
(:func:`parallel_axes`, Pinocchio's joint Jacobian: the simulator does not ask the
fit which parameters it has). A URDF robot's geometry is its joint origins: each
joint's zero and its origin's six errors, of the same sizes by the joint's kind
(:func:`default_urdf_errors`), written into the URDF text (:func:`moved_urdf`).
:func:`as_built` applies them to the drawing.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
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
#: (a homing switch's repeatability and mounting), a, alpha of the link before it [mm, deg], and its
#: fixed theta [deg] (the rails turned about their own axis as mounted, sized like the arm's twists);
#: no error in d (a prismatic joint's d is its coordinate: an error in it is one in its zero)
_PRISMATIC_ERRORS = {"dq": (0.4, -0.3), "da": (0.15, -0.2), "dalpha": (0.02, -0.015), "dtheta": (0.025, -0.03)}
_BETA_DEG = 0.03
#: a URDF joint's errors of the same sizes, one per joint of its kind in order (repeated beyond): its zero
#: [deg; mm on a prismatic joint], its origin's position along the previous joint's x, y, z [mm] and its
#: rotation about them [deg] (the sizes of a, d and alpha)
_URDF_ARM_ERRORS = {"dq": _ARM_ERRORS["dq"], "dpx": _ARM_ERRORS["da"], "dpy": (-0.15, 0.25, 0.1, 0.2, -0.3, 0.45),
                    "dpz": _ARM_ERRORS["dd"], "drx": _ARM_ERRORS["dalpha"],
                    "dry": (-0.03, 0.025, -0.02, 0.035, -0.04, 0.03), "drz": (0.025, 0.035, -0.03, 0.02, -0.025, 0.04)}
_URDF_PRISMATIC_ERRORS = {"dq": _PRISMATIC_ERRORS["dq"], "dpx": (0.15, -0.2), "dpy": (-0.2, 0.1), "dpz": (0.1, 0.25),
                          "drx": (0.02, -0.015), "dry": (-0.015, 0.02), "drz": (0.02, 0.015)}
#: the URDF errors that are lengths (the rest are angles, but for a prismatic joint's zero)
_URDF_LENGTHS = ("dpx", "dpy", "dpz")


def default_kinematic_errors(prismatic: Sequence[bool], parallel: Sequence[bool]) -> tuple[tuple[str, float], ...]:
    """``--hidden kinematic_errors`` for a chain with these joints (``prismatic[i]``; ``parallel[i]``: joint
    i+1's axis parallel to joint i's): each joint its zero error of its own kind (an angle on a revolute
    joint, a length on a prismatic one), every joint with errors in a, d (revolute), theta (prismatic: its
    fixed angle) and alpha, a Hayati tilt beta on each axis parallel to the one before, the markers' errors
    of :data:`KINEMATIC_ERRORS`. The revolute joints take the six-axis arm's values in order, so a six-axis arm is the HH-150's exactly."""
    per_kind: dict[str, list[tuple[str, float]]] = {k: [] for k in ("dq", "da", "dd", "dalpha", "dtheta")}
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


def default_urdf_errors(prismatic: Sequence[bool]) -> tuple[tuple[str, float], ...]:
    """``--hidden kinematic_errors`` for a URDF robot with these joints (``prismatic[i]``): each joint its zero
    error of its own kind (an angle on a revolute joint, a length on a prismatic one) and its origin's three
    position and three rotation errors in the previous joint's frame (``dpx<j>``.. ``drz<j>``, the sizes of
    a DH robot's lengths and twists), the markers' errors of :data:`KINEMATIC_ERRORS`."""
    out: list[tuple[str, float]] = []
    revolute = slide = 0
    for i, p in enumerate(prismatic, start=1):
        table, k = (_URDF_PRISMATIC_ERRORS, slide) if p else (_URDF_ARM_ERRORS, revolute)
        for kind, values in table.items():
            v = values[k % len(values)]
            out.append((f"{kind}{i}", v * 1e-3 if kind in _URDF_LENGTHS or (p and kind == "dq") else math.radians(v)))
        slide, revolute = slide + bool(p), revolute + (not p)
    return tuple(out) + tuple((n, v) for n, v in KINEMATIC_ERRORS if n.startswith(("dx_", "dy_", "dz_")))


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
    """Unit of a kinematic error: joint zeros, twists and a URDF origin's rotations in rad, lengths, a URDF
    origin's position, markers and the zero of a prismatic joint (``prismatic[i]``) in m."""
    kind = name.rstrip("0123456789")
    if kind == "dq" and int(name[2:]) <= len(prismatic) and prismatic[int(name[2:]) - 1]:
        return "m"
    return "rad" if kind in ("dq", "dalpha", "dbeta", "dtheta", "drx", "dry", "drz") else "m"


def as_built(robot: Robot, errors: Sequence[tuple[str, float]]) -> Robot:
    """The robot as built: the drawing's DH table and markers with the truth's errors
    (``dq<i>``, ``da<i>``, ``dd<i>``, ``dalpha<i>``, ``dbeta<i>`` on joint i, ``dtheta<i>`` on a
    prismatic joint i's fixed theta, ``dx_<m>``.. on marker m); errors naming a joint or marker the
    robot does not have are ignored. A URDF robot's are ``dq<i>`` and its origin's
    ``dpx<i>``..``drz<i>`` (:func:`moved_urdf`); a DH table's errors on a URDF robot are refused."""
    if not errors:
        return robot
    urdf = robot.urdf is not None
    field_of = {"dq": "offset"} if urdf else {"dq": "offset", "da": "a", "dd": "d", "dalpha": "alpha", "dbeta": "beta",
                                              "dtheta": "theta"}
    joints = list(robot.joints)
    markers = {m: np.array(p, dtype=float) for m, p in robot.tool.flange_p_markers}
    origin = np.zeros((len(joints), 6))
    for name, value in errors:
        if name.startswith(("dx_", "dy_", "dz_")):
            if name[3:] in markers:
                markers[name[3:]]["xyz".index(name[1])] += value
            continue
        kind = name.rstrip("0123456789")
        i = int(name[len(kind):]) - 1
        if urdf and kind in ("da", "dd", "dalpha", "dbeta", "dtheta"):
            raise ValueError(f"{name} is a DH error; a URDF robot's geometry is its joint origins "
                             f"(dpx{i + 1}..drz{i + 1})")
        if kind in ORIGIN_KINDS and 0 <= i < len(joints):
            if not urdf:
                continue        # a DH robot has no URDF origins: ignored as a joint it does not have
            origin[i, ORIGIN_KINDS.index(kind)] += value
        elif kind in field_of and 0 <= i < len(joints):
            key = field_of[kind]
            joints[i] = replace(joints[i], **{key: getattr(joints[i], key) + value})
    tool = replace(robot.tool, flange_p_markers=tuple((m, tuple(float(x) for x in markers[m]))
                                                      for m, _ in robot.tool.flange_p_markers))
    if urdf and np.any(origin):
        return replace(robot, joints=tuple(joints), tool=tool, urdf=replace(robot.urdf, xml=moved_urdf(robot, origin)))
    return replace(robot, joints=tuple(joints), tool=tool)


#: a URDF origin's errors, in the order of :func:`moved_urdf`'s rows
ORIGIN_KINDS = ("dpx", "dpy", "dpz", "drx", "dry", "drz")


def _origin_element(root: ET.Element, name: str) -> ET.Element:
    joint = next(j for j in root.iter("joint") if j.get("name") == name)
    el = joint.find("origin")
    return ET.SubElement(joint, "origin") if el is None else el


def moved_urdf(robot: Robot, origin_errors: np.ndarray) -> str:
    """The URDF text of ``robot`` with each chain joint's origin moved: row i of ``origin_errors``
    (N, 6) is joint i+1's ``dp`` [m] along and ``dr`` [rad] about the axes of the previous joint's
    frame (base_link's for the first), ``placement' = (exp(dr) R, p + dp)``. Where fixed joints sit
    between, the placement is F * origin (F the fixed links' transform, from Pinocchio's chain), so the
    URDF origin becomes F^-1 * placement'."""
    import pinocchio as pin

    placements = robot.model.jointPlacements          # each joint in the previous joint's frame, as described
    root = ET.fromstring(robot.urdf.xml)
    for i, (joint, err) in enumerate(zip(robot.joints, np.asarray(origin_errors, dtype=float)), start=1):
        if not np.any(err):
            continue
        el = _origin_element(root, joint.name)
        xyz = np.array([float(v) for v in (el.get("xyz") or "0 0 0").split()])
        rpy = np.array([float(v) for v in (el.get("rpy") or "0 0 0").split()])
        placement = pin.SE3(placements[i])
        fixed = placement * pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz).inverse()
        moved = pin.SE3(pin.exp3(err[3:]) @ placement.rotation, placement.translation + err[:3])
        new = fixed.inverse() * moved
        el.set("xyz", " ".join(repr(float(v)) for v in new.translation))
        el.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(new.rotation)))
    return ET.tostring(root, encoding="unicode")
