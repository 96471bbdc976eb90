"""Kinematic errors of a URDF robot: each joint origin's six errors and the joint offsets.

A URDF robot's geometry is the origin of each joint of its chain, not a DH
table (docs/formats.md, "URDF robots"). Its kinematic parameters (docs/cli.md,
effect ``kinematic_errors``) are, per joint ``j``, the joint offset ``dq<j>``
[rad, or m for a prismatic joint] and the six errors of its origin in the frame
of the joint before it (``base_link`` for the first): ``dpx<j>, dpy<j>, dpz<j>``
[m] along that frame's axes and ``drx<j>, dry<j>, drz<j>`` [rad] about them,
through the joint's origin:

    origin' = (exp(dr) R, p + dp)     (R, p the nominal placement)

When fixed joints sit between two movable ones, that frame is the previous
movable joint's, and the URDF joint's own origin carries the same error turned
into its parent link's axes (:func:`corrected_urdf`). The marker positions in
``tip_link`` add ``dx_<m>, dy_<m>, dz_<m>`` as on a DH robot.

:func:`corrected_urdf_robot` writes the errors into the URDF text (the calibrated
URDF is then the robot's own ``urdf.xml``); :func:`urdf_position_jacobian` gives
the exact derivatives of the marker positions from the frames of the corrected
chain. Which of them the data determine, and what absorbs the rest, is the same
pivoted QR as for a DH robot (identify/kinematics.py, ``identifiable_set``): on a
serial chain every revolute joint's offset is one of its origin's rotations
about its axis, and the frame and markers absorb the base's and the tip's.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import replace
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.kinds import JointKind
from elastocal.model.robot import MARKER_PREFIX, Robot, RobotData
from elastocal.model.urdf import urdf_chain

#: a URDF joint's error kinds, in the order of the parameter vector
URDF_KINDS = ("dq", "dpx", "dpy", "dpz", "drx", "dry", "drz")
UNITS = {"dpx": "m", "dpy": "m", "dpz": "m", "drx": "rad", "dry": "rad", "drz": "rad"}


def urdf_parameter_names(robot: Robot, markers: Sequence[str]) -> tuple[str, ...]:
    names = [f"{k}{i}" for i in range(1, robot.n_joints + 1) for k in URDF_KINDS]
    for m in markers:
        names += [f"dx_{m}", f"dy_{m}", f"dz_{m}"]
    return tuple(names)


def describe_urdf(kind: str, joint: str) -> str | None:
    if kind in ("dpx", "dpy", "dpz"):
        return f"the {kind[2]} position of joint {joint}'s origin"
    if kind in ("drx", "dry", "drz"):
        return f"the rotation of joint {joint}'s origin about {kind[2]}"
    return None


def _origins(xml: str, base_link: str, tip_link: str, names: tuple[str, ...]) -> tuple:
    """Per chain joint: its URDF origin (SE3, in its parent link) and the fixed transform F
    from the previous movable joint's frame to that parent link (placement = F * origin). Parsed
    on every call, not memoised in the module: an absolute fit asks three times, 0.4 ms each."""
    from elastocal.model.urdf import UrdfSource

    chain = urdf_chain(UrdfSource(xml=xml, base_link=base_link, tip_link=tip_link), list(names), source="<urdf>")
    root = ET.fromstring(xml)
    origins = []
    for name, placement in zip(names, chain.placements):
        origin = _origin_of(root, name)
        origins.append((origin, placement * origin.inverse()))
    return tuple(origins)


def _origin_of(root: ET.Element, name: str) -> pin.SE3:
    joint = next((j for j in root.iter("joint") if j.get("name") == name), None)
    if joint is None:
        raise InputError(f"URDF has no joint {name!r}", column="joint.name")
    el = joint.find("origin")
    xyz = np.zeros(3) if el is None else np.array([float(v) for v in (el.get("xyz") or "0 0 0").split()])
    rpy = np.zeros(3) if el is None else np.array([float(v) for v in (el.get("rpy") or "0 0 0").split()])
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def _split(names: Sequence[str], values: Sequence[float], n: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """(offsets (N,), origin errors (N, 6) as dp, dr, marker errors) from names and values."""
    dq = np.zeros(n)
    dorigin = np.zeros((n, 6))
    markers: dict[str, np.ndarray] = {}
    for name, v in zip(names, values):
        if name.startswith(("dx_", "dy_", "dz_")):
            markers.setdefault(name[3:], np.zeros(3))["xyz".index(name[1])] += float(v)
            continue
        kind = name.rstrip("0123456789")
        j = int(name[len(kind):]) - 1
        if kind == "dq":
            dq[j] += float(v)
        else:
            dorigin[j, URDF_KINDS.index(kind) - 1] += float(v)
    return dq, dorigin, markers


def corrected_urdf(robot: Robot, dorigin: np.ndarray) -> str:
    """The robot's URDF text with each chain joint's origin carrying its six errors (module docstring)."""
    names = tuple(j.name for j in robot.joints)
    src = robot.urdf
    origins = _origins(src.xml, src.base_link, src.tip_link, names)
    root = ET.fromstring(src.xml)
    for name, (origin, fixed), err in zip(names, origins, dorigin):
        if not np.any(err):
            continue
        rot_f = fixed.rotation
        new_rot = rot_f.T @ pin.exp3(err[3:]) @ rot_f @ origin.rotation
        new_pos = origin.translation + rot_f.T @ err[:3]
        joint = next(j for j in root.iter("joint") if j.get("name") == name)
        el = joint.find("origin")
        if el is None:
            el = ET.SubElement(joint, "origin")
        el.set("xyz", " ".join(repr(float(v)) for v in new_pos))
        el.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(new_rot)))
    return ET.tostring(root, encoding="unicode")


def corrected_urdf_robot(robot: Robot, names: Sequence[str], values: Sequence[float]) -> Robot:
    """A new URDF robot whose joint origins, offsets and markers carry the errors ``names = values``."""
    dq, dorigin, markers = _split(names, values, robot.n_joints)
    for m in markers:
        robot.frame_id(m)
    joints = tuple(replace(j, offset=j.offset + float(d)) for j, d in zip(robot.joints, dq))
    tool = replace(robot.tool, flange_p_markers=tuple(
        (m, tuple(float(x) for x in np.array(p) + markers.get(m, np.zeros(3)))) for m, p in robot.tool.flange_p_markers))
    urdf = robot.urdf if not np.any(dorigin) else replace(robot.urdf, xml=corrected_urdf(robot, dorigin))
    return replace(robot, joints=joints, tool=tool, urdf=urdf)


def urdf_position_jacobian(robot: Robot, theta: np.ndarray, markers: Sequence[str], cols,
                           kinds: Sequence[str], data: RobotData | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Base positions (S, M, 3) of ``markers`` at the joint variables ``theta`` (S, N) of the URDF
    ``robot`` and their derivatives (S, M, 3, n) in the parameters ``cols`` (kinematics.Columns,
    whose ``kind`` indexes ``kinds``)."""
    theta = np.atleast_2d(np.asarray(theta, dtype=float))
    ns, nj = theta.shape
    model = robot.model
    data = (robot.create_data() if data is None else data).rigid
    fids = [model.getFrameId(MARKER_PREFIX + m) for m in markers]
    nm = len(markers)
    placements = [model.jointPlacements[i] for i in range(1, nj + 1)]
    idx_v = [model.joints[i].idx_v for i in range(1, nj + 1)]
    prismatic = np.array([j.kind is JointKind.PRISMATIC for j in robot.joints])
    pos = np.empty((ns, nm, 3))
    prev_rot = np.empty((ns, nj, 3, 3))        # the frame before each joint (the errors' axes)
    origin = np.empty((ns, nj, 3))             # each joint's origin, before its own motion
    axis = np.empty((ns, nj, 3))               # each joint's axis, base frame
    tip_rot = np.empty((ns, 3, 3))
    for s in range(ns):
        pin.computeJointJacobians(model, data, theta[s])       # forward kinematics and the joints' axes
        for i in range(nj):
            parent = data.oMi[i]
            origin[s, i] = (parent * placements[i]).translation
            prev_rot[s, i] = parent.rotation
            col = data.J[:, idx_v[i]]
            axis[s, i] = col[:3] if prismatic[i] else col[3:]
        tip_rot[s] = data.oMi[nj].rotation
        for m, fid in enumerate(fids):
            pos[s, m] = pin.updateFramePlacement(model, data, fid).translation
    n = len(cols.names)
    jac = np.zeros((ns, nm, 3, n))
    arm = pos[:, :, None, :] - origin[:, None, :, :]               # (S, M, N, 3)
    for c in range(n):
        k, j = int(cols.kind[c]), int(cols.joint[c]) - 1
        if k == -1:                                               # a marker coordinate in the flange
            if cols.marker[c] >= 0:
                jac[:, cols.marker[c], :, c] = tip_rot[:, :, cols.axis[c]]
            continue
        kind = kinds[k]
        if kind == "dq":
            if prismatic[j]:
                jac[:, :, :, c] = axis[:, None, j, :]
            else:
                jac[:, :, :, c] = np.cross(axis[:, None, j, :], arm[:, :, j, :])
        elif kind in ("dpx", "dpy", "dpz"):
            jac[:, :, :, c] = prev_rot[:, None, j, :, "xyz".index(kind[2])]
        elif kind in ("drx", "dry", "drz"):
            direction = prev_rot[:, j, :, "xyz".index(kind[2])]
            jac[:, :, :, c] = np.cross(direction[:, None, :], arm[:, :, j, :])
        else:
            raise InputError(f"{cols.names[c]} is a DH parameter; a URDF robot's geometry is its joint origins",
                             argument="model")
    return pos, jac
