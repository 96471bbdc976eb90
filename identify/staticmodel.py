"""The static model of one dataset: what the deflection fit (identify/static.py), the
absolute fit (identify/absolute.py), the calibration check (identify/accuracy.py) and
experiment design (identify/design_matrix.py) evaluate.

A :class:`Problem` holds a robot, a dataset, the effects of a model and the
computation's Pinocchio work buffers; from it come each state's gear torques
(:func:`state_torques`), the :class:`StaticContext` the effects build their bases on
(:func:`static_context`), the bases of the deflections (:func:`static_bases`) and of the
absolute positions (:func:`absolute_bases`), and the predicted deflections with their
Jacobian (:func:`evaluate`) or absolute positions (:func:`absolute_positions`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.identify.dataset import StaticDataset
from elastocal.model.effects.base import Effect, StaticBasis, StaticContext
from elastocal.model.kinds import KinematicForm, TorqueSource, expect
from elastocal.model.robot import LOAD_FRAME, Robot, RobotData


@dataclass(frozen=True, eq=False)
class Problem:
    robot: Robot
    ds: StaticDataset
    effects: tuple[Effect, ...]
    torque: TorqueSource
    form: KinematicForm
    frames: tuple[str, ...]
    #: this problem's Pinocchio work buffers (made by the robot, used by every kinematics call
    #: of the solve: creating a Data costs more than the kinematics it serves)
    data: RobotData | None = None

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque, "torque")
        expect(KinematicForm, self.form, "form")
        if self.data is None:
            object.__setattr__(self, "data", self.robot.create_data())
        elif not self.data.belongs_to(self.robot):
            raise ValueError("the work buffers were made by another robot")

    @property
    def torque_at_deflection(self) -> bool:
        """Whether an effect of the model takes the torques at the deflected configuration
        (``Effect.torque_at_deflection``): a force-based fit then recomputes them as it iterates."""
        return any(eff.torque_at_deflection for eff in self.effects)

    @cached_property
    def nominal_theta(self) -> np.ndarray:
        """(S, N) link-side angles of every state's commanded pose (``robot.theta``)."""
        return self.ds.q[self.ds.state_pose] + self.robot.offsets

    @cached_property
    def nominal_kinematics(self) -> tuple[np.ndarray, np.ndarray]:
        """Marker positions (P, M, 3) and position Jacobians (P, M, 3, nv) of every pose
        at its commanded configuration: computed once per problem, read by the
        first-order form, the noise covariance and its rank."""
        theta = link_configurations(self.robot, self.ds.q + self.robot.offsets)
        return kinematics_batch(self.robot, theta, self.frames, self.data)

    @cached_property
    def load_jacobians(self) -> np.ndarray:
        """(P, 6, nv) Jacobian of the load point of every pose at its commanded
        configuration (LOCAL_WORLD_ALIGNED, as ``Robot.jacobians``)."""
        model, data = self.robot.link_model, self.data.links
        fid = model.getFrameId(LOAD_FRAME)
        theta = link_configurations(self.robot, self.ds.q + self.robot.offsets)
        out = np.empty((len(theta), 6, model.nv))
        for pi, th in enumerate(theta):
            pin.computeJointJacobians(model, data, th)
            pin.updateFramePlacements(model, data)
            out[pi] = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        return out

    @cached_property
    def pose_deflections(self) -> tuple[np.ndarray, ...]:
        """The deflection indices of each pose (ascending), one array per pose."""
        pose_of = self.ds.state_pose[self.ds.defl_state]
        order = np.argsort(pose_of, kind="stable")
        bounds = np.searchsorted(pose_of[order], np.arange(len(self.ds.pose_ids) + 1))
        return tuple(order[bounds[i]:bounds[i + 1]] for i in range(len(self.ds.pose_ids)))

    @cached_property
    def state_rank(self) -> tuple[np.ndarray, np.ndarray]:
        """Each state's place among its pose's states (ascending), and each pose's number of states."""
        sp = self.ds.state_pose
        order = np.argsort(sp, kind="stable")
        counts = np.bincount(sp, minlength=len(self.ds.pose_ids))
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.empty(len(sp), dtype=np.intp)
        rank[order] = np.arange(len(sp)) - start[sp[order]]
        return rank, counts


def link_configurations(robot: Robot, theta: np.ndarray, link_angles: np.ndarray | None = None) -> np.ndarray:
    """``Robot.theta_links`` of many states at once: (S, N + springs) from (S, N) and (S, springs)."""
    out = np.zeros((len(theta), len(robot.link_joint_order)))
    out[:, robot.actuated_in_link_model] = theta
    if link_angles is not None:
        out[:, robot.springs_in_link_model] = link_angles
    return out


