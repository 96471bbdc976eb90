"""URDF robots: the serial chain elastocal needs, read from a URDF with Pinocchio
(robots are written out as URDF by :mod:`elastocal.model.urdf_export`).

A URDF robot's ``robot.toml`` gives ``urdf = "path.urdf"`` (or the text inline
as ``urdf_xml``), the chain's ``base_link`` and ``tip_link`` (optional: the URDF's
root link, and the link the last named joint moves), and one ``[[joint]]`` table
per movable joint of that chain naming its URDF joint (docs/formats.md §1).
:func:`urdf_chain` builds the URDF with :func:`pinocchio.buildModelFromXML`,
locks every joint that is not on the chain at zero (:func:`pinocchio.buildReducedModel`;
other branches of the tree are ignored), checks that the named joints are exactly
the movable joints between ``base_link`` and ``tip_link``, base to tip, each
revolute (or continuous) or prismatic, and returns for each its placement in the
previous joint's frame (the first in ``base_link``'s frame), its kind, its axis,
its limits and the mass and centre of mass of the body it moves (links merged
through fixed joints included, as Pinocchio merges them), and ``tip_link``'s
placement in the last joint's frame (the flange: markers are given in it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.kinds import JointKind


@dataclass(frozen=True)
class UrdfSource:
    """The URDF text a robot was built from, and what of it elastocal uses."""

    xml: str
    path: str = ""          # where it was read from ("" when inline), for messages
    tip_link: str = ""      # URDF link or frame that is the flange ("" = the last joint's frame)
    base_link: str = ""     # URDF link the chain starts from ("" = the URDF's root)
    #: the robot.toml key that named the tip, for messages (``tip_link``, or the older ``tool.flange``)
    tip_column: str = "tip_link"

    @property
    def flange(self) -> str:
        """The older name of ``tip_link`` (robot.toml's ``[tool] flange``)."""
        return self.tip_link


@dataclass(frozen=True)
class UrdfChain:
    """The actuated joints of a URDF chain, base to tip (arrays per joint, N joints)."""

    placements: tuple[pin.SE3, ...]        # joint i's frame in joint i-1's frame at q = 0 (joint 1: in base_link's)
    kinds: tuple[JointKind, ...]
    axes: np.ndarray                       # (N, 3) unit axes (rotation or translation), in each joint's own frame
    lower: np.ndarray                      # (N,) URDF limits of the joint variable [rad or m]; nan for continuous
    upper: np.ndarray
    masses: np.ndarray                     # (N,) [kg]
    velocity: np.ndarray                   # (N,) URDF speed limits [rad/s or m/s]; nan where 0 (not given)
    effort: np.ndarray                     # (N,) URDF effort limits [N·m or N]; nan where 0 (not given)
    coms: np.ndarray                       # (N, 3) centres of mass in each joint's frame [m]
    flange_placement: pin.SE3              # tip_link in the last joint's frame


def _build(urdf: UrdfSource, *, source: str) -> pin.Model:
    where = urdf.path or "urdf_xml"
    try:
        return pin.buildModelFromXML(urdf.xml)
    except (RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"not a valid URDF ({where}): {first}", source=source, column="urdf") from None


def _link_joint(model: pin.Model, link: str, *, where: str, source: str, column: str) -> tuple[int, pin.SE3]:
    """(parent joint id, placement in that joint's frame) of a URDF link or frame."""
    if not model.existFrame(link):
        links = [f.name for f in model.frames if f.type == pin.FrameType.BODY]
        raise InputError(f"URDF {where} has no link or frame {link!r}; its links are {', '.join(links)}",
                         source=source, column=column)
    frame = model.frames[model.getFrameId(link)]
    return int(frame.parentJoint), pin.SE3(frame.placement)


def _ancestors(model: pin.Model, joint: int) -> list[int]:
    """Joint ids from the root to ``joint`` (inclusive, the universe 0 excluded)."""
    out = []
    while joint != 0:
        out.append(joint)
        joint = int(model.parents[joint])
    return out[::-1]


def _joint_axes(model, data, ids: Sequence[int], joint_names: Sequence[str], *, source: str):
    """(kinds, unit axes, lower, upper limits) of the chain's joints at the neutral
    configuration: a joint's Jacobian column says whether it turns or slides."""
    kinds, axes, lower, upper = [], [], [], []
    for i, name in zip(ids, joint_names):
        jm = model.joints[i]
        column = pin.getJointJacobian(model, data, i, pin.LOCAL)[:, jm.idx_v] if jm.nv == 1 else None
        if column is not None and np.linalg.norm(column[3:]) < 1e-12 and abs(np.linalg.norm(column[:3]) - 1) < 1e-9:
            kinds.append(JointKind.PRISMATIC)
            axes.append(column[:3] / np.linalg.norm(column[:3]))
        elif column is not None and np.linalg.norm(column[:3]) < 1e-12 and abs(np.linalg.norm(column[3:]) - 1) < 1e-9:
            kinds.append(JointKind.REVOLUTE)
            axes.append(column[3:] / np.linalg.norm(column[3:]))
        else:
            raise InputError(f"URDF joint {name!r} ({jm.shortname()}) is neither revolute nor prismatic",
                             source=source, column="joint.name")
        if jm.nq == 1:          # revolute or prismatic: URDF limits
            lower.append(float(model.lowerPositionLimit[jm.idx_q]))
            upper.append(float(model.upperPositionLimit[jm.idx_q]))
        else:                   # continuous (cos, sin): no limits in the URDF
            lower.append(math.nan)
            upper.append(math.nan)
    return kinds, axes, lower, upper


def urdf_chain(urdf: UrdfSource, joint_names: Sequence[str], *, source: str) -> UrdfChain:
    """Read the chain of ``joint_names`` from ``urdf`` (errors name ``source``)."""
    where = urdf.path or "urdf_xml"
    full = _build(urdf, source=source)
    names = list(full.names)[1:]
    missing = [n for n in joint_names if n not in names]
    if missing:
        raise InputError(f"URDF {where} has no joint {missing[0]!r}; its movable joints are "
                         f"{', '.join(names) or 'none'}", source=source, column="joint.name")
    if len(set(joint_names)) != len(joint_names):
        raise InputError("two [[joint]] tables name the same URDF joint", source=source, column="joint.name")
    tip_joint = full.getJointId(joint_names[-1])
    if urdf.tip_link:
        tip_joint, _ = _link_joint(full, urdf.tip_link, where=where, source=source, column=urdf.tip_column)
    base_joint = 0
    if urdf.base_link:
        base_joint, _ = _link_joint(full, urdf.base_link, where=where, source=source, column="base_link")
    tip_path = _ancestors(full, tip_joint)
    if urdf.tip_link and full.getJointId(joint_names[-1]) not in tip_path:
        raise InputError(f"tip_link {urdf.tip_link!r} does not move with the last joint {joint_names[-1]!r}",
                         source=source, column=urdf.tip_column)
    if base_joint and base_joint not in tip_path:
        raise InputError(f"tip_link {urdf.tip_link or joint_names[-1]!r} is not beyond base_link "
                         f"{urdf.base_link!r} in URDF {where}", source=source, column="base_link")
    chain = tip_path[tip_path.index(base_joint) + 1:] if base_joint else tip_path
    chain_names = [full.names[j] for j in chain]
    if list(joint_names) != chain_names:
        extra = [n for n in joint_names if n not in chain_names]
        if extra:
            raise InputError(f"URDF joint {extra[0]!r} is not on the chain from {urdf.base_link or 'the root'} to "
                             f"{urdf.tip_link or joint_names[-1]}; that chain's movable joints are "
                             f"{', '.join(chain_names)}", source=source, column="joint.name")
        absent = [n for n in chain_names if n not in joint_names]
        if absent:
            raise InputError(f"the chain's movable joint {absent[0]!r} has no [[joint]] table; name every movable "
                             f"joint from base to tip: {', '.join(chain_names)}", source=source, column="joint.name")
        raise InputError(f"the [[joint]] tables must name the serial chain of URDF {where} from base to tip, in order: "
                         f"{', '.join(chain_names)}", source=source, column="joint.name")
    locked = [j for j in range(1, full.njoints) if j not in chain]
    q_neutral = pin.neutral(full)
    model = pin.buildReducedModel(full, locked, q_neutral) if locked else full
    ids = [model.getJointId(n) for n in joint_names]
    data = model.createData()
    q0 = pin.neutral(model)
    pin.forwardKinematics(model, data, q0)
    pin.updateFramePlacements(model, data)
    pin.computeJointJacobians(model, data, q0)
    kinds, axes, lower, upper = _joint_axes(model, data, ids, joint_names, source=source)
    base_placement = pin.SE3.Identity()
    if urdf.base_link:
        # every joint between the root and base_link is locked at zero: base_link stands still
        base_placement = data.oMf[model.getFrameId(urdf.base_link)]
    placements = [pin.SE3(model.jointPlacements[i]) for i in ids]
    placements[0] = base_placement.actInv(placements[0])
    flange = pin.SE3.Identity()
    if urdf.tip_link:
        frame = model.frames[model.getFrameId(urdf.tip_link)]
        if frame.parentJoint != ids[-1]:
            raise InputError(f"tip_link {urdf.tip_link!r} does not move with the last joint {joint_names[-1]!r}",
                             source=source, column=urdf.tip_column)
        flange = pin.SE3(frame.placement)
    return UrdfChain(
        placements=tuple(placements), kinds=tuple(kinds),
        axes=np.array(axes), lower=np.array(lower), upper=np.array(upper),
        masses=np.array([model.inertias[i].mass for i in ids]),
        velocity=_given([model.velocityLimit[model.joints[i].idx_v] for i in ids]),
        effort=_given([model.effortLimit[model.joints[i].idx_v] for i in ids]),
        coms=np.array([model.inertias[i].lever for i in ids]),
        flange_placement=flange)


def _given(limits: Sequence[float]) -> np.ndarray:
    """URDF limits with 0 (what a URDF writes when it does not know) as nan."""
    out = np.array(limits, dtype=float)
    out[~(out > 0.0) | ~np.isfinite(out)] = np.nan
    return out
