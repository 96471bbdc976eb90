"""URDF robots: the serial chain elastocal needs, read from a URDF with Pinocchio,
and the modified-DH robots written out as URDF.

A URDF robot's ``robot.toml`` gives ``urdf = "path.urdf"`` (or the text inline
as ``urdf_xml``) and one ``[[joint]]`` table per actuated joint naming a URDF
joint (docs/formats.md §1). :func:`urdf_chain` builds the URDF with
:func:`pinocchio.buildModelFromXML`, locks every joint the tables do not name at
zero (:func:`pinocchio.buildReducedModel`), checks that the six named joints are
revolute and form a chain base to tip, and returns for each its placement in
the previous joint's frame, its axis, its limits and the mass and centre of
mass of the body it moves (links merged through fixed joints included, as
Pinocchio merges them). The flange is the frame of the sixth joint unless
``[tool] flange`` names a URDF link or frame further out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError


@dataclass(frozen=True)
class UrdfSource:
    """The URDF text a robot was built from, and what of it elastocal uses."""

    xml: str
    path: str = ""          # where it was read from ("" when inline), for messages
    flange: str = ""        # URDF link or frame that is the flange ("" = the sixth joint's frame)


@dataclass(frozen=True)
class UrdfChain:
    """The six actuated joints of a URDF, base to tip (arrays per joint)."""

    placements: tuple[pin.SE3, ...]        # joint i's frame in joint i-1's frame at theta = 0
    axes: np.ndarray                       # (6, 3) unit rotation axes, in each joint's own frame
    lower: np.ndarray                      # (6,) URDF limits of theta [rad]; nan for continuous joints
    upper: np.ndarray
    masses: np.ndarray                     # (6,) [kg]
    coms: np.ndarray                       # (6, 3) centres of mass in each joint's frame [m]
    flange_placement: pin.SE3              # the flange in the sixth joint's frame


def urdf_chain(urdf: UrdfSource, joint_names: Sequence[str], *, source: str) -> UrdfChain:
    """Read the chain of ``joint_names`` from ``urdf`` (errors name ``source``)."""
    where = urdf.path or "urdf_xml"
    try:
        full = pin.buildModelFromXML(urdf.xml)
    except (RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"not a valid URDF ({where}): {first}", source=source, column="urdf") from None
    names = list(full.names)[1:]
    missing = [n for n in joint_names if n not in names]
    if missing:
        raise InputError(f"URDF {where} has no joint {missing[0]!r}; its movable joints are "
                         f"{', '.join(names) or 'none'}", source=source, column="joint.name")
    if len(set(joint_names)) != len(joint_names):
        raise InputError("two [[joint]] tables name the same URDF joint", source=source, column="joint.name")
    locked = [full.getJointId(n) for n in names if n not in joint_names]
    model = pin.buildReducedModel(full, locked, pin.neutral(full)) if locked else full
    ids = [model.getJointId(n) for n in joint_names]
    if ids != list(range(1, len(joint_names) + 1)) or any(model.parents[i] != i - 1 for i in ids):
        raise InputError(f"the [[joint]] tables must name a serial chain of URDF {where} from base to tip, "
                         f"in order; the URDF orders them {', '.join(model.names[1:])}",
                         source=source, column="joint.name")
    data = model.createData()
    q0 = pin.neutral(model)
    pin.computeJointJacobians(model, data, q0)
    axes, lower, upper = [], [], []
    for i, name in zip(ids, joint_names):
        jm = model.joints[i]
        if jm.nv != 1:
            raise InputError(f"URDF joint {name!r} ({jm.shortname()}) is not a revolute joint",
                             source=source, column="joint.name")
        column = pin.getJointJacobian(model, data, i, pin.LOCAL)[:, jm.idx_v]
        if np.linalg.norm(column[:3]) > 1e-12 or abs(np.linalg.norm(column[3:]) - 1.0) > 1e-9:
            raise InputError(f"URDF joint {name!r} ({jm.shortname()}) is not a revolute joint",
                             source=source, column="joint.name")
        axes.append(column[3:] / np.linalg.norm(column[3:]))
        if jm.nq == 1:          # revolute: URDF limits
            lower.append(float(model.lowerPositionLimit[jm.idx_q]))
            upper.append(float(model.upperPositionLimit[jm.idx_q]))
        else:                   # continuous (cos, sin): no limits in the URDF
            lower.append(math.nan)
            upper.append(math.nan)
    flange = pin.SE3.Identity()
    if urdf.flange:
        if not model.existFrame(urdf.flange):
            raise InputError(f"URDF {where} has no link or frame {urdf.flange!r}", source=source,
                             column="tool.flange")
        frame = model.frames[model.getFrameId(urdf.flange)]
        if frame.parentJoint != ids[-1]:
            raise InputError(f"flange {urdf.flange!r} does not move with the last joint {joint_names[-1]!r}",
                             source=source, column="tool.flange")
        flange = frame.placement
    return UrdfChain(
        placements=tuple(pin.SE3(model.jointPlacements[i]) for i in ids),
        axes=np.array(axes), lower=np.array(lower), upper=np.array(upper),
        masses=np.array([model.inertias[i].mass for i in ids]),
        coms=np.array([model.inertias[i].lever for i in ids]),
        flange_placement=pin.SE3(flange))


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def dh_urdf(name: str, placements: Sequence[pin.SE3], joint_names: Sequence[str], lower: Sequence[float],
            upper: Sequence[float], masses: Sequence[float], coms: Sequence[Sequence[float]],
            sphere_radius_m: float) -> str:
    """A URDF of a chain of z-axis revolute joints (a modified-DH robot): links
    ``base_link``, ``link1`` … ``link6`` (``link6`` is the flange), each link's
    inertia that of a solid sphere of ``sphere_radius_m`` at its centre of mass.
    Limits are given in theta (the URDF joint variable)."""
    lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(name)}>", '  <link name="base_link"/>']
    for i, (placement, jname, lo, hi, mass, com) in enumerate(
            zip(placements, joint_names, lower, upper, masses, coms), start=1):
        rpy = pin.rpy.matrixToRpy(placement.rotation)
        lines.append(f'  <link name="link{i}">')
        if mass > 0.0:
            inertia = 0.4 * mass * sphere_radius_m ** 2
            lines += ["    <inertial>", f'      <origin xyz="{_fmt(com)}" rpy="0 0 0"/>',
                      f'      <mass value="{float(mass)!r}"/>',
                      f'      <inertia ixx="{inertia!r}" iyy="{inertia!r}" izz="{inertia!r}" '
                      'ixy="0" ixz="0" iyz="0"/>', "    </inertial>"]
        lines.append("  </link>")
        parent = "base_link" if i == 1 else f"link{i - 1}"
        lines += [f"  <joint name={quoteattr(jname)} type=\"revolute\">",
                  f'    <parent link="{parent}"/>', f'    <child link="link{i}"/>',
                  f'    <origin xyz="{_fmt(placement.translation)}" rpy="{_fmt(rpy)}"/>',
                  '    <axis xyz="0 0 1"/>',
                  f'    <limit lower="{float(lo)!r}" upper="{float(hi)!r}" effort="0" velocity="0"/>',
                  "  </joint>"]
    lines.append("</robot>")
    return "\n".join(lines) + "\n"
