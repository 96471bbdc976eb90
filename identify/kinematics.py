"""Kinematic (geometric) errors of a modified-DH robot and their identifiable set.

The real robot differs from its drawing by small errors of the DH table
(docs/physics.md, "Absolute positions"): per joint ``i`` the joint zero ``dq<i>``
[rad], the link length ``da<i>`` (of ``a_{i-1}``) [m], the offset along the axis
``dd<i>`` [m] and the twist ``dalpha<i>`` (of ``alpha_{i-1}``) [rad] (on a prismatic joint
``dq<i>`` is the zero of its travel [m], a slide along its axis, ``dd<i>`` moves
nothing: ``d_i`` is the travel, and ``dtheta<i>`` [rad] is the error of its fixed angle
``theta_i``, a turn about its axis, as a track's rails are mounted); where the
axes of joints ``i-1`` and ``i`` are parallel (``alpha_{i-1}`` = 0 or pi, joints
2-3 of an industrial arm) a small tilt about y cannot be written with the four
DH parameters, and Hayati's ``dbeta<i>`` [rad] joins them:
``T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta_i) Rz(theta_i) Tz(d_i)``. The
marker positions in the flange (``dx_<marker>``, ``dy_<marker>``,
``dz_<marker>`` [m]) are errors of the same kind.

:func:`corrected_robot` builds a new immutable :class:`Robot` (new Pinocchio
models) from the corrected table: the nominal robot is never changed and
reverted. :func:`position_jacobian` gives the derivatives of marker positions
in these parameters, exactly, from the frames of the corrected chain
(rotations about and translations along the joint and link axes).

Not every parameter is identifiable from absolute positions: the tracker
frame absorbs the joint-1 zero and the base offsets, the marker positions
absorb the joint-6 zero and ``dd6``, and on parallel axes ``dd<i>`` is the same
motion as ``dd<i-1>``. :func:`identifiable_set` keeps the columns of the
stacked regressor that a QR with columns taken in a fixed priority order finds
independent (FIGAROH's base parameters) and says which kept parameters absorb
each dropped one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.kinds import JointKind
from elastocal.model.robot import MARKER_PREFIX, Robot, RobotData
from elastocal.identify.urdf_geometry import UNITS as URDF_UNITS
from elastocal.identify.urdf_geometry import (
    URDF_KINDS,
    corrected_urdf_robot,
    describe_urdf,
    urdf_parameter_names,
    urdf_position_jacobian,
)

#: DH error kinds per joint, in the order of the parameter vector
DH_KINDS = ("dq", "da", "dd", "dalpha", "dbeta", "dtheta")
UNITS = {"dq": "rad", "da": "m", "dd": "m", "dalpha": "rad", "dbeta": "rad", "dtheta": "rad", "marker": "m",
         **URDF_UNITS}
#: every kind: the DH ones, then a URDF joint origin's six (identify/urdf_geometry.py)
ALL_KINDS = DH_KINDS + URDF_KINDS[1:]
#: |sin(alpha_{i-1})| below this: the axes of joints i-1 and i are parallel
PARALLEL_TOL = 1e-6
#: a column whose part independent of the columns kept before it is below this
#: fraction of its norm is absorbed (relative to the scaled regressor)
ABSORB_TOL = 1e-5
#: a column this small next to the largest (both whitened, so in the same units) is zero
ZERO_COLUMN = 1e-9

WORDS = {
    "rx": "the frame rotation about x", "ry": "the frame rotation about y", "rz": "the frame rotation about z",
    "tx": "the frame translation along x", "ty": "the frame translation along y",
    "tz": "the frame translation along z",
}


def parallel_joints(robot: Robot) -> tuple[int, ...]:
    """Joints i (1-based, i >= 2) whose axis is parallel to the axis of joint i-1."""
    if robot.urdf is not None:
        return ()
    return tuple(i for i, j in enumerate(robot.joints, start=1)
                 if i >= 2 and abs(math.sin(j.alpha)) < PARALLEL_TOL)


def parameter_names(robot: Robot, markers: Sequence[str]) -> tuple[str, ...]:
    """The full set of kinematic parameters of ``robot`` with these markers."""
    if robot.urdf is not None:            # each joint origin's six errors and the offsets
        return urdf_parameter_names(robot, markers)
    parallel = parallel_joints(robot)
    names = []
    for i, joint in enumerate(robot.joints, start=1):
        # dbeta only where the axes are parallel; dtheta only where theta is fixed (a prismatic joint:
        # a revolute joint's theta error is its zero, dq)
        names += [f"{k}{i}" for k in DH_KINDS if (k != "dbeta" or i in parallel)
                  and (k != "dtheta" or joint.kind is JointKind.PRISMATIC)]
    for m in markers:
        names += [f"dx_{m}", f"dy_{m}", f"dz_{m}"]
    return tuple(names)


def unit_of(name: str, robot: Robot | None = None) -> str:
    """The unit of a kinematic parameter (``dq`` of a prismatic joint of ``robot`` is a length)."""
    if name.startswith(("dx_", "dy_", "dz_")):
        return UNITS["marker"]
    kind = name.rstrip("0123456789")
    if kind == "dq" and robot is not None and robot.joints[int(name[2:]) - 1].kind is JointKind.PRISMATIC:
        return "m"
    return UNITS[kind]


def describe(name: str) -> str:
    """A parameter's meaning in words."""
    if name in WORDS:
        return WORDS[name]
    if name.startswith(("dx_", "dy_", "dz_")):
        return f"the {name[1]} position of marker {name[3:]} in the flange"
    kind, joint = name.rstrip("0123456789"), name[len(name.rstrip("0123456789")):]
    if describe_urdf(kind, joint):
        return describe_urdf(kind, joint)
    return {"dq": f"the zero of joint {joint}", "da": f"the link length a{int(joint) - 1}",
            "dd": f"the offset d{joint} along axis {joint}", "dalpha": f"the twist alpha{int(joint) - 1}",
            "dbeta": f"the tilt beta{joint} of axis {joint} (parallel to axis {int(joint) - 1})",
            "dtheta": f"the fixed angle theta{joint} of sliding joint {joint}, about its axis"}.get(kind, name)


