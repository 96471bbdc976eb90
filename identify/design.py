"""Design of calibration experiments (K §V.C, Y §4.2; physics.md "Design of experiments").

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

:func:`first_order_map` is Yang's analysis (Y Fig. 4-6): over a grid of
(q2, q3), the exact statics of the simulated cell give noise-free deflections
under a large load; the first-order model ``dP = J(q) C Gamma`` identifies the
stiffness from them; where every relative stiffness error stays below 5 % the
first-order model is good enough.

Pure functions, frozen results; plotting writes a file and nothing else.
"""

from __future__ import annotations

import itertools
import math
import pathlib
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.identify.robot import LOAD_FRAME, Robot

#: prior joint stiffness when nothing better is known: Yang Table 3, the
#: "arbitrary values" of his analysis (the good zone barely depends on them) [N·m/rad]
DEFAULT_PRIOR_STIFFNESS = (1.0e6, 1.5e6, 2.0e6, 0.5e6, 0.5e6, 0.5e6)
#: relative stiffness error under which the first-order model is good enough (Y §4.2)
GOOD_ENOUGH = 0.05
#: weight of the A-optimal term (scaled compliances) added to the industry measure,
#: relative to the measure's own trace: keeps every stiffness identifiable
IDENTIFIABILITY_WEIGHT = 1e-3
#: ridge (relative to a typical pose's information) that makes the greedy start well posed
RIDGE = 1e-9
DIRECTION_KINDS = ("any", "down")


# ====================================================================== inputs
@dataclass(frozen=True)
class TestPose:
    """Where the robot works: the test pose ``q`` and the process wrench on the
    load point (fx, fy, fz, mx, my, mz; base axes) [rad, N, N·m]."""

    __test__ = False  # not a pytest test class

    q: tuple[float, ...]
    wrench: tuple[float, ...]

    def __post_init__(self) -> None:
        q = tuple(float(v) for v in self.q)
        w = tuple(float(v) for v in self.wrench)
        if len(q) != 6 or not all(math.isfinite(v) for v in q):
            raise InputError(f"expected 6 finite joint values, got {self.q!r}", source="--test-pose")
        if len(w) != 6 or not all(math.isfinite(v) for v in w):
            raise InputError(f"expected 6 finite wrench values, got {self.wrench!r}", source="--load")
        if not any(w):
            raise InputError("the process load is zero: nothing deflects at the test pose", source="--load")
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "wrench", w)


@dataclass(frozen=True)
class Workspace:
    """What a calibration pose and load must respect.

    * the joint limits of the robot (q1, q4, q6 also within +-pi);
    * every joint origin from the elbow on, the load point and the markers at
      least ``min_height_m`` above the base plane; the load point at most
      ``max_height_m`` high and at least ``min_radius_m`` from the axis of joint 1
      (a hung load clears the base);
    * with ``base_p_tracker``: every marker within ``tracker_range_m`` of the
      tracker and its line of sight clear of the links, modelled as capsules
      of radius ``link_radius_m`` around the segments joining the joint origins;
    * loads: forces of size ``f_max_n`` on the load point; ``directions``
      "down" (hung weights only) or "any" (weights and horizontal or slanted pulls).
    """

    f_max_n: float
    directions: str = "any"
    min_height_m: float = 0.3
    max_height_m: float = 3.0
    min_radius_m: float = 0.5
    base_p_tracker: tuple[float, float, float] | None = None
    link_radius_m: float = 0.15
    tracker_range_m: float = 20.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.f_max_n) and self.f_max_n > 0):
            raise InputError(f"must be a positive force [N], got {self.f_max_n!r}", source="--f-max")
        if self.directions not in DIRECTION_KINDS:
            raise InputError(f"must be one of {', '.join(DIRECTION_KINDS)}, got {self.directions!r}",
                             source="--directions")
        if not self.max_height_m > self.min_height_m:
            raise InputError(f"max height {self.max_height_m} m is not above min height {self.min_height_m} m",
                             source="--max-height")
        for name, flag in (("link_radius_m", "--link-radius"), ("tracker_range_m", "tracker_range_m")):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"must be > 0, got {v!r}", source=flag)
        if self.base_p_tracker is not None:
            p = tuple(float(v) for v in self.base_p_tracker)
            if len(p) != 3 or not all(math.isfinite(v) for v in p):
                raise InputError(f"expected x,y,z in metres, got {self.base_p_tracker!r}",
                                 source="--tracker-position")
            object.__setattr__(self, "base_p_tracker", p)


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise of one reading (one standard deviation) and the
    number of readings averaged per marker and load state."""

    tracker_m: float = 10e-6
    current_a: float = 0.02
    repeats: int = 3

    def __post_init__(self) -> None:
        if not (self.tracker_m > 0 and math.isfinite(self.tracker_m)):
            raise InputError(f"must be > 0, got {self.tracker_m!r}", source="--tracker-noise")
        if not (self.current_a >= 0 and math.isfinite(self.current_a)):
            raise InputError(f"must be >= 0, got {self.current_a!r}", source="--current-noise")
        if self.repeats < 1:
            raise InputError(f"must be >= 1, got {self.repeats!r}", source="--repeats")


# ================================================================ kinematics
def _six(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != 6:
        raise ValueError(f"expected poses of shape (n, 6), got {q.shape}")
    return q


def pose_matrices(robot: Robot, q: np.ndarray, markers: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: ``G = sum_m J_m^T J_m`` (n, 6, 6) over the markers' position
    Jacobians, and ``B = J_f^T`` (n, 6, 6) of the load point, so that a wrench
    ``W`` loads the joints with ``Gamma = B W`` and one deflection measurement
    of every marker adds ``diag(Gamma) G diag(Gamma)`` to the information."""
    q = _six(q)
    frames = [LOAD_FRAME, *markers]
    g = np.empty((len(q), 6, 6))
    b = np.empty((len(q), 6, 6))
    for i, qi in enumerate(q):
        jac = robot.jacobians(robot.theta(qi), frames)
        jm = jac[1:, :3, :]
        g[i] = np.einsum("mki,mkj->ij", jm, jm)
        b[i] = jac[0].T
    return g, b


