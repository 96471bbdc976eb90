"""The robot's kinematic chain evaluated over whole paths at once.

Pinocchio computes one configuration per call; from Python each call costs
more than the kinematics itself, and a compensated path needs about ten
kinematic evaluations per sample. :class:`BatchedChain` evaluates the chain of
the robot's Pinocchio model (its joint placements, axes, body masses and
centres of mass, and frames, read from the ``pin.Model``; nothing of the
robot is written twice) over arrays of configurations with numpy, for the
three things compensation needs:

* frame positions (the tool point, the load point),
* the full static load torque ``J_f^T W - g(theta)`` of a wrench ``W`` on a
  frame (LOCAL_WORLD_ALIGNED Jacobian, docs/formats.md sign) and gravity,
* frame Jacobians (LOCAL_WORLD_ALIGNED).

For a revolute joint ``j`` with world axis ``z_j`` through ``o_j``, the torque
of the wrench ``(f, m)`` on the point ``p`` and of gravity on the bodies
``i >= j`` (masses ``m_i`` at ``c_i``) is::

    tau_j = z_j . [ (p - o_j) x f + m + (sum_i m_i c_i - (sum_i m_i) o_j) x g ]

which is ``J_f^T W - g(theta)`` with Pinocchio's generalised gravity ``g``
(``-sum_i J_ci^T m_i g``). tests/test_compensation_fast.py checks every output
against Pinocchio's ``forwardKinematics``, ``computeFrameJacobian`` and
``computeGeneralizedGravity`` to 1e-12.

A prismatic joint ``j`` (a track) moves its child along ``z_j`` by its coordinate and
carries ``tau_j = z_j . [ f + (sum_i m_i) g ]``: the force and the weight along its axis.

Arrays are "structure of arrays": joint coordinates ``(N, n)``, vectors ``(3, n)``,
so every numpy operation runs over contiguous rows of ``n`` samples. Each
joint's frame is turned so that its axis is the local z axis (a constant
rotation folded into the placements), so every joint is a rotation about z or a
translation along it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

#: Pinocchio joint kinds the batched chain evaluates, with their axis (the unaligned one carries its own)
_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0),
         "JointModelPX": (1.0, 0.0, 0.0), "JointModelPY": (0.0, 1.0, 0.0), "JointModelPZ": (0.0, 0.0, 1.0)}
_UNALIGNED = ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned")

#: rotation angle [rad] below which log6 takes the series of V^-1's coefficient (truncation
#: below 1e-16 there; the closed form above it loses less than eps / angle^2)
LOG_SERIES_RAD = 0.1

#: |theta - base| [rad] up to which cos/sin come from the base's by the addition theorem and a
#: Taylor series (terms to the 9th power: error below 3e-17 there); beyond it numpy's cos/sin
TAYLOR_LIMIT_RAD = 0.1


def _to_z(axis: np.ndarray) -> np.ndarray:
    """A rotation taking the local z axis onto ``axis`` (unit)."""
    return pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), axis).matrix()


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (..., 3, n) arrays (or a (3, 1) column)."""
    return np.stack((a[..., 1, :] * b[..., 2, :] - a[..., 2, :] * b[..., 1, :],
                     a[..., 2, :] * b[..., 0, :] - a[..., 0, :] * b[..., 2, :],
                     a[..., 0, :] * b[..., 1, :] - a[..., 1, :] * b[..., 0, :]), axis=-2)


def _cross_component(a: np.ndarray, b: np.ndarray, ax: int) -> np.ndarray:
    """Component ``ax`` of the row-wise cross product of (..., 3, n) arrays."""
    i, j = (ax + 1) % 3, (ax + 2) % 3
    return a[..., i, :] * b[..., j, :] - a[..., j, :] * b[..., i, :]


def _signed_permutation(rotation: np.ndarray, tol: float = 1e-14) -> tuple[tuple, tuple] | None:
    """``(p, sign)`` when column b of ``rotation`` is ``sign_b e_{p_b}`` to within ``tol`` (the
    placements of modified-DH robots, alpha a multiple of 90 degrees), else None."""
    p = np.argmax(np.abs(rotation), axis=0)
    sign = np.sign(rotation[p, np.arange(3)])
    exact = np.zeros((3, 3))
    exact[p, np.arange(3)] = sign
    if len(set(p.tolist())) != 3 or np.max(np.abs(rotation - exact)) > tol:
        return None
    return tuple(int(k) for k in p), tuple(float(g) for g in sign)