def _split(names: Sequence[str], values: Sequence[float]) -> tuple[dict[tuple[str, int], float], dict[str, np.ndarray]]:
    dh: dict[tuple[str, int], float] = {}
    markers: dict[str, np.ndarray] = {}
    for name, v in zip(names, values):
        if name.startswith(("dx_", "dy_", "dz_")):
            markers.setdefault(name[3:], np.zeros(3))["xyz".index(name[1])] += float(v)
        else:
            kind = name.rstrip("0123456789")
            dh[(kind, int(name[len(kind):]))] = dh.get((kind, int(name[len(kind):])), 0.0) + float(v)
    return dh, markers


def corrected_robot(robot: Robot, names: Sequence[str], values: Sequence[float]) -> Robot:
    """A new robot whose DH table and markers carry the errors ``names = values``
    (names as :func:`parameter_names`; absent ones are zero)."""
    if robot.urdf is not None:
        return corrected_urdf_robot(robot, names, values)
    dh, markers = _split(names, values)
    for m in markers:
        robot.frame_id(m)
    joints = []
    for i, j in enumerate(robot.joints, start=1):
        joints.append(replace(j, offset=j.offset + dh.get(("dq", i), 0.0), a=j.a + dh.get(("da", i), 0.0),
                              d=j.d + dh.get(("dd", i), 0.0), alpha=j.alpha + dh.get(("dalpha", i), 0.0),
                              beta=j.beta + dh.get(("dbeta", i), 0.0), theta=j.theta + dh.get(("dtheta", i), 0.0),
                              lower=j.lower, upper=j.upper))
    tool = replace(robot.tool, flange_p_markers=tuple(
        (m, tuple(float(x) for x in np.array(p) + markers.get(m, np.zeros(3)))) for m, p in robot.tool.flange_p_markers))
    return replace(robot, joints=tuple(joints), tool=tool)


