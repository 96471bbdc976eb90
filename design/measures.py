"""Design of experiments, the measures: Klimchik's industry measure K40 and the
predicted accuracy of an experiment with the full noise model (K §V.C, Y §4.2;
docs/physics.md "Design of experiments"). The search that minimises them is in
:mod:`elastocal.design.search`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.design.candidates import TestPose, _poses
from elastocal.model.robot import DEFAULT_PRIOR_STIFFNESS, LOAD_FRAME, Robot



@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise of one reading (one standard deviation) and the
    number of readings averaged per marker and load state."""

    tracker_m: float = 10e-6
    current_a: float = 0.02
    repeats: int = 3

    def __post_init__(self) -> None:
        if not (self.tracker_m > 0 and math.isfinite(self.tracker_m)):
            raise InputError(f"must be > 0, got {self.tracker_m!r}", argument="tracker_noise")
        if not (self.current_a >= 0 and math.isfinite(self.current_a)):
            raise InputError(f"must be >= 0, got {self.current_a!r}", argument="current_noise")
        if self.repeats < 1:
            raise InputError(f"must be >= 1, got {self.repeats!r}", argument="repeats")


def pose_matrices(robot: Robot, q: np.ndarray, markers: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: ``G = sum_m J_m^T J_m`` (n, N, N) over the markers' position
    Jacobians, and ``B = J_f^T`` (n, N, 6) of the load point, so that a wrench
    ``W`` loads the joints with ``Gamma = B W`` and one deflection measurement
    of every marker adds ``diag(Gamma) G diag(Gamma)`` to the information."""
    q = _poses(robot, q)
    frames = [LOAD_FRAME, *markers]
    g = np.empty((len(q), robot.n_joints, robot.n_joints))
    b = np.empty((len(q), robot.n_joints, 6))
    data = robot.create_data()
    for i, qi in enumerate(q):
        jac = robot.jacobians(robot.theta(qi), frames, data=data)
        jm = jac[1:, :3, :]
        g[i] = np.einsum("mki,mkj->ij", jm, jm)
        b[i] = jac[0].T
    return g, b


def _marker_jacobians(robot: Robot, q: np.ndarray, markers: Sequence[str]) -> np.ndarray:
    """(n, M, 3, N) position Jacobians of the markers."""
    data = robot.create_data()
    return np.array([robot.jacobians(robot.theta(qi), list(markers), data=data)[:, :3, :] for qi in _poses(robot, q)])


def a0_matrix(robot: Robot, test: TestPose) -> np.ndarray:
    """``A0 = J_p(q0) diag(J_f(q0)^T W0)`` (3, N): the load point's deflection
    per unit compliance at the test pose under the process load (K31)."""
    jac = robot.jacobians(robot.theta(np.array(test.q)), [LOAD_FRAME])[0]
    gamma = jac.T @ np.array(test.wrench)
    return jac[:3] * gamma[None, :]


# =================================================================== quality
def _unseen(information: np.ndarray, rel_tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-analysis of the information in compliances scaled to unit diagonal
    (so that joints of very different stiffness compare): scale (6,), eigenvalues
    and eigenvectors of the scaled matrix, with the eigenvalues of directions the
    experiment cannot see (below ``rel_tol`` of the largest) set to 0."""
    d = np.diag(information).copy()
    seen = d > rel_tol * max(float(d.max()), 0.0)
    scale = np.where(seen, 1.0 / np.sqrt(np.where(seen, d, 1.0)), 0.0)
    m = information * scale[:, None] * scale[None, :]
    w, v = np.linalg.eigh(0.5 * (m + m.T))
    w = np.where(w > rel_tol * max(float(w[-1]), 0.0), w, 0.0)
    return scale, w, v


def industry_measure(information: np.ndarray, a0: np.ndarray, *, rel_tol: float = 1e-10) -> float:
    """``trace(A0 M^-1 A0^T)`` (K40); ``inf`` when the test pose's deflection
    depends on a combination of compliances the experiment cannot see."""
    scale, w, v = _unseen(information, rel_tol)
    a0s = a0 * scale[None, :]
    blind = np.linalg.norm(a0[:, scale == 0.0])              # compliances never excited at all
    proj = a0s @ v                                           # (3, 6)
    good = w > 0.0
    if not np.any(good):
        return math.inf
    seen = np.linalg.norm(proj[:, good])
    lost = np.linalg.norm(proj[:, ~good])
    if blind > 1e-9 * np.linalg.norm(a0) or lost > 1e-6 * max(seen, 1e-300):
        return math.inf
    return float(np.sum(proj[:, good] ** 2 / w[good]))


@dataclass(frozen=True, eq=False)
class DesignQuality:
    """How good an experiment is for the test pose (first-order, current-based torques)."""

    k40: float                    # trace(A0 M^-1 A0^T) [-]
    accuracy_m: float             # predicted rms positioning error at the test pose after compensation [m]
    test_deflection_m: float      # size of the test pose's deflection under the process load [m]
    stiffness_rel_std: np.ndarray  # (N,) predicted std(k_j)/k_j (inf where unidentifiable)
    information: np.ndarray       # (N, N) M in compliances (rad/(N·m); m/N for a prismatic joint)
    covariance: np.ndarray        # (N, N) predicted covariance of the compliances
    n_deflections: int


def _noise_per_pose(jc: np.ndarray, n_loads: int, noise: NoiseModel, xi: np.ndarray) -> np.ndarray:
    """Covariance of one pose's deflections, rows ordered (load, marker, xyz).

    ``jc`` (M*3, 6) = marker Jacobians times the prior compliances. Every
    deflection is a loaded mean minus the pose's unloaded mean: the reference
    is shared, hence ``(I_L + 1 1^T)``."""
    per = noise.tracker_m ** 2 / noise.repeats * np.eye(jc.shape[0])
    if noise.current_a > 0:
        # one current sample per tracker reading (docs/formats.md §2): a state's mean
        # current averages repeats x markers samples
        var_tau = (xi * noise.current_a) ** 2 / (noise.repeats * (jc.shape[0] // 3))
        per = per + (jc * var_tau) @ jc.T
    return np.kron(np.eye(n_loads) + np.ones((n_loads, n_loads)), per)


def evaluate_design(robot: Robot, q: np.ndarray, wrenches: np.ndarray | Sequence[np.ndarray], test: TestPose,
                    markers: Sequence[str], *, prior_stiffness: Sequence[float] | None = None,
                    noise: NoiseModel = NoiseModel()) -> DesignQuality:
    """K40, predicted accuracy and stiffness std of an experiment: poses ``q``
    (n, 6), each measured unloaded and under the wrenches ``wrenches[i]``
    (L_i, 6) on the load point (base axes), every marker read ``repeats`` times
    per state."""
    q = _poses(robot, q)
    if len(wrenches) != len(q):
        raise ValueError("one array of wrenches per pose")
    if prior_stiffness is None:
        prior_stiffness = robot.prior_stiffness() if robot.n_joints != 6 else DEFAULT_PRIOR_STIFFNESS
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    nj = robot.n_joints
    xi = robot.torque_constants
    a0 = a0_matrix(robot, test)
    info = np.zeros((nj, nj))
    blocks = []
    n_defl = 0
    jm_all = _marker_jacobians(robot, q, markers)          # (n, M, 3, N)
    _, b_all = pose_matrices(robot, q, [])
    for i in range(len(q)):
        w = np.atleast_2d(np.asarray(wrenches[i], dtype=float))
        jm = jm_all[i].reshape(-1, nj)                      # (3M, N)
        gam = w @ b_all[i].T                                # (L, N)
        a_i = np.concatenate([jm * g[None, :] for g in gam])   # (L*3M, N)
        info += a_i.T @ a_i
        blocks.append((a_i, _noise_per_pose(jm * c_prior[None, :], len(w), noise, xi)))
        n_defl += len(w) * len(markers)
    k40 = industry_measure(info, a0)
    m_inv = np.linalg.pinv(info, rcond=1e-12, hermitian=True)
    meat = sum(a.T @ s @ a for a, s in blocks)
    cov = m_inv @ meat @ m_inv
    if math.isfinite(k40):
        accuracy = float(np.sqrt(max(np.trace(a0 @ cov @ a0.T), 0.0)))
    else:
        accuracy = math.inf
    rel = np.sqrt(np.clip(np.diag(cov), 0.0, None)) / c_prior
    # directions the experiment cannot see: the compliances they touch are unidentifiable
    scale, w, v = _unseen(info, 1e-10)
    null = np.linalg.norm(v[:, w == 0.0], axis=1) > 1e-6
    rel = np.where(null | (scale == 0.0), np.inf, rel)
    defl = float(np.linalg.norm(a0 @ c_prior))
    return DesignQuality(k40=k40, accuracy_m=accuracy, test_deflection_m=defl, stiffness_rel_std=rel,
                         information=info, covariance=cov, n_deflections=n_defl)