@dataclass(frozen=True, eq=False)
class Angles:
    """Joint angles ``theta`` (6, n) with their cosines and sines."""

    theta: np.ndarray
    cos: np.ndarray
    sin: np.ndarray

    @classmethod
    def of(cls, theta: np.ndarray) -> "Angles":
        return cls(theta, np.cos(theta), np.sin(theta))

    def near(self, theta: np.ndarray) -> "Angles":
        """Angles ``theta`` (6, n) close to these: cos/sin by the addition theorem from these,
        the small differences' by their Taylor series (far cheaper than numpy's cos/sin)."""
        d = theta - self.theta
        if not np.all(np.abs(d) <= TAYLOR_LIMIT_RAD):
            return Angles.of(theta)
        d2 = d * d
        cd = 1.0 + d2 * (-1.0 / 2 + d2 * (1.0 / 24 + d2 * (-1.0 / 720 + d2 * (1.0 / 40320))))
        sd = d * (1.0 + d2 * (-1.0 / 6 + d2 * (1.0 / 120 + d2 * (-1.0 / 5040 + d2 * (1.0 / 362880)))))
        return Angles(theta, self.cos * cd - self.sin * sd, self.sin * cd + self.cos * sd)

    def take(self, index: np.ndarray) -> "Angles":
        """The samples ``index``."""
        return Angles(self.theta[:, index], self.cos[:, index], self.sin[:, index])


@dataclass(frozen=True, eq=False)
class ChainState:
    """The chain at ``n`` configurations: joint axes ``z`` and origins ``o`` (N, 3, n) in the base
    frame, the last joint's rotations ``rot`` (3, 3, n) and the mass moments ``mc`` (N, 3, n),
    ``sum over bodies i >= j of m_i c_i`` (zero without masses); ``end`` (3, n) the origin of the
    last body (the last joint's origin, moved along its axis when it is prismatic)."""

    z: np.ndarray
    o: np.ndarray
    rot: np.ndarray
    mc: np.ndarray | None
    end: np.ndarray