@dataclass(frozen=True, eq=False)
class Columns:
    """The kinematic parameters ``names`` decoded once (kind, joint, marker, axis)
    for :func:`position_jacobian`."""

    names: tuple[str, ...]
    kind: np.ndarray        # (n,) index into DH_KINDS, or -1 for a marker coordinate
    joint: np.ndarray       # (n,) 1-based joint (0 for markers)
    marker: np.ndarray      # (n,) index into the markers (-1 for DH errors)
    axis: np.ndarray        # (n,) x, y, z of a marker coordinate


def columns(names: Sequence[str], markers: Sequence[str]) -> Columns:
    kind, joint, marker, axis = [], [], [], []
    for name in names:
        if name.startswith(("dx_", "dy_", "dz_")):
            kind.append(-1)
            joint.append(0)
            marker.append(list(markers).index(name[3:]) if name[3:] in markers else -2)
            axis.append("xyz".index(name[1]))
        else:
            k = name.rstrip("0123456789")
            kind.append(ALL_KINDS.index(k))
            joint.append(int(name[len(k):]))
            marker.append(-1)
            axis.append(0)
    return Columns(tuple(names), np.array(kind, dtype=int), np.array(joint, dtype=int), np.array(marker, dtype=int),
                   np.array(axis, dtype=int))


def _prismatic_columns(robot: Robot, cols: Columns) -> tuple[np.ndarray, np.ndarray]:
    """(n,) bool twice: the ``dq`` columns of prismatic joints, whose zero is a length along the
    joint's axis (``d_i = q_i + offset``: a translation, not a turn about it), and their ``dd``
    columns, which move nothing (``d_i`` is the joint's travel, the table's ``d`` unused)."""
    prismatic = np.array([False] + [jt.kind is JointKind.PRISMATIC for jt in robot.joints])
    on_prismatic = prismatic[cols.joint] & (cols.kind >= 0)
    return (on_prismatic & (cols.kind == DH_KINDS.index("dq")),
            on_prismatic & (cols.kind == DH_KINDS.index("dd")))