def _marker_jacobians(robot: Robot, q: np.ndarray, markers: Sequence[str]) -> np.ndarray:
    """(n, M, 3, 6) position Jacobians of the markers."""
    return np.array([robot.jacobians(robot.theta(qi), list(markers))[:, :3, :] for qi in _six(q)])


def a0_matrix(robot: Robot, test: TestPose) -> np.ndarray:
    """``A0 = J_p(q0) diag(J_f(q0)^T W0)`` (3, 6): the load point's deflection
    per unit compliance at the test pose under the process load (K31)."""
    jac = robot.jacobians(robot.theta(np.array(test.q)), [LOAD_FRAME])[0]
    gamma = jac.T @ np.array(test.wrench)
    return jac[:3] * gamma[None, :]


def _joint_origins(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(n, 8, 3): base origin, the six joint origins, the load point."""
    model = robot.model
    data = model.createData()
    fid = model.getFrameId(LOAD_FRAME)
    out = np.empty((len(q), 8, 3))
    for i, qi in enumerate(q):
        pin.framesForwardKinematics(model, data, robot.theta(qi))
        out[i, 0] = 0.0
        for j in range(1, 7):
            out[i, j] = data.oMi[j].translation
        out[i, 7] = data.oMf[fid].translation
    return out


def _segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Shortest distance between segments p1-q1 and p2-q2, broadcast over the
    leading axes (Ericson, Real-Time Collision Detection, 5.1.9; degenerate
    segments are points)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("...k,...k->...", d1, d1)
    e = np.einsum("...k,...k->...", d2, d2)
    f = np.einsum("...k,...k->...", d2, r)
    c = np.einsum("...k,...k->...", d1, r)
    b = np.einsum("...k,...k->...", d1, d2)
    eps = 1e-12
    a_ok, e_ok = a > eps, e > eps
    safe_a, safe_e = np.where(a_ok, a, 1.0), np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    s_gen = np.where(denom > eps, np.clip((b * f - c * e) / np.where(denom > eps, denom, 1.0), 0.0, 1.0), 0.0)
    t_gen = (b * s_gen + f) / safe_e
    s_gen = np.where(t_gen < 0.0, np.clip(-c / safe_a, 0.0, 1.0),
                     np.where(t_gen > 1.0, np.clip((b - c) / safe_a, 0.0, 1.0), s_gen))
    t_gen = np.clip(t_gen, 0.0, 1.0)
    s = np.where(a_ok, np.where(e_ok, s_gen, np.clip(-c / safe_a, 0.0, 1.0)), 0.0)
    t = np.where(e_ok, np.where(a_ok, t_gen, np.clip(f / safe_e, 0.0, 1.0)), 0.0)
    return np.linalg.norm((p1 + s[..., None] * d1) - (p2 + t[..., None] * d2), axis=-1)


#: reasons a sampled pose is rejected, in the order they are tested
REJECTIONS = ("height", "reach", "markers hidden")


def check_poses(robot: Robot, q: np.ndarray, workspace: Workspace, markers: Sequence[str]) -> np.ndarray:
    """Index (n,) of the first constraint of :data:`REJECTIONS` each pose breaks,
    -1 for poses that respect them all (joint limits are the caller's: sampled
    poses are within them)."""
    q = _six(q)
    origins = _joint_origins(robot, q)
    mpos = np.array([robot.positions(robot.theta(qi), list(markers)) for qi in q])  # (n, M, 3)
    load = origins[:, 7]
    out = np.full(len(q), -1)
    low = np.minimum(origins[:, 3:8, 2].min(axis=1), mpos[:, :, 2].min(axis=1))
    height_bad = (low < workspace.min_height_m) | (load[:, 2] > workspace.max_height_m)
    out[height_bad] = 0
    reach_bad = np.hypot(load[:, 0], load[:, 1]) < workspace.min_radius_m
    out[(out < 0) & reach_bad] = 1
    if workspace.base_p_tracker is not None:
        tracker = np.array(workspace.base_p_tracker)
        seg_a = origins[:, :6]          # capsules: base-J1, J1-J2, ..., J5-J6
        seg_b = origins[:, 1:7]
        hidden = np.zeros(len(q), dtype=bool)
        for m in range(len(markers)):
            p = mpos[:, m]                                         # (n, 3)
            far = np.linalg.norm(p - tracker, axis=1) > workspace.tracker_range_m
            # capsules the marker sits on (its own tool and wrist) do not hide it
            own = _segment_distance(p[:, None, :], p[:, None, :], seg_a, seg_b) < workspace.link_radius_m + 0.05
            sight = _segment_distance(np.broadcast_to(tracker, p.shape)[:, None, :], p[:, None, :], seg_a, seg_b)
            blocked = np.any((sight < workspace.link_radius_m) & ~own, axis=1)
            hidden |= far | blocked
        out[(out < 0) & hidden] = 2
    return out


@dataclass(frozen=True, eq=False)
class Candidates:
    """Sampled poses that respect the workspace, and why the others did not."""

    q: np.ndarray                         # (n, 6)
    sampled: int                          # poses drawn
    accepted: int                         # of them respecting the workspace (the first n are kept)
    rejected: tuple[tuple[str, int], ...]  # (reason, count) of the others


def sample_candidates(robot: Robot, n: int, rng: np.random.Generator, workspace: Workspace,
                      markers: Sequence[str], *, max_sampled: int | None = None) -> Candidates:
    """``n`` poses drawn uniformly within the joint limits (q1, q4, q6 within
    +-pi) that respect ``workspace``; raises InputError when fewer than ``n``
    of ``max_sampled`` (default 50 n) draws do."""
    if n < 1:
        raise InputError(f"must be >= 1, got {n}", source="--candidates")
    lo = robot.lower.copy()
    hi = robot.upper.copy()
    for j in (0, 3, 5):
        lo[j], hi[j] = max(lo[j], -math.pi), min(hi[j], math.pi)
    limit = max_sampled if max_sampled is not None else 50 * n
    kept: list[np.ndarray] = []
    counts = np.zeros(len(REJECTIONS), dtype=int)
    sampled = 0
    while len(kept) < n and sampled < limit:
        batch = min(max(2 * (n - len(kept)), 64), limit - sampled)
        q = rng.uniform(lo, hi, size=(batch, 6))
        sampled += batch
        code = check_poses(robot, q, workspace, markers)
        for k in range(len(REJECTIONS)):
            counts[k] += int(np.sum(code == k))
        kept.extend(q[code < 0])
    if len(kept) < n:
        reasons = ", ".join(f"{c} {r}" for r, c in zip(REJECTIONS, counts) if c)
        raise InputError(f"only {len(kept)} of {sampled} sampled poses respect the workspace (rejected: {reasons}); "
                         "relax the constraints or check the tracker position", source="--candidates")
    return Candidates(q=np.array(kept[:n]), sampled=sampled, accepted=len(kept),
                      rejected=tuple((r, int(c)) for r, c in zip(REJECTIONS, counts)))


def load_directions(kind: str, gravity: Sequence[float] = (0.0, 0.0, -9.81)) -> np.ndarray:
    """Unit force directions (D, 3) offered to the planner. "down": the
    direction of gravity (hung weights). "any": the 13 directions of the cube's
    faces, edges and corners taken once up to sign (F and -F inform alike),
    each turned to pull down or sideways, gravity's direction first."""
    g = np.asarray(gravity, dtype=float)
    down = g / np.linalg.norm(g)
    if kind == "down":
        return down[None, :]
    if kind != "any":
        raise InputError(f"must be one of {', '.join(DIRECTION_KINDS)}, got {kind!r}", source="--directions")
    dirs = [down]
    for v in itertools.product((-1, 0, 1), repeat=3):
        u = np.array(v, dtype=float)
        if not u.any():
            continue
        u /= np.linalg.norm(u)
        along = float(u @ down)
        if along < -1e-12 or (abs(along) <= 1e-12 and tuple(np.sign(u[np.abs(u) > 1e-12]))[0] < 0):
            u = -u
        if not any(np.allclose(u, d) for d in dirs):
            dirs.append(u)
    return np.array(dirs)


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
    stiffness_rel_std: np.ndarray  # (6,) predicted std(k_j)/k_j (inf where unidentifiable)
    information: np.ndarray       # (6, 6) M in compliances (rad/(N·m))
    covariance: np.ndarray        # (6, 6) predicted covariance of the compliances
    n_deflections: int


def _noise_per_pose(jc: np.ndarray, n_loads: int, noise: NoiseModel, xi: np.ndarray) -> np.ndarray:
    """Covariance of one pose's deflections, rows ordered (load, marker, xyz).

    ``jc`` (M*3, 6) = marker Jacobians times the prior compliances. Every
    deflection is a loaded mean minus the pose's unloaded mean: the reference
    is shared, hence ``(I_L + 1 1^T)``."""
    per = noise.tracker_m ** 2 / noise.repeats * np.eye(jc.shape[0])
    if noise.current_a > 0:
        # one current sample per tracker reading (formats.md §2): a state's mean
        # current averages repeats x markers samples
        var_tau = (xi * noise.current_a) ** 2 / (noise.repeats * (jc.shape[0] // 3))
        per = per + (jc * var_tau) @ jc.T
    return np.kron(np.eye(n_loads) + np.ones((n_loads, n_loads)), per)


def evaluate_design(robot: Robot, q: np.ndarray, wrenches: np.ndarray | Sequence[np.ndarray], test: TestPose,
                    markers: Sequence[str], *, prior_stiffness: Sequence[float] = DEFAULT_PRIOR_STIFFNESS,
                    noise: NoiseModel = NoiseModel()) -> DesignQuality:
    """K40, predicted accuracy and stiffness std of an experiment: poses ``q``
    (n, 6), each measured unloaded and under the wrenches ``wrenches[i]``
    (L_i, 6) on the load point (base axes), every marker read ``repeats`` times
    per state."""
    q = _six(q)
    if len(wrenches) != len(q):
        raise ValueError("one array of wrenches per pose")
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    xi = robot.torque_constants
    a0 = a0_matrix(robot, test)
    info = np.zeros((6, 6))
    blocks = []
    n_defl = 0
    jm_all = _marker_jacobians(robot, q, markers)          # (n, M, 3, 6)
    _, b_all = pose_matrices(robot, q, [])
    for i in range(len(q)):
        w = np.atleast_2d(np.asarray(wrenches[i], dtype=float))
        jm = jm_all[i].reshape(-1, 6)                       # (3M, 6)
        gam = w @ b_all[i].T                                # (L, 6)
        a_i = np.concatenate([jm * g[None, :] for g in gam])   # (L*3M, 6)
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
    jm = _marker_jacobians(robot, q, markers).reshape(len(q), -1, 6)     # (n, 3M, 6)
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
    return w + IDENTIFIABILITY_WEIGHT * np.trace(w) / 6.0 * np.eye(6)


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
        raise InputError(f"must be >= 1, got {n_poses}", source="--poses")
    if n_poses > nc:
        raise InputError(f"cannot choose {n_poses} poses out of {nc} candidates", source="--poses")
    dirs = load_directions(workspace.directions, robot.gravity)
    if not 1 <= loads_per_pose <= len(dirs):
        raise InputError(f"must be between 1 and {len(dirs)} for directions={workspace.directions}, "
                         f"got {loads_per_pose}", source="--loads-per-pose")
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    # scaled compliances x = c / c_prior: the measure is invariant, the ridge and the A-optimal term are not
    h, gamma = _weighted_info_parts(robot, candidates.q, markers, workspace.f_max_n * dirs, c_prior, noise)
    weight = _weight(a0_matrix(robot, test) * c_prior[None, :])
    combos = [tuple(c) for c in itertools.combinations(range(len(dirs)), loads_per_pose)]
    # start from the directions best for the candidates as a whole
    mean_info = np.array([_combo_info(h, gamma, c).mean(axis=0) for c in combos])
    chosen = combos[int(np.argmin(_phi(mean_info, weight)))]
    pose_info = _combo_info(h, gamma, chosen)
    ridge = RIDGE * float(np.mean(np.trace(pose_info, axis1=-2, axis2=-1))) / 6.0 * np.eye(6)
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
        raise InputError(f"must be between 1 and {n}, got {n_check}", source="--check-poses")
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    g, b = pose_matrices(robot, design.q, markers)
    a0 = a0_matrix(robot, test) * c_prior[None, :]
    weight = a0.T @ a0 + IDENTIFIABILITY_WEIGHT * np.trace(a0.T @ a0) / 6.0 * np.eye(6)
    best: tuple[float, int, list[int]] | None = None
    for li, f in enumerate(design.forces):
        gam = np.einsum("nij,j->ni", b[:, :, :3], f) * c_prior[None, :]
        info = g * gam[:, :, None] * gam[:, None, :]
        ridge = RIDGE * float(np.mean(np.trace(info, axis1=-2, axis2=-1))) / 6.0 * np.eye(6)
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


# ============================================================ first-order map
@dataclass(frozen=True, eq=False)
class FirstOrderMap:
    """Where the first-order model identifies the stiffness well (Y Fig. 4-6)."""

    q2: np.ndarray                # (n2,) [rad]
    q3: np.ndarray                # (n3,) [rad]
    stiffness_error: np.ndarray   # (n3, n2, 6) |k_identified - k| / k (inf: not identifiable)
    position_error: np.ndarray    # (n3, n2) eps_P = |dP(k_id) - dP(k)| / |dP(k)| at the load point
    q_base: tuple[float, ...]
    wrench: tuple[float, ...]
    torque: str
    threshold: float = GOOD_ENOUGH

    @property
    def max_stiffness_error(self) -> np.ndarray:
        return np.max(self.stiffness_error, axis=2)

    @property
    def good(self) -> np.ndarray:
        """(n3, n2) True where every joint's relative stiffness error is below the threshold."""
        return self.max_stiffness_error < self.threshold

    @property
    def good_fraction(self) -> float:
        return float(np.mean(self.good))


def first_order_map(robot: Robot, *, q_base: Sequence[float], wrench: Sequence[float],
                    stiffness: Sequence[float] = DEFAULT_PRIOR_STIFFNESS, markers: Sequence[str] | None = None,
                    torque: str = "current", n_grid: int = 25, threshold: float = GOOD_ENOUGH) -> FirstOrderMap:
    """Yang's analysis over (q2, q3), the other joints at ``q_base``.

    At every grid point the exact statics of the simulated cell (links'
    gravity, compensator at its nominal parameters, ``wrench`` on the load
    point, joint springs ``stiffness``) give noise-free marker deflections;
    the first-order model ``dP = J_m(q) diag(Gamma) c`` identifies ``c`` from
    them, with ``Gamma`` from the gear torques ("current") or ``J_f(q)^T W``
    ("force")."""
    from elastocal.sims.cell import CellTruth, SimCell

    if torque not in ("current", "force"):
        raise InputError(f"must be current or force, got {torque!r}", source="--torque")
    if n_grid < 2:
        raise InputError(f"must be >= 2, got {n_grid}", source="--map-grid")
    markers = list(markers or robot.marker_names)
    k = np.asarray(stiffness, dtype=float)
    comp = None
    if robot.compensator is not None:
        nom = robot.compensator.nominal_parameters()
        comp = None if nom is None else (float(nom[0]), float(nom[1]))
    cell = SimCell(robot, CellTruth(stiffness=k, compensator=comp, tracker_noise_m=0.0, current_noise_a=0.0))
    w = np.asarray(wrench, dtype=float)
    q2 = np.linspace(robot.lower[1], robot.upper[1], n_grid)
    q3 = np.linspace(robot.lower[2], robot.upper[2], n_grid)
    err = np.full((n_grid, n_grid, 6), np.inf)
    eps = np.full((n_grid, n_grid), np.inf)
    frames = [LOAD_FRAME, *markers]
    for a, v3 in enumerate(q3):
        for b_, v2 in enumerate(q2):
            q = np.array(q_base, dtype=float)
            q[1], q[2] = v2, v3
            eq0 = cell.equilibrium(q)
            eq1 = cell.equilibrium(q, w, reference=eq0)
            d_markers = cell.marker_positions(eq1, markers) - cell.marker_positions(eq0, markers)
            jac = robot.jacobians(robot.theta(q), frames)
            gam = eq1.gear_torque - eq0.gear_torque if torque == "current" else jac[0].T @ w
            a_mat = (jac[1:, :3, :] * gam[None, None, :]).reshape(-1, 6)
            scale = np.linalg.norm(a_mat, axis=0)
            ok = scale > 1e-9 * max(float(scale.max()), 1e-300)
            if not np.all(ok):
                continue
            sv = np.linalg.svd(a_mat / scale, compute_uv=False)
            if sv[-1] < 1e-9 * sv[0]:
                continue
            c_id = np.linalg.lstsq(a_mat / scale, d_markers.reshape(-1), rcond=None)[0] / scale
            with np.errstate(divide="ignore"):
                k_id = np.where(c_id > 0, 1.0 / c_id, np.inf)
            err[a, b_] = np.abs(k_id - k) / k
            true_d = jac[0][:3] @ (gam / k)
            eps[a, b_] = float(np.linalg.norm(jac[0][:3] @ (gam * (c_id - 1.0 / k))) /
                               max(np.linalg.norm(true_d), 1e-300))
    return FirstOrderMap(q2=q2, q3=q3, stiffness_error=err, position_error=eps,
                         q_base=tuple(float(v) for v in q_base), wrench=tuple(float(v) for v in w), torque=torque,
                         threshold=threshold)


def plot_first_order_map(fmap: FirstOrderMap, path: str | pathlib.Path, *, test_q: Sequence[float] | None = None,
                         poses: np.ndarray | None = None) -> None:
    """Write the map as PNG or SVG (by the file's suffix): (a) the largest
    relative stiffness error over the joints (blank above 10 %, Y Fig. 4),
    (b) the relative position error eps_P (Y Fig. 5), both with the good
    zone's border (Y Fig. 6), the test pose and the planned poses."""
    from matplotlib.figure import Figure

    path = pathlib.Path(path)
    if path.suffix.lower() not in (".png", ".svg"):
        raise InputError("the map is written as .png or .svg", source=str(path))
    fig = Figure(figsize=(10.0, 4.4), layout="constrained")
    axes = fig.subplots(1, 2)
    x, y = np.degrees(fmap.q2), np.degrees(fmap.q3)
    panels = ((fmap.max_stiffness_error, "(a) largest relative stiffness error"),
              (fmap.position_error, "(b) relative position error $\\epsilon_P$"))
    for ax, (values, title) in zip(axes, panels):
        shown = np.where(np.isfinite(values) & (values <= 0.10), values * 100.0, np.nan)
        mesh = ax.pcolormesh(x, y, shown, shading="nearest", cmap="viridis", vmin=0.0, vmax=10.0)
        fig.colorbar(mesh, ax=ax, label="%")
        if not np.all(fmap.good):
            ax.contourf(x, y, (~fmap.good).astype(float), levels=[0.5, 1.5], colors="none", hatches=["///"])
            ax.contour(x, y, fmap.good.astype(float), levels=[0.5], colors="red", linewidths=1.0)
        if poses is not None and len(poses):
            ax.plot(np.degrees(poses[:, 1]), np.degrees(poses[:, 2]), "o", mfc="white", mec="black", ms=5,
                    label="planned poses (their q2, q3)")
        if test_q is not None:
            ax.plot(math.degrees(test_q[1]), math.degrees(test_q[2]), "*", color="orange", mec="black", ms=13,
                    label="test pose")
        ax.set_xlabel("q2 [deg]")
        ax.set_ylabel("q3 [deg]")
        ax.set_title(title, fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        axes[0].legend(loc="lower left", fontsize=8)
    w = fmap.wrench
    fig.suptitle(f"first-order model, {fmap.torque}-based torques, load ({w[0]:.0f}, {w[1]:.0f}, {w[2]:.0f}) N\n"
                 f"good enough where every stiffness error < {fmap.threshold * 100:.0f} % "
                 f"(not hatched, {fmap.good_fraction * 100:.0f} % of the grid); blank: above 10 %", fontsize=9)
    fig.savefig(path, dpi=110)