class BatchedChain:
    """A serial chain of revolute and prismatic joints (the robot's Pinocchio model), evaluated over
    arrays of configurations. Immutable after construction; every call allocates its own work arrays."""

    def __init__(self, model: pin.Model) -> None:
        self.nq = model.nq
        njoints = model.njoints - 1
        if njoints != model.nq or model.nv != model.nq:
            raise ValueError("the batched chain needs one joint per coordinate")
        turns = [np.eye(3)]
        prismatic = []
        for i in range(1, njoints + 1):
            jm = model.joints[i]
            kind = jm.shortname()
            if model.parents[i] != i - 1 or not (kind in _AXES or kind in _UNALIGNED):
                raise ValueError(f"the batched chain needs a serial chain of revolute and prismatic joints, "
                                 f"joint {i} is {kind}")
            prismatic.append(kind.startswith("JointModelP"))
            axis = np.array(_AXES[kind] if kind in _AXES else jm.axis, dtype=float)
            turns.append(_to_z(axis / np.linalg.norm(axis)))
        # placements in the turned frames: R'_i = T_{i-1}^T R_i T_i, t'_i = T_{i-1}^T t_i
        rotations = [turns[i - 1].T @ model.jointPlacements[i].rotation @ turns[i] for i in range(1, njoints + 1)]
        self._rot_t = np.array([r.T for r in rotations])
        #: which joints are prismatic (a translation along their z, no rotation)
        self._prismatic = tuple(prismatic)
        self._perm = [_signed_permutation(r) for r in rotations]
        self._trans = np.array([turns[i - 1].T @ model.jointPlacements[i].translation for i in range(1, njoints + 1)])
        self._mass = np.array([model.inertias[i].mass for i in range(1, njoints + 1)])
        self._com = np.array([turns[i].T @ model.inertias[i].lever for i in range(1, njoints + 1)])
        self._total_mass = np.cumsum(self._mass[::-1])[::-1]          # sum of m_i over i >= j
        self._has_mass = bool(np.any(self._mass > 0.0))
        self._gravity = np.array(model.gravity.linear, dtype=float)
        # the frames on the last joint (the flange, the load point, the markers): their origins there
        self._frames = {fid: turns[-1].T @ frame.placement.translation for fid, frame in enumerate(model.frames)
                        if frame.parentJoint == njoints}
        self._frame_rot_t = {fid: (turns[-1].T @ frame.placement.rotation).T for fid, frame in enumerate(model.frames)
                             if frame.parentJoint == njoints}

    # ------------------------------------------------------------ the chain
    def state(self, ang: Angles, *, masses: bool = False) -> ChainState:
        """Joint axes and origins of every joint, and with ``masses`` the bodies' mass moments."""
        n = ang.theta.shape[1]
        last = self.nq
        z = np.empty((last, 3, n))
        o = np.empty((last, 3, n))
        mc = np.empty((last, 3, n)) if masses and self._has_mass else None
        rot = np.broadcast_to(np.eye(3)[:, :, None], (3, 3, n))
        tmp = np.empty((3, n))
        child = None               # the origin of the previous body (its joint's, moved along a prismatic axis)
        for i in range(last):
            if i == 0:
                o[0] = self._trans[0][:, None]
            else:
                np.matmul(self._trans[i], rot, out=o[i])
                o[i] += o[i - 1] if child is None else child
            if self._prismatic[i]:
                # a translation along the turned z axis: the body keeps the placement's rotation
                a = self._rot_t[i] @ rot
                new = np.ascontiguousarray(a)
                z[i] = a[:, 2]
                child = o[i] + z[i] * ang.theta[i]
                self._mass_moment(mc, i, new, child)
                rot = new
                continue
            child = None
            c, s = ang.cos[i], ang.sin[i]
            new = np.empty((3, 3, n))
            perm = self._perm[i]
            if perm is None:                       # a = rot R'_i (row r: R'_i^T applied to rot's row r)
                a = self._rot_t[i] @ rot
                a0, a1, a2, c0, s0, c1, s1 = a[:, 0], a[:, 1], a[:, 2], c, s, c, s
            else:                                  # R'_i a signed permutation: a[:, b] = sign_b rot[:, p_b]
                (p0, p1, p2), (g0, g1, g2) = perm
                a0, a1 = rot[:, p0], rot[:, p1]
                c0, s0, c1, s1 = (c, s, c, s) if g0 > 0 and g1 > 0 else (g0 * c, g0 * s, g1 * c, g1 * s)
                a2 = rot[:, p2] if g2 > 0 else -rot[:, p2]
            # new = a Rz(theta_i)
            np.multiply(a0, c0, out=new[:, 0])
            np.multiply(a1, s1, out=tmp)
            new[:, 0] += tmp
            np.multiply(a1, c1, out=new[:, 1])
            np.multiply(a0, s0, out=tmp)
            new[:, 1] -= tmp
            new[:, 2] = a2
            z[i] = a2
            self._mass_moment(mc, i, new, o[i])
            rot = new
        if mc is not None:
            for j in range(last - 2, -1, -1):
                mc[j] += mc[j + 1]
        return ChainState(z=z, o=o, rot=rot, mc=mc, end=o[-1] if child is None else child)

    def _mass_moment(self, mc: np.ndarray | None, i: int, rot: np.ndarray, origin: np.ndarray) -> None:
        """``m_i c_i`` of body ``i`` (its rotation and origin in base axes) into ``mc[i]``."""
        if mc is None:
            return
        if self._mass[i] > 0.0:
            np.matmul(self._com[i], rot, out=mc[i])
            mc[i] += origin
            mc[i] *= self._mass[i]
        else:
            mc[i] = 0.0

    def position(self, state: ChainState, frame_id: int) -> np.ndarray:
        """Base-frame position (3, n) of frame ``frame_id`` (a frame on the last joint)."""
        return state.end + np.matmul(self._frames[frame_id], state.rot)

    def rotation(self, state: ChainState, frame_id: int) -> np.ndarray:
        """Base-frame orientation (3, 3, n) of frame ``frame_id`` (a frame on the last joint)."""
        return self._frame_rot_t[frame_id] @ state.rot

    # ------------------------------------------------------------ statics
    def torque(self, state: ChainState, *, force: np.ndarray | None = None, moment: np.ndarray | None = None,
               frame_id: int | None = None) -> np.ndarray:
        """``J_f^T W - g(theta)`` (6, n) for the wrench ``force``, ``moment`` (3, n) on frame
        ``frame_id`` in base axes (without ``force``: ``-g`` alone); gravity when the state
        carries the mass moments (:meth:`state` with ``masses``).

        ``tau_j = sum_a [g_a (z_j x x_j)_a + f_a (z_j x (p - o_j))_a + m_a z_ja]`` with
        ``x_j = sum_i m_i c_i - (sum_i m_i) o_j``: only the components of ``g``, ``f`` and
        ``m`` that are not zero everywhere are evaluated."""
        z, o = state.z, state.o
        tau = np.zeros((self.nq, o.shape[2]))
        if state.mc is not None:
            x = state.mc - self._total_mass[:, None, None] * o
            for ax in np.flatnonzero(self._gravity):
                tau += self._gravity[ax] * _cross_component(z, x, ax)
        if force is not None:
            r = self.position(state, frame_id)[None] - o
            for ax in range(3):
                if np.any(force[ax]):
                    tau += force[ax] * _cross_component(z, r, ax)
                if np.any(moment[ax]):
                    tau += moment[ax] * z[:, ax]
        for j in np.flatnonzero(self._prismatic):
            # a prismatic joint carries the force and the weight of the bodies beyond it along its axis
            tau[j] = 0.0
            if state.mc is not None:
                tau[j] += self._total_mass[j] * (self._gravity @ z[j])
            if force is not None:
                tau[j] += np.einsum("an,an->n", z[j], force)
        return tau

    def point_velocity(self, state: ChainState, frame_id: int, rate: np.ndarray) -> np.ndarray:
        """``J_p(theta) rate`` (3, n): the motion of frame ``frame_id``'s origin for joint motions
        ``rate`` (6, n) (a small deflection: the point's first-order displacement)."""
        r = self.position(state, frame_id)[None] - state.o
        moved = state.z * rate[:, None, :]
        out = _cross(moved, r)
        for j in np.flatnonzero(self._prismatic):
            out[j] = moved[j]                 # a prismatic joint moves every point along its axis
        return out.sum(axis=0)

    def jacobian(self, state: ChainState, frame_id: int) -> np.ndarray:
        """LOCAL_WORLD_ALIGNED Jacobians (6, N, n) of frame ``frame_id``: rows 0-2 the velocity of
        its origin in base axes, rows 3-5 the angular velocity."""
        p = self.position(state, frame_id)
        jac = np.empty((6, self.nq, p.shape[1]))
        jac[:3] = np.moveaxis(_cross(state.z, p[None] - state.o), 0, 1)
        jac[3:] = np.moveaxis(state.z, 0, 1)
        for j in np.flatnonzero(self._prismatic):
            jac[:3, j] = state.z[j]
            jac[3:, j] = 0.0
        return jac