def position_jacobian(robot: Robot, theta: np.ndarray, markers: Sequence[str],
                      names: Sequence[str], cols: Columns | None = None,
                      link_angles: np.ndarray | None = None,
                      data: RobotData | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Base positions (M, 3) of ``markers`` at the DH angles ``theta`` of the
    (corrected) ``robot``, and their derivatives (M, 3, len(names)) in the
    kinematic parameters ``names`` (``cols``: the same names decoded once).
    With ``link_angles`` (the 4 link springs), on the chain with its links bent. ``data``: the
    caller's work buffers (``robot.create_data()``), made once for a loop of calls."""
    cols = columns(names, markers) if cols is None else cols
    theta = np.asarray(theta, dtype=float)
    nj = len(robot.joints)
    if robot.urdf is not None:
        if link_angles is not None:
            raise InputError("kinematic_errors with link_compliance needs a modified-DH robot (a URDF robot's "
                             "bent links are not modelled)", argument="model")
        pos, jac = urdf_position_jacobian(robot, theta[None], markers, cols, ALL_KINDS, data)
        return pos[0], jac[0]
    if link_angles is None:
        model, config, ids = robot.model, theta, list(range(nj + 1))
        first = list(range(1, nj + 1))          # the Pinocchio joint that carries joint i's DH placement
    else:       # the springs sit at joint i's origin, after its DH placement: parents stay the joints
        model, config = robot.link_model, robot.theta_links(theta, link_angles)
        ids = [0, *(int(k) + 1 for k in robot.actuated_in_link_model)]
        first = [ids[i - 1] + 1 for i in range(1, nj + 1)]
    data = (robot.create_data() if data is None else data).of(link_angles is not None)
    pin.forwardKinematics(model, data, config)
    pin.updateFramePlacements(model, data)
    pos = np.array([data.oMf[model.getFrameId(MARKER_PREFIX + m)].translation for m in markers])
    rot = np.array([data.oMi[i].rotation for i in ids])          # (7, 3, 3), 0 = base
    trans = np.array([data.oMi[i].translation for i in ids])
    # the direction of Tz(d_i): z after joint i's placement, before any spring and theta_i
    z_dd = np.array([np.zeros(3)] + [data.oMi[ids[i - 1]].rotation @ model.jointPlacements[first[i - 1]].rotation[:, 2]
                                     for i in range(1, nj + 1)])
    alpha = np.array([0.0] + [j.alpha for j in robot.joints])
    a = np.array([0.0] + [j.a for j in robot.joints])
    n = len(cols.names)
    jac = np.zeros((len(markers), 3, n))
    k, j = cols.kind, cols.joint
    slide, fixed_d = _prismatic_columns(robot, cols)
    # translations: along z_i before any spring (dd), along the joint's own axis after the springs it
    # rides on (a prismatic joint's zero dq: its travel's), along x_{i-1} (da)
    sel = k == DH_KINDS.index("dd")
    jac[:, :, sel] = z_dd[j[sel]].T[None]
    jac[:, :, fixed_d] = 0.0
    jac[:, :, slide] = rot[j[slide], :, 2].T[None]
    sel = k == DH_KINDS.index("da")
    jac[:, :, sel] = rot[j[sel] - 1, :, 0].T[None]
    # rotations: about z_i through o_i (dq), x_{i-1} through o_{i-1} (dalpha), Hayati's y (dbeta)
    axes = np.zeros((n, 3))
    origins = np.zeros((n, 3))
    sel = (k == DH_KINDS.index("dq")) & ~slide
    axes[sel], origins[sel] = rot[j[sel], :, 2], trans[j[sel]]
    sel_a = k == DH_KINDS.index("dalpha")
    axes[sel_a], origins[sel_a] = rot[j[sel_a] - 1, :, 0], trans[j[sel_a] - 1]
    sel_b = k == DH_KINDS.index("dbeta")
    if sel_b.any():
        jb = j[sel_b]
        local = np.stack([np.zeros(len(jb)), np.cos(alpha[jb]), np.sin(alpha[jb])], axis=1)
        axes[sel_b] = np.einsum("nij,nj->ni", rot[jb - 1], local)
        origins[sel_b] = trans[jb - 1] + a[jb][:, None] * rot[jb - 1, :, 0]
    # a prismatic joint's fixed theta: a turn about its sliding axis (z after its DH placement, before
    # any spring), through the placement's origin, a point of that axis
    sel_t = k == DH_KINDS.index("dtheta")
    axes[sel_t] = z_dd[j[sel_t]]
    origins[sel_t] = np.array([data.oMi[first[i - 1]].translation for i in j[sel_t]]).reshape(-1, 3)
    rotation = sel | sel_a | sel_b | sel_t
    if rotation.any():
        arm = pos[:, None, :] - origins[None, rotation, :]                     # (M, R, 3)
        jac[:, :, rotation] = np.cross(axes[None, rotation, :], arm).transpose(0, 2, 1)
    # marker coordinates in the flange
    for c in np.flatnonzero((k == -1) & (cols.marker >= 0)):
        jac[cols.marker[c], :, c] = rot[nj][:, cols.axis[c]]
    return pos, jac


def position_jacobian_batch(robot: Robot, theta: np.ndarray, markers: Sequence[str],
                            names: Sequence[str], cols: Columns | None = None,
                            data: RobotData | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`position_jacobian` of many configurations at once, on the chain without link springs:
    base positions (S, M, 3) at the DH angles ``theta`` (S, N) and their derivatives (S, M, 3, n).
    One forward kinematics per configuration, the rest in whole-array operations (the fit of a
    geometric calibration table evaluates hundreds of poses per iteration)."""
    cols = columns(names, markers) if cols is None else cols
    theta = np.asarray(theta, dtype=float)
    if robot.urdf is not None:
        return urdf_position_jacobian(robot, theta, markers, cols, ALL_KINDS, data)
    ns, nj = theta.shape[0], len(robot.joints)
    model = robot.model
    data = (robot.create_data() if data is None else data).rigid
    fids = [model.getFrameId(MARKER_PREFIX + m) for m in markers]
    nm = len(markers)
    pos = np.empty((ns, nm, 3))
    rot = np.empty((ns, nj + 1, 3, 3))
    trans = np.empty((ns, nj + 1, 3))
    for s_ in range(ns):
        pin.forwardKinematics(model, data, theta[s_])
        for i in range(nj + 1):
            rot[s_, i] = data.oMi[i].rotation
            trans[s_, i] = data.oMi[i].translation
        for m, fid in enumerate(fids):
            pos[s_, m] = pin.updateFramePlacement(model, data, fid).translation
    # the direction of Tz(d_i): z after joint i's placement, before theta_i
    place_z = np.array([model.jointPlacements[i].rotation[:, 2] for i in range(1, nj + 1)])     # (N, 3)
    z_dd = np.zeros((ns, nj + 1, 3))
    z_dd[:, 1:] = np.einsum("sjab,jb->sja", rot[:, :nj], place_z)
    alpha = np.array([0.0] + [j.alpha for j in robot.joints])
    a = np.array([0.0] + [j.a for j in robot.joints])
    n = len(cols.names)
    jac = np.zeros((ns, nm, 3, n))
    k, j = cols.kind, cols.joint
    slide, fixed_d = _prismatic_columns(robot, cols)
    sel = (k == DH_KINDS.index("dd")) | slide
    jac[:, :, :, sel] = z_dd[:, j[sel]].transpose(0, 2, 1)[:, None]
    jac[:, :, :, fixed_d] = 0.0
    sel = k == DH_KINDS.index("da")
    rot_x, rot_z = rot[..., 0], rot[..., 2]                 # (S, N + 1, 3): the frames' x and z axes
    jac[:, :, :, sel] = rot_x[:, j[sel] - 1].transpose(0, 2, 1)[:, None]
    axes = np.zeros((ns, n, 3))
    origins = np.zeros((ns, n, 3))
    sel = (k == DH_KINDS.index("dq")) & ~slide
    axes[:, sel], origins[:, sel] = rot_z[:, j[sel]], trans[:, j[sel]]
    sel_a = k == DH_KINDS.index("dalpha")
    axes[:, sel_a], origins[:, sel_a] = rot_x[:, j[sel_a] - 1], trans[:, j[sel_a] - 1]
    sel_b = k == DH_KINDS.index("dbeta")
    if sel_b.any():
        jb = j[sel_b]
        local = np.stack([np.zeros(len(jb)), np.cos(alpha[jb]), np.sin(alpha[jb])], axis=1)
        axes[:, sel_b] = np.einsum("snij,nj->sni", rot[:, jb - 1], local)
        origins[:, sel_b] = trans[:, jb - 1] + a[jb][None, :, None] * rot_x[:, jb - 1]
    # a prismatic joint's fixed theta: a turn about its sliding axis through its frame's origin (on that axis)
    sel_t = k == DH_KINDS.index("dtheta")
    axes[:, sel_t], origins[:, sel_t] = z_dd[:, j[sel_t]], trans[:, j[sel_t]]
    rotation = sel | sel_a | sel_b | sel_t
    if rotation.any():
        arm = pos[:, :, None, :] - origins[:, None, rotation, :]                 # (S, M, R, 3)
        jac[:, :, :, rotation] = np.cross(axes[:, None, rotation, :], arm).transpose(0, 1, 3, 2)
    for c in np.flatnonzero((k == -1) & (cols.marker >= 0)):
        jac[:, cols.marker[c], :, c] = rot[:, nj, :, cols.axis[c]]
    return pos, jac


@dataclass(frozen=True)
class IdentifiableSet:
    """Which columns of a regressor the data determine, and what absorbs the rest."""

    names: tuple[str, ...]                        # the regressor's columns
    keep: np.ndarray                              # (n,) bool
    #: dropped name -> ((kept name, coefficient), ...): the dropped column is this
    #: combination of kept columns, so a kept parameter's estimate holds
    #: ``coefficient * dropped`` besides its own value
    absorbed_by: Mapping[str, tuple[tuple[str, float], ...]]

    def base_value(self, truth: Mapping[str, float]) -> dict[str, float]:
        """What each kept parameter estimates when the true values are ``truth``
        (its own value plus the dropped parameters it absorbs), to first order."""
        out = {n: float(truth.get(n, 0.0)) for n, k in zip(self.names, self.keep) if k}
        for dropped, combo in self.absorbed_by.items():
            for kept, coef in combo:
                out[kept] += coef * float(truth.get(dropped, 0.0))
        return out


def identifiable_set(a: np.ndarray, names: Sequence[str], priority: Sequence[str]) -> IdentifiableSet:
    """Columns of ``a`` kept in the order ``priority`` (names; the rest after
    them) while each adds to the rank; each dropped column expressed by the
    kept ones (least squares on the column-scaled regressor)."""
    names = list(names)
    order = [names.index(n) for n in priority if n in names]
    order += [k for k in range(len(names)) if k not in order]
    scale = np.linalg.norm(a, axis=0)
    # a column that is rounding noise next to the others moves nothing (a marker on the axis it turns about)
    scale = np.where(scale > ZERO_COLUMN * float(np.max(scale, initial=0.0)), scale, 0.0)
    scaled = a / np.where(scale > 0, scale, 1.0)
    keep = np.zeros(len(names), dtype=bool)
    basis = np.zeros((a.shape[0], 0))
    for k in order:
        if scale[k] == 0.0:
            continue
        col = scaled[:, k]
        resid = col - basis @ (basis.T @ col)
        resid = resid - basis @ (basis.T @ resid)       # twice is enough (Gram-Schmidt)
        if np.linalg.norm(resid) > ABSORB_TOL:
            keep[k] = True
            basis = np.column_stack([basis, resid / np.linalg.norm(resid)])
    absorbed: dict[str, tuple[tuple[str, float], ...]] = {}
    kept_idx = np.flatnonzero(keep)
    dropped = np.flatnonzero(~keep)
    # each dropped column as a combination of the kept ones (one solve of the scaled normal equations)
    sk = scaled[:, kept_idx]
    coefs = np.zeros((len(kept_idx), len(dropped)))
    if dropped.size and kept_idx.size:
        coefs = np.linalg.solve(sk.T @ sk, sk.T @ scaled[:, dropped]) / np.where(
            scale[kept_idx] > 0, scale[kept_idx], 1.0)[:, None] * np.where(scale[dropped] > 0, scale[dropped], 1.0)
    for col, k in enumerate(dropped):
        if scale[k] == 0.0:
            absorbed[names[k]] = ()
            continue
        coef = coefs[:, col]
        weight = np.abs(coef) * scale[kept_idx]
        big = np.flatnonzero(weight > 1e-3 * max(float(weight.max()), 1e-300))
        big = big[np.argsort(-weight[big])]
        absorbed[names[k]] = tuple((names[kept_idx[b]], float(coef[b])) for b in big)
    return IdentifiableSet(names=tuple(names), keep=keep, absorbed_by=absorbed)


def absorbed_words(dropped: str, combo: Sequence[tuple[str, float]], *, limit: int = 3) -> str:
    """``dq1 is absorbed by the frame rotation about z (rz)``."""
    if not combo:
        return f"{dropped} ({describe(dropped)}) does not change the positions these data hold"
    parts = [f"{describe(n)} ({n})" for n, _ in combo[:limit]]
    more = f" and {len(combo) - limit} more" if len(combo) > limit else ""
    return f"{dropped} ({describe(dropped)}) is absorbed by {', '.join(parts)}{more}"
