"""A robot written out as URDF, for the tools beyond elastocal (a controller's
kinematics, MoveIt, RViz, Pinocchio, any URDF reader).

:func:`robot_urdf` writes the chain of :attr:`Robot.model` (the Pinocchio model
elastocal computes with, so a calibrated robot's corrections are in it),
whatever the description came from (a modified-DH table or a URDF):

* links ``base_link``, ``link1`` … ``linkN``, one joint per actuated joint with
  the description's name, axis, kind (revolute or prismatic), limits and the
  mass and centre of mass the models use;
* by default the joint variable is the controller's ``q``: each joint's
  ``offset`` (the calibrated joint zero included) is turned into its origin
  (a rotation about, or a slide along, the joint's axis), so controller angles
  fed to the URDF give the robot's positions, and the limits are those of ``q``;
  with ``controller_angles=False`` the variable is elastocal's
  ``theta = q + offset`` (the offsets stay in robot.toml's ``[[joint]]`` tables);
* fixed joints to the links ``flange`` (the tip frame markers are given in),
  ``load_point`` (the tool point where loads act) and ``marker_<name>`` (each
  tracker marker), the last two on the flange;
* each joint's ``velocity`` and ``effort`` limits from the description; a URDF
  reader needs them (urdfdom refuses a joint without), so a description
  without them is refused, naming the joint, rather than written with zeros.
"""

from __future__ import annotations

from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.kinds import JointKind

if TYPE_CHECKING:
    from elastocal.model.robot import Robot

FLANGE_LINK = "flange"
LOAD_LINK = "load_point"
MARKER_LINK_PREFIX = "marker_"


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def _origin(placement: pin.SE3) -> str:
    return (f'<origin xyz="{_fmt(placement.translation)}" '
            f'rpy="{_fmt(pin.rpy.matrixToRpy(placement.rotation))}"/>')


def _inertial(inertia: pin.Inertia) -> list[str]:
    if not inertia.mass > 0.0:
        return []
    i = [[float(x) for x in row] for row in inertia.inertia]
    return ["    <inertial>", f'      <origin xyz="{_fmt(inertia.lever)}" rpy="0 0 0"/>',
            f'      <mass value="{float(inertia.mass)!r}"/>',
            f'      <inertia ixx="{i[0][0]!r}" ixy="{i[0][1]!r}" ixz="{i[0][2]!r}" iyy="{i[1][1]!r}" '
            f'iyz="{i[1][2]!r}" izz="{i[2][2]!r}"/>', "    </inertial>"]


def _axes(model: pin.Model, ids: list[int]) -> list[np.ndarray]:
    """Each joint's unit axis in its own frame (the angular part of its motion subspace for a
    revolute joint, the linear part for a prismatic one)."""
    data = model.createData()
    q0 = pin.neutral(model)
    pin.computeJointJacobians(model, data, q0)
    out = []
    for jid in ids:
        column = pin.getJointJacobian(model, data, jid, pin.LOCAL)[:, model.joints[jid].idx_v]
        out.append(column[3:] if np.linalg.norm(column[3:]) > 0.5 else column[:3])
    return out


def _limits(robot: Robot, i: int, shift: float) -> str:
    j = robot.joints[i - 1]
    for key, unit in (("velocity", j.unit + "/s"), ("effort", "N·m" if j.kind is JointKind.REVOLUTE else "N")):
        if getattr(j, key) is None:
            raise InputError(f"joint {i} ({j.name or f'joint{i}'}) has no {key} limit; a URDF joint needs one: "
                             f"give {key} = … [{unit}] in its [[joint]] table", source=robot.source,
                             column=f"joint[{i}].{key}")
    return (f'    <limit lower="{j.lower + shift!r}" upper="{j.upper + shift!r}" effort="{float(j.effort)!r}" '
            f'velocity="{float(j.velocity)!r}"/>')


def _fixed(name: str, parent: str, placement: pin.SE3) -> list[str]:
    return [f"  <link name={quoteattr(name)}/>",
            f"  <joint name={quoteattr(name + '_joint')} type=\"fixed\">",
            f'    <parent link="{parent}"/>', f"    <child link={quoteattr(name)}/>",
            f"    {_origin(placement)}", "  </joint>"]


def robot_urdf(robot: Robot, *, controller_angles: bool = True) -> str:
    """The robot's chain as URDF text (module docstring)."""
    from elastocal.model.robot import FLANGE_FRAME, LOAD_FRAME, MARKER_PREFIX

    model = robot.model
    ids = [model.getJointId(f"joint{i}") for i in range(1, robot.n_joints + 1)]
    names = [j.name or f"joint{i}" for i, j in enumerate(robot.joints, start=1)]
    if len(set(names)) != len(names):
        raise InputError("two joints have the same name; a URDF needs distinct joint names", source=robot.source,
                         column="joint.name")
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(robot.name)}>", '  <link name="base_link"/>']
    for i, (jid, axis, name, joint) in enumerate(zip(ids, _axes(model, ids), names, robot.joints), start=1):
        placement = pin.SE3(model.jointPlacements[jid])
        if controller_angles:        # theta = q + offset: the offset's motion goes into the origin
            placement = placement * (pin.SE3(pin.exp3(axis * joint.offset), np.zeros(3))
                                     if joint.kind is JointKind.REVOLUTE
                                     else pin.SE3(np.eye(3), axis * joint.offset))
        lines += [f'  <link name="link{i}">', *_inertial(model.inertias[jid]), "  </link>",
                  f"  <joint name={quoteattr(name)} type=\"{joint.kind.value}\">",
                  f'    <parent link="{"base_link" if i == 1 else f"link{i - 1}"}"/>', f'    <child link="link{i}"/>',
                  f"    {_origin(placement)}", f'    <axis xyz="{_fmt(axis)}"/>',
                  _limits(robot, i, 0.0 if controller_angles else joint.offset), "  </joint>"]
    flange = pin.SE3(model.frames[model.getFrameId(FLANGE_FRAME)].placement)
    lines += _fixed(FLANGE_LINK, f"link{robot.n_joints}", flange)
    tool = [(LOAD_LINK, LOAD_FRAME)] + [(MARKER_LINK_PREFIX + m, MARKER_PREFIX + m) for m in robot.marker_names]
    for link, frame in tool:
        lines += _fixed(link, FLANGE_LINK, flange.actInv(pin.SE3(model.frames[model.getFrameId(frame)].placement)))
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def controller_urdf_robot(robot: Robot) -> Robot:
    """The same robot as a URDF robot on :func:`robot_urdf`'s text: joint variable ``q``
    (offsets 0), tip ``flange``, the same markers, load point, limits, masses and the rest of
    each ``[[joint]]`` table; its robot.toml (``to_toml``) carries the URDF inline."""
    from dataclasses import replace
    from math import nan

    from elastocal.model.urdf import UrdfSource

    joints = tuple(replace(j, a=nan, alpha=nan, d=nan, theta=nan, beta=0.0, offset=0.0) for j in robot.joints)
    return replace(robot, joints=joints, urdf=UrdfSource(xml=robot_urdf(robot), tip_link=FLANGE_LINK))
