"""Design of calibration experiments (K §V.C, Y §4.2; docs/physics.md "Design of experiments").

Which poses and loads make the joint stiffness most accurate *where the robot
works*? Klimchik's industry measure answers: after compensation with the
identified compliances ``c = 1/k``, the positioning error at a user's test pose
``q0`` under the process load ``W0`` is ``A0 dc`` with (K31, first-order)::

    A0 = J_p(q0) diag(J_f(q0)^T W0)        (3 x 6)

and with independent tracker noise ``sigma`` per coordinate its mean square is
(K39) ``rho0^2 = sigma^2 trace(A0 M^-1 A0^T)``, ``M = sum_i A_i^T A_i`` over
every measured deflection ``A_i = J_marker(q_i) diag(J_f(q_i)^T W_i)``. The
plan minimises ``K40 = trace(A0 M^-1 A0^T)`` subject to the joint limits, the
load point being reachable, the markers being visible from the tracker, and
``|F| <= F_max`` (K41).

The search (:func:`plan_experiment`) picks ``n`` poses out of sampled candidate
poses and a set of load forces shared by all poses (each of size ``F_max``:
the model is linear in the force, so the largest allowed force is always
best, and ``F`` and ``-F`` carry the same information, so only directions
that hang or pull downwards or sideways are offered). It alternates a Fedorov
exchange of poses with an exhaustive choice of the load directions until
neither improves. A small A-optimal term (:data:`IDENTIFIABILITY_WEIGHT`)
keeps every stiffness identifiable, so the calibration also serves other poses.

:func:`evaluate_design` gives, for any experiment, K40, the predicted rms
positioning error at the test pose with the full noise model (tracker noise
with repeats and shared unloaded references, current noise through the prior
compliances), and the predicted relative std of each stiffness.

This module holds the search; the inputs (test pose, workspace, candidates) are in
:mod:`elastocal.design.candidates`, the measures (K40, predicted accuracy)
in :mod:`elastocal.design.measures`. Yang's first-order map runs the
simulated cell's statics and lives in :mod:`elastocal.sims.first_order_map`.

Pure functions, frozen results.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.design.candidates import Candidates, TestPose, Workspace, load_directions
from elastocal.design.measures import (
    DEFAULT_PRIOR_STIFFNESS,
    DesignQuality,
    NoiseModel,
    _marker_jacobians,
    a0_matrix,
    evaluate_design,
    industry_measure,
    pose_matrices,
)
from elastocal.model.robot import Robot

#: weight of the A-optimal term (scaled compliances) added to the industry measure,
#: relative to the measure's own trace: keeps every stiffness identifiable
IDENTIFIABILITY_WEIGHT = 1e-3
#: ridge (relative to a typical pose's information) that makes the greedy start well posed
RIDGE = 1e-9


# ==================================================================== search
@dataclass(frozen=True, eq=False)
class ExperimentDesign:
    """A planned experiment: poses, the load forces measured at every pose, its quality."""

    q: np.ndarray                 # (n, 6)
    forces: np.ndarray            # (L, 3) forces on the load point, base axes [N]
    candidate_index: np.ndarray   # (n,) rows of the candidates used
    quality: DesignQuality
    rounds: int
    exchanges: int

    @property
    def wrenches(self) -> np.ndarray:
        """(n, L, 6) wrench of every loaded state."""
        w = np.concatenate([self.forces, np.zeros_like(self.forces)], axis=1)
        return np.broadcast_to(w, (len(self.q), *w.shape)).copy()


def _phi(x: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``trace(weight x^-1)`` for a batch of symmetric positive definite x."""
    try:
        sol = np.linalg.solve(x, np.broadcast_to(weight, x.shape))
    except np.linalg.LinAlgError:
        return np.full(x.shape[:-2], np.inf)
    return np.trace(sol, axis1=-2, axis2=-1)