def state_torques(pr: Problem, theta_states: np.ndarray | None) -> np.ndarray:
    """Absolute gear torque (S, N) of each state."""
    robot, ds = pr.robot, pr.ds
    if pr.torque is TorqueSource.CURRENT:
        return ds.state_currents * robot.torque_constants
    comp = robot.compensator.nominal_parameters() if robot.compensator is not None else None
    theta = pr.nominal_theta if theta_states is None else np.ascontiguousarray(theta_states, dtype=float)
    # Robot.load_torque's J_f^T W - g(theta) - M e2, step for step, on the problem's Data (each
    # Pinocchio call below overwrites what the next one reads)
    model, data = robot.model, pr.data.rigid
    fid = model.getFrameId(LOAD_FRAME)
    world = pin.LOCAL_WORLD_ALIGNED
    c = robot.compensator.index if comp is not None else 0
    offset_c = robot.joints[c].offset
    out = np.empty((ds.n_states, robot.n_joints))
    for s in range(ds.n_states):
        th = theta[s]
        tau = np.zeros(model.nv)
        pin.computeJointJacobians(model, data, th)
        pin.updateFramePlacements(model, data)
        tau += pin.getFrameJacobian(model, data, fid, world).T @ ds.state_wrench[s]
        if robot.has_masses:
            tau -= pin.computeGeneralizedGravity(model, data, th)
        if comp is not None:
            tau[c] -= float(robot.compensator.torque(th[c] - offset_c, comp))
        out[s] = tau
    return out


