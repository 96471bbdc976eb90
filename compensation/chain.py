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

Arrays are "structure of arrays": joint angles ``(6, n)``, vectors ``(3, n)``,
so every numpy operation runs over contiguous rows of ``n`` samples. Each
joint's frame is turned so that its axis is the local z axis (a constant
rotation folded into the placements), so every joint is a rotation about z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

#: Pinocchio joint kinds the batched chain evaluates, with their axis (the unaligned one carries its own)
_AXES = {"JointModelRX": (1.0, 0.0, 0.0), "JointModelRY": (0.0, 1.0, 0.0), "JointModelRZ": (0.0, 0.0, 1.0)}

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
    """The chain at ``n`` configurations: joint axes ``z`` and origins ``o`` (6, 3, n) in the base
    frame, the last joint's rotations ``rot`` (3, 3, n) and the mass moments ``mc`` (6, 3, n),
    ``sum over bodies i >= j of m_i c_i`` (zero without masses)."""

    z: np.ndarray
    o: np.ndarray
    rot: np.ndarray
    mc: np.ndarray | None


class BatchedChain:
    """A serial chain of revolute joints (the robot's Pinocchio model), evaluated over arrays of
    configurations. Immutable after construction; every call allocates its own work arrays."""

    def __init__(self, model: pin.Model) -> None:
        self.nq = model.nq
        njoints = model.njoints - 1
        if njoints != model.nq or model.nv != model.nq:
            raise ValueError("the batched chain needs one revolute joint per coordinate")
        turns = [np.eye(3)]
        for i in range(1, njoints + 1):
            jm = model.joints[i]
            kind = jm.shortname()
            if model.parents[i] != i - 1 or not (kind in _AXES or kind == "JointModelRevoluteUnaligned"):
                raise ValueError(f"the batched chain needs a serial chain of revolute joints, joint {i} is {kind}")
            axis = np.array(_AXES[kind] if kind in _AXES else jm.axis, dtype=float)
            turns.append(_to_z(axis / np.linalg.norm(axis)))
        self._turns = turns
        # placements in the turned frames: R'_i = T_{i-1}^T R_i T_i, t'_i = T_{i-1}^T t_i
        self._rot_t = np.array([(turns[i - 1].T @ model.jointPlacements[i].rotation @ turns[i]).T
                                for i in range(1, njoints + 1)])
        self._trans = np.array([turns[i - 1].T @ model.jointPlacements[i].translation for i in range(1, njoints + 1)])
        self._mass = np.array([model.inertias[i].mass for i in range(1, njoints + 1)])
        self._com = np.array([turns[i].T @ model.inertias[i].lever for i in range(1, njoints + 1)])
        self._total_mass = np.cumsum(self._mass[::-1])[::-1]          # sum of m_i over i >= j
        self._has_mass = bool(np.any(self._mass > 0.0))
        g = np.array(model.gravity.linear, dtype=float)
        self._gravity_cross = -pin.skew(g)                            # v x g = G v
        # the frames on the last joint (the flange, the load point, the markers): their origins there
        self._frames = {fid: turns[-1].T @ frame.placement.translation for fid, frame in enumerate(model.frames)
                        if frame.parentJoint == njoints}

    # ------------------------------------------------------------ the chain
    def state(self, ang: Angles, *, masses: bool = False) -> ChainState:
        """Joint axes and origins of every joint, and with ``masses`` the bodies' mass moments."""
        n = ang.theta.shape[1]
        last = self.nq
        z = np.empty((last, 3, n))
        o = np.empty((last, 3, n))
        mc = np.empty((last, 3, n)) if masses and self._has_mass else None
        rot = None
        for i in range(last):
            if rot is None:
                a = np.broadcast_to(self._rot_t[i].T[:, :, None], (3, 3, n))
                o[i] = self._trans[i][:, None]
            else:
                a = self._rot_t[i] @ rot          # row r of the product: R'_i^T applied to rot's row r
                np.matmul(self._trans[i], rot, out=o[i])
                o[i] += o[i - 1]
            c, s = ang.cos[i], ang.sin[i]
            new = np.empty((3, 3, n))
            np.multiply(a[:, 0], c, out=new[:, 0])
            new[:, 0] += a[:, 1] * s
            np.multiply(a[:, 1], c, out=new[:, 1])
            new[:, 1] -= a[:, 0] * s
            new[:, 2] = a[:, 2]
            z[i] = a[:, 2]
            if mc is not None:
                if self._mass[i] > 0.0:
                    np.matmul(self._com[i], new, out=mc[i])
                    mc[i] += o[i]
                    mc[i] *= self._mass[i]
                else:
                    mc[i] = 0.0
            rot = new
        if mc is not None:
            for j in range(last - 2, -1, -1):
                mc[j] += mc[j + 1]
        return ChainState(z=z, o=o, rot=rot, mc=mc)

    def position(self, state: ChainState, frame_id: int) -> np.ndarray:
        """Base-frame position (3, n) of frame ``frame_id`` (a frame on the last joint)."""
        return state.o[-1] + np.matmul(self._frames[frame_id], state.rot)

    # ------------------------------------------------------------ statics
    def torque(self, state: ChainState, *, force: np.ndarray | None = None, moment: np.ndarray | None = None,
               frame_id: int | None = None) -> np.ndarray:
        """``J_f^T W - g(theta)`` (6, n) for the wrench ``force``, ``moment`` (3, n) on frame
        ``frame_id`` in base axes (without ``force``: ``-g`` alone); gravity when the state
        carries the mass moments (:meth:`state` with ``masses``)."""
        v = None
        if state.mc is not None:
            v = self._gravity_cross @ (state.mc - self._total_mass[:, None, None] * state.o)
        if force is not None:
            w = _cross(self.position(state, frame_id)[None] - state.o, force[None])
            w += moment[None]
            v = w if v is None else v + w
        if v is None:
            return np.zeros((self.nq, state.o.shape[2]))
        z = state.z
        return z[:, 0] * v[:, 0] + z[:, 1] * v[:, 1] + z[:, 2] * v[:, 2]

    def point_velocity(self, state: ChainState, frame_id: int, rate: np.ndarray) -> np.ndarray:
        """``J_p(theta) rate`` (3, n): the motion of frame ``frame_id``'s origin for joint motions
        ``rate`` (6, n) (a small deflection: the point's first-order displacement)."""
        r = self.position(state, frame_id)[None] - state.o
        return _cross(state.z * rate[:, None, :], r).sum(axis=0)

    def jacobian(self, state: ChainState, frame_id: int) -> np.ndarray:
        """LOCAL_WORLD_ALIGNED Jacobians (6, 6, n) of frame ``frame_id``: rows 0-2 the velocity of
        its origin in base axes, rows 3-5 the angular velocity."""
        p = self.position(state, frame_id)
        jac = np.empty((6, self.nq, p.shape[1]))
        jac[:3] = np.moveaxis(_cross(state.z, p[None] - state.o), 0, 1)
        jac[3:] = np.moveaxis(state.z, 0, 1)
        return jac