def _weighted_info_parts(robot: Robot, q: np.ndarray, markers: Sequence[str], forces: np.ndarray,
                         c_prior: np.ndarray, noise: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """Per pose ``H = J^T P^-1 J`` (n, 6, 6), ``J`` the stacked marker Jacobians
    and ``P`` the covariance of one load state's marker readings (tracker noise
    and current noise through the prior compliances), and the scaled joint
    torques ``gamma = c_prior * J_f^T F`` (n, F, 6) of each force."""
    jm = _marker_jacobians(robot, q, markers).reshape(len(q), -1, robot.n_joints)     # (n, 3M, N)
    _, b = pose_matrices(robot, q, [])
    n_rows = jm.shape[1]
    p = np.broadcast_to(noise.tracker_m ** 2 / noise.repeats * np.eye(n_rows), (len(q), n_rows, n_rows)).copy()
    if noise.current_a > 0:
        var_tau = (robot.torque_constants * noise.current_a) ** 2 / (noise.repeats * len(markers))
        jc = jm * c_prior[None, None, :]
        p += np.einsum("nrj,j,nsj->nrs", jc, var_tau, jc)
    h = np.einsum("nri,nrj->nij", jm, np.linalg.solve(p, jm))
    gamma = np.einsum("nij,fj->nfi", b[:, :, :3], np.atleast_2d(forces)) * c_prior[None, None, :]
    return h, gamma


def _combo_info(h: np.ndarray, gamma: np.ndarray, combo: Sequence[int]) -> np.ndarray:
    """Information (n, 6, 6) of each pose measured unloaded and under the forces
    ``combo``: ``A^T Sigma^-1 A`` with the unloaded reference shared by the loads,
    ``H . (sum_l g_l g_l^T - s s^T / (L + 1))``, ``s = sum_l g_l``."""
    g = gamma[:, list(combo)]                                            # (n, L, 6)
    s = g.sum(axis=1)
    outer = np.einsum("nli,nlj->nij", g, g) - np.einsum("ni,nj->nij", s, s) / (len(combo) + 1)
    return h * outer


def _weight(a0_scaled: np.ndarray) -> np.ndarray:
    w = a0_scaled.T @ a0_scaled
    n = w.shape[0]
    return w + IDENTIFIABILITY_WEIGHT * np.trace(w) / n * np.eye(n)


def _greedy(info: np.ndarray, m0: np.ndarray, weight: np.ndarray, n: int) -> list[int]:
    m = m0.copy()
    picked: list[int] = []
    for _ in range(n):
        val = _phi(m + info, weight)
        val[picked] = np.inf
        j = int(np.argmin(val))
        picked.append(j)
        m = m + info[j]
    return picked


def plan_experiment(robot: Robot, candidates: Candidates, test: TestPose, *, n_poses: int, loads_per_pose: int,
                    workspace: Workspace, markers: Sequence[str],
                    prior_stiffness: Sequence[float] = DEFAULT_PRIOR_STIFFNESS, noise: NoiseModel = NoiseModel(),
                    max_rounds: int = 8) -> ExperimentDesign:
    """Choose ``n_poses`` of the candidate poses and ``loads_per_pose`` load
    directions (shared by all poses, size ``workspace.f_max_n``) that make the
    test pose's positioning error after compensation smallest.

    The criterion is the industry measure with the experiment's own noise
    (Klimchik's eq. 36 before the i.i.d. simplification of eq. 37):
    ``trace(A0 (sum_i A_i^T Sigma_i^-1 A_i)^-1 A0^T)``, where ``Sigma_i`` holds
    the tracker noise, the current noise (it scales with the compliances, so
    the wrist joints weigh) and the unloaded reference that a pose's loads
    share. With tracker noise alone it is ``sigma^2`` K40."""
    nc = len(candidates.q)
    if n_poses < 1:
        raise InputError(f"must be >= 1, got {n_poses}", argument="poses")
    if n_poses > nc:
        raise InputError(f"cannot choose {n_poses} poses out of {nc} candidates", argument="poses")
    dirs = load_directions(workspace.directions, robot.gravity)
    if not 1 <= loads_per_pose <= len(dirs):
        raise InputError(f"must be between 1 and {len(dirs)} for directions={workspace.directions}, "
                         f"got {loads_per_pose}", argument="loads_per_pose")
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    # scaled compliances x = c / c_prior: the measure is invariant, the ridge and the A-optimal term are not
    h, gamma = _weighted_info_parts(robot, candidates.q, markers, workspace.f_max_n * dirs, c_prior, noise)
    weight = _weight(a0_matrix(robot, test) * c_prior[None, :])
    combos = [tuple(c) for c in itertools.combinations(range(len(dirs)), loads_per_pose)]
    # start from the directions best for the candidates as a whole
    mean_info = np.array([_combo_info(h, gamma, c).mean(axis=0) for c in combos])
    chosen = combos[int(np.argmin(_phi(mean_info, weight)))]
    pose_info = _combo_info(h, gamma, chosen)
    n_el = pose_info.shape[-1]
    ridge = RIDGE * float(np.mean(np.trace(pose_info, axis1=-2, axis2=-1))) / n_el * np.eye(n_el)
    sel = np.array(_greedy(pose_info, ridge, weight, n_poses))
    exchanges = 0
    rounds = 0
    for rounds in range(1, max_rounds + 1):
        # Fedorov exchange of poses
        m = ridge + pose_info[sel].sum(axis=0)
        current = float(_phi(m, weight))
        changed = True
        while changed:
            changed = False
            for k in range(n_poses):
                rest = m - pose_info[sel[k]]
                val = _phi(rest + pose_info, weight)
                val[sel] = np.inf
                j = int(np.argmin(val))
                if val[j] < current * (1.0 - 1e-9):
                    sel[k] = j
                    m = rest + pose_info[j]
                    current = float(val[j])
                    exchanges += 1
                    changed = True
        # best load directions for these poses
        mats = np.array([ridge + _combo_info(h[sel], gamma[sel], c).sum(axis=0) for c in combos])
        vals = _phi(mats, weight)
        best = combos[int(np.argmin(vals))]
        if best == chosen or float(np.min(vals)) >= current * (1.0 - 1e-9):
            break
        chosen = best
        pose_info = _combo_info(h, gamma, chosen)
    forces = workspace.f_max_n * dirs[list(chosen)]
    q = candidates.q[sel]
    wrenches = np.concatenate([forces, np.zeros_like(forces)], axis=1)
    quality = evaluate_design(robot, q, [wrenches] * len(q), test, markers, prior_stiffness=prior_stiffness,
                              noise=noise)
    return ExperimentDesign(q=q, forces=forces, candidate_index=sel.copy(), quality=quality, rounds=rounds,
                            exchanges=exchanges)


def random_design_k40(robot: Robot, candidates: Candidates, forces: np.ndarray, test: TestPose, *, n_poses: int,
                      markers: Sequence[str], rng: np.random.Generator, draws: int = 50) -> np.ndarray:
    """K40 of ``draws`` experiments of ``n_poses`` candidate poses drawn at
    random, each measured under ``forces`` (L, 3): the baseline a plan beats."""
    g, b = pose_matrices(robot, candidates.q, markers)
    gamma = np.einsum("nij,lj->nli", b[:, :, :3], np.atleast_2d(forces))
    info = (g[:, None] * gamma[:, :, :, None] * gamma[:, :, None, :]).sum(axis=1)
    a0 = a0_matrix(robot, test)
    out = np.empty(draws)
    for k in range(draws):
        idx = rng.choice(len(candidates.q), size=n_poses, replace=False)
        out[k] = industry_measure(info[idx].sum(axis=0), a0)
    return out


@dataclass(frozen=True, eq=False)
class CheckChoice:
    """Poses of a plan (indices) and the one load (index into the plan's forces) for the check."""

    poses: np.ndarray
    load: int
    quality: DesignQuality


def choose_check(robot: Robot, design: ExperimentDesign, test: TestPose, *, n_check: int, markers: Sequence[str],
                 prior_stiffness: Sequence[float] = DEFAULT_PRIOR_STIFFNESS,
                 noise: NoiseModel = NoiseModel()) -> CheckChoice:
    """The ``n_check`` poses of the plan and the single load whose K40 at the
    test pose is smallest (greedy): a short check that looks where it matters."""
    n = len(design.q)
    if not 1 <= n_check <= n:
        raise InputError(f"must be between 1 and {n}, got {n_check}", argument="check_poses")
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    g, b = pose_matrices(robot, design.q, markers)
    a0 = a0_matrix(robot, test) * c_prior[None, :]
    n_el = a0.shape[1]
    weight = a0.T @ a0 + IDENTIFIABILITY_WEIGHT * np.trace(a0.T @ a0) / n_el * np.eye(n_el)
    best: tuple[float, int, list[int]] | None = None
    for li, f in enumerate(design.forces):
        gam = np.einsum("nij,j->ni", b[:, :, :3], f) * c_prior[None, :]
        info = g * gam[:, :, None] * gam[:, None, :]
        ridge = RIDGE * float(np.mean(np.trace(info, axis1=-2, axis2=-1))) / n_el * np.eye(n_el)
        m = ridge.copy()
        picked: list[int] = []
        for _ in range(n_check):
            val = _phi(m + info, weight)
            val[picked] = np.inf
            j = int(np.argmin(val))
            picked.append(j)
            m = m + info[j]
        score = float(_phi(m, weight))
        if best is None or score < best[0]:
            best = (score, li, sorted(picked))
    _, li, picked = best
    w = np.concatenate([design.forces[li], np.zeros(3)])
    quality = evaluate_design(robot, design.q[picked], [w[None, :]] * len(picked), test, markers,
                              prior_stiffness=prior_stiffness, noise=noise)
    return CheckChoice(poses=np.array(picked), load=li, quality=quality)