def static_context(pr: Problem, tau: np.ndarray, estimate: np.ndarray | None = None) -> StaticContext:
    robot, ds = pr.robot, pr.ds
    delta_tau = tau - tau[ds.state_ref]
    # every state at once: the wrench change the torque change carries (J_act^T dW = dtau), and
    # what it puts on the link springs (J_spr^T dW)
    jac = pr.load_jacobians[ds.state_pose]
    j_act_t = np.swapaxes(jac[:, :, robot.actuated_in_link_model], 1, 2)
    j_spr_t = np.swapaxes(jac[:, :, robot.springs_in_link_model], 1, 2)
    if pr.torque is TorqueSource.CURRENT and robot.n_joints != 6:
        # N joint torques of one 6-component wrench: least squares (N > 6), the least wrench (N < 6)
        delta_wrench = np.stack([np.linalg.lstsq(j_act_t[s], delta_tau[s], rcond=None)[0]
                                 for s in range(ds.n_states)])
    elif pr.torque is TorqueSource.CURRENT:
        try:
            delta_wrench = np.linalg.solve(j_act_t, delta_tau[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:       # a singular pose: least squares for that one
            delta_wrench = np.empty((ds.n_states, 6))
            for s in range(ds.n_states):
                try:
                    delta_wrench[s] = np.linalg.solve(j_act_t[s], delta_tau[s])
                except np.linalg.LinAlgError:
                    delta_wrench[s] = np.linalg.lstsq(j_act_t[s], delta_tau[s], rcond=None)[0]
    else:
        delta_wrench = ds.state_wrench - ds.state_wrench[ds.state_ref]
    delta_link = (j_spr_t @ delta_wrench[:, :, None])[:, :, 0]
    # the whole wrench: with currents the change is all they show (the reference carries none)
    wrench = delta_wrench.copy() if pr.torque is TorqueSource.CURRENT else ds.state_wrench.copy()
    torque_noise = None
    if ds.sigma_current is not None and pr.torque is TorqueSource.CURRENT:
        torque_noise = robot.torque_constants * ds.sigma_current / np.sqrt(ds.state_n_currents)[:, None]
    return StaticContext(tau=tau, delta_tau=delta_tau, delta_link_moment=delta_link,
                         delta_wrench=delta_wrench, wrench=wrench, torque_noise=torque_noise, robot=robot,
                         dataset=ds,
                         state_is_reference=ds.state_ref == np.arange(ds.n_states),
                         deflection_dt=ds.defl_dt, n_deflections=ds.n_deflections, torque_source=pr.torque,
                         form=pr.form, estimate=estimate,
                         estimate_names=tuple(p for eff in pr.effects for p in eff.parameters), data=pr.data)


def static_bases(pr: Problem, ctx: StaticContext) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ds = pr.ds
    thetas, links, adds = [], [], []
    for eff in pr.effects:
        p = len(eff.parameters)
        if p == 0:
            continue
        b = eff.static_basis(ctx) if eff.static_basis is not None else StaticBasis()
        thetas.append(b.theta if b.theta is not None else np.zeros((ds.n_states, pr.robot.n_joints, p)))
        links.append(b.links if b.links is not None
                     else np.zeros((ds.n_states, len(pr.robot.link_spring_names), p)))
        adds.append(b.add if b.add is not None else np.zeros((ds.n_deflections, 3, p)))
    return np.concatenate(thetas, axis=2), np.concatenate(links, axis=2), np.concatenate(adds, axis=2)


def kinematics(robot: Robot, theta10: np.ndarray, frames: Sequence[str],
                data: RobotData) -> tuple[np.ndarray, np.ndarray]:
    """Positions (M, 3) and position Jacobians (M, 3, 10) of frames in the link model."""
    pos, jac = kinematics_batch(robot, np.asarray(theta10, dtype=float)[None], tuple(frames), data)
    return pos[0], jac[0]


def kinematics_batch(robot: Robot, theta10: np.ndarray, frames: tuple[str, ...],
                      data: RobotData) -> tuple[np.ndarray, np.ndarray]:
    """Positions (S, M, 3) and position Jacobians (S, M, 3, 10) of frames in the link
    model at each of the configurations ``theta10`` (S, 10): one Pinocchio pass
    (joint Jacobians and frame placements) per configuration, into arrays made once, on the
    caller's ``data`` (``robot.create_data()``)."""
    model, pdata = robot.link_model, data.links
    fids = tuple(model.getFrameId(f) for f in frames)
    theta10 = np.ascontiguousarray(theta10, dtype=float)
    pos = np.empty((len(theta10), len(fids), 3))
    jac = np.empty((len(theta10), len(fids), 3, model.nv))
    world = pin.LOCAL_WORLD_ALIGNED
    for s, th in enumerate(theta10):
        pin.computeJointJacobians(model, pdata, th)
        pin.updateFramePlacements(model, pdata)
        for k, fid in enumerate(fids):
            pos[s, k] = pdata.oMf[fid].translation
            jac[s, k] = pin.getFrameJacobian(model, pdata, fid, world)[:3]
    return pos, jac


def evaluate(pr: Problem, beta: np.ndarray, bases, exact: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted deflections (D, 3), their Jacobian (D*3, p) and the marker positions
    (S, M, 3) the kinematics gave (exact: at the deflected configurations; first
    order: at the commanded ones)."""
    ds = pr.ds
    b_theta, b_links, b_add = bases
    if exact:
        theta10 = link_configurations(pr.robot, pr.nominal_theta + b_theta @ beta, b_links @ beta)
        pos, jac = kinematics_batch(pr.robot, theta10, pr.frames, pr.data)
    else:
        pos0, jac0 = pr.nominal_kinematics
        pos, jac = pos0[ds.state_pose], jac0[ds.state_pose]
    d_idx = np.arange(ds.n_deflections)
    m = ds.defl_marker
    sl, sr = ds.defl_state, ds.defl_ref
    j_act_l = jac[sl, m][:, :, pr.robot.actuated_in_link_model]
    j_act_r = jac[sr, m][:, :, pr.robot.actuated_in_link_model]
    j_spr_l = jac[sl, m][:, :, pr.robot.springs_in_link_model]
    j_spr_r = jac[sr, m][:, :, pr.robot.springs_in_link_model]
    if exact:
        a = (j_act_l @ b_theta[sl] - j_act_r @ b_theta[sr] + j_spr_l @ b_links[sl] - j_spr_r @ b_links[sr]
             + b_add[d_idx])
        pred = pos[sl, m] - pos[sr, m] + b_add @ beta
    else:
        a = j_act_l @ (b_theta[sl] - b_theta[sr]) + j_spr_l @ (b_links[sl] - b_links[sr]) + b_add
        pred = a @ beta
    return pred, a.reshape(-1, a.shape[2]), pos


def absolute_bases(pr: Problem, ctx: StaticContext) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's bases per state for absolute positions (Effect.absolute): theta (S, 6, p),
    links (S, 4, p) and add (S, M, 3, p)."""
    parts = [eff.absolute(ctx) for eff in pr.effects if eff.parameters]
    return (np.concatenate([b.theta for b in parts], axis=2), np.concatenate([b.links for b in parts], axis=2),
            np.concatenate([b.add for b in parts], axis=3))


def absolute_positions(robot: Robot, ds: StaticDataset, frames: Sequence[str], beta: np.ndarray,
                       bases: tuple[np.ndarray, np.ndarray, np.ndarray],
                       data: RobotData | None = None) -> np.ndarray:
    """Base positions (S, M, 3) of every state's markers under a model's absolute bases
    (:func:`absolute_bases`): the joint angles carry the absolute torques, the link springs
    and the located compliance the moments of gravity and of the load."""
    b_theta, b_links, b_add = bases
    theta10 = link_configurations(robot, ds.q[ds.state_pose] + robot.offsets + b_theta @ beta, b_links @ beta)
    data = robot.create_data() if data is None else data
    return kinematics_batch(robot, theta10, tuple(frames), data)[0] + b_add @ beta


def fitted_positions(pr: Problem, beta: np.ndarray, ctx: StaticContext) -> np.ndarray:
    """Base positions (S, M, 3) of every state's markers under the fitted model."""
    return absolute_positions(pr.robot, pr.ds, pr.frames, beta, absolute_bases(pr, ctx), pr.data)
