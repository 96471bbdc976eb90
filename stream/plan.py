"""Everything the stream needs of the calibrated model, computed for the whole path before it starts.

The correction of a cycle is exact for the joint-spring model and cheap. The plan means the
pose the robot reaches running ``q`` without the process load (compensation's ``unloaded``
reference): the link angles ``theta*`` of the unloaded equilibrium at ``q``. A command
``q_c`` puts the loaded robot there when ``theta* = q_c + offset + c ⊙ tau(theta*, W)``; since
``theta* = q + offset + c ⊙ tau(theta*, 0)`` and the load torque is ``tau(theta, W) =
tau(theta, 0) + J(theta)^T W`` (docs/formats.md sign), the correction is

    q_c - q = - c ⊙ J(theta*)^T W,

linear in the wrench of the cycle. So per path sample the stream keeps ``-c ⊙ J(theta*)^T``
(n x 6), the unloaded torque ``tau(theta*, 0)`` and ``(J(theta*)^T)^+`` (the wrench from a
torque change, for the current-based force source), the load point's position Jacobian and
its rotation (to draw the correction, to turn a tool-mounted sensor's wrench into base
axes). They come from compensation's batched kernels (:class:`StaticKernel`,
:class:`BatchedChain`), as offline compensation computes them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.compensation.chain import Angles
from elastocal.compensation.model import CompensationModel, StaticKernel
from elastocal.errors import InputError


@dataclass(frozen=True, eq=False)
class StreamPlan:
    """The path and its precomputed model terms (arrays over the path's m samples, n joints)."""

    t: np.ndarray                   # (m,) path time [s], from 0
    q: np.ndarray                   # (m, n) planned joint coordinates [rad]
    gain: np.ndarray                # (m, n, 6) -c ⊙ J(theta*)^T: the correction per unit wrench [rad/(N, N·m)]
    tau_unloaded: np.ndarray        # (m, n) tau(theta*, 0): the joints' torque without the process [N·m]
    wrench_of_torque: np.ndarray    # (m, 6, n) (J(theta*)^T)^+ [(N, N·m)/(N·m)]
    position_jacobian: np.ndarray   # (m, 3, n) of the load point at theta* [m/rad]
    tool_rotation: np.ndarray       # (m, 3, 3) base <- load point frame at theta*
    load_point: np.ndarray          # (m, 3) where the plan puts the load point [m]
    torque_constants: np.ndarray | None   # (n,) xi [N·m/A]: load torque = xi * motor current (None: not described)

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])

    def locate(self, t_s: float) -> tuple[int, float]:
        """(i, w): path time ``t_s`` lies between samples i and i+1 at fraction w (held at the ends)."""
        t = self.t
        if t_s <= t[0]:
            return 0, 0.0
        if t_s >= t[-1]:
            return len(t) - 2 if len(t) > 1 else 0, 1.0 if len(t) > 1 else 0.0
        i = int(np.searchsorted(t, t_s, side="right")) - 1
        return i, float((t_s - t[i]) / (t[i + 1] - t[i]))

    def at(self, array: np.ndarray, i: int, w: float) -> np.ndarray:
        """``array`` (one of the per-sample arrays) interpolated linearly at (i, w)."""
        if w == 0.0 or len(array) == 1:
            return array[i]
        return array[i] + w * (array[i + 1] - array[i])


def build_plan(model: CompensationModel, t: np.ndarray, q: np.ndarray) -> StreamPlan:
    """The :class:`StreamPlan` of the planned path ``(t, q)`` for the calibrated ``model``."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(q, dtype=float)
    n = len(model.robot.joints)
    if q.ndim != 2 or q.shape[1] != n or len(t) != len(q) or len(t) < 1:
        raise InputError(f"the path needs times and {n} joint coordinates per sample")
    if np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(f"the path's times must increase; sample {i + 2} is at {t[i + 1]:g} s after {t[i]:g} s",
                         argument="path")
    kernel = StaticKernel(model)
    base = kernel.base_angles(q)
    target = kernel.equilibrium(q, np.zeros((len(q), 6)), base=base)          # theta* (m, n)
    tau0 = kernel.torque(target, np.zeros((len(q), 6)), base)                  # (m, n)
    chain = kernel.chain
    state = chain.state(Angles.of(target.T))
    jac = np.moveaxis(chain.jacobian(state, kernel.fid), 2, 0)                 # (m, 6, n), base axes
    jt = np.transpose(jac, (0, 2, 1))                                          # (m, n, 6)
    gain = -model.compliance[None, :, None] * jt
    wrench_of_torque = np.linalg.pinv(jt)                                      # (m, 6, n)
    rot = np.moveaxis(chain.rotation(state, kernel.fid), 2, 0)
    pos = chain.position(state, kernel.fid).T
    return StreamPlan(t=t - t[0], q=q, gain=gain, tau_unloaded=tau0, wrench_of_torque=wrench_of_torque,
                      position_jacobian=jac[:, :3, :], tool_rotation=rot, load_point=pos,
                      torque_constants=np.asarray(model.robot.torque_constants, dtype=float)
                      if model.robot.has_torque_constants else None)