def log6_local(rot: np.ndarray, pos: np.ndarray, rot_target: np.ndarray, pos_target: np.ndarray) -> np.ndarray:
    """``log6(M^-1 M_target)`` (6, n), linear part first (Pinocchio's ``log6(...).vector``), for
    poses given as rotations (3, 3, n) and positions (3, n): the error a frame at ``M`` has to a
    target, in the frame's own axes. Near-zero angles by their series; angles beyond
    ``LOG_SERIES_RAD`` by the closed forms (up to pi, excluded)."""
    r = np.einsum("kan,kbn->abn", rot, rot_target)                 # R^T R_target
    p = np.einsum("kan,kn->an", rot, pos_target - pos)              # R^T (p_target - p)
    vee = np.stack((r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]))
    s = 0.5 * np.sqrt(np.sum(vee * vee, axis=0))                   # sin(angle)
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)                   # cos(angle)
    angle = np.arctan2(s, c)
    a2 = angle * angle
    with np.errstate(divide="ignore", invalid="ignore"):
        # angle / (2 sin) and (1 - (angle/2) cot(angle/2)) / angle^2, by series where the closed
        # forms lose digits (the second cancels to eps / angle^2)
        half_over_sin = np.where(angle < 1e-2, 0.5 + a2 * (1.0 / 12 + a2 * 7.0 / 720), angle / (2.0 * s))
        beta = np.where(angle < LOG_SERIES_RAD, 1.0 / 12 + a2 * (1.0 / 720 + a2 * (1.0 / 30240 + a2 / 1209600)),
                        (1.0 - angle * s / (2.0 * (1.0 - c))) / a2)
    w = half_over_sin * vee                                         # the rotation vector
    wxp = _cross(w, p)
    v = p - 0.5 * wxp + beta * _cross(w, wxp)                       # V(w)^-1 p
    return np.concatenate((v, w))
