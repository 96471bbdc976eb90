"""Design of experiments, the inputs: where the robot works (:class:`TestPose`),
what a calibration pose and load must respect (:class:`Workspace`), and the
candidate poses and load directions the search chooses from (docs/physics.md "Design of
experiments"). The measures are in :mod:`elastocal.design.measures`, the
search in :mod:`elastocal.design.search`."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.robot import LOAD_FRAME, Robot


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
        if not q or not all(math.isfinite(v) for v in q):
            raise InputError(f"expected one finite value per joint, got {self.q!r}", argument="test_pose")
        if len(w) != 6 or not all(math.isfinite(v) for v in w):
            raise InputError(f"expected 6 finite wrench values, got {self.wrench!r}", argument="wrench")
        if not any(w):
            raise InputError("the process load is zero: nothing deflects at the test pose", argument="wrench")
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
            raise InputError(f"must be a positive force [N], got {self.f_max_n!r}", argument="f_max")
        if self.directions not in DIRECTION_KINDS:
            raise InputError(f"must be one of {', '.join(DIRECTION_KINDS)}, got {self.directions!r}",
                             argument="directions")
        if not self.max_height_m > self.min_height_m:
            raise InputError(f"max height {self.max_height_m} m is not above min height {self.min_height_m} m",
                             argument="max_height")
        for name, argument in (("link_radius_m", "link_radius"), ("tracker_range_m", "tracker_range_m")):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"must be > 0, got {v!r}", argument=argument)
        if self.base_p_tracker is not None:
            p = tuple(float(v) for v in self.base_p_tracker)
            if len(p) != 3 or not all(math.isfinite(v) for v in p):
                raise InputError(f"expected x,y,z in metres, got {self.base_p_tracker!r}",
                                 argument="tracker_position")
            object.__setattr__(self, "base_p_tracker", p)


# ================================================================ kinematics
def _poses(robot: Robot, q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != robot.n_joints:
        raise ValueError(f"expected poses of shape (n, {robot.n_joints}), got {q.shape}")
    return q


#: the joints of a six-axis arm; joints before them (a track) are auxiliary
ARM_JOINTS = 6


def _auxiliary(robot: Robot) -> int:
    return max(robot.n_joints - ARM_JOINTS, 0)


def _joint_origins(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(n, N + 2, 3): base origin, the N joint origins, the load point."""
    model = robot.model
    data = model.createData()
    fid = model.getFrameId(LOAD_FRAME)
    n = robot.n_joints
    out = np.empty((len(q), n + 2, 3))
    for i, qi in enumerate(q):
        pin.framesForwardKinematics(model, data, robot.theta(qi))
        out[i, 0] = 0.0
        for j in range(1, n + 1):
            out[i, j] = data.oMi[j].translation
        out[i, n + 1] = data.oMf[fid].translation
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
    q = _poses(robot, q)
    origins = _joint_origins(robot, q)
    n_joints, aux = robot.n_joints, _auxiliary(robot)
    data = robot.create_data()
    mpos = np.array([robot.positions(robot.theta(qi), list(markers), data=data) for qi in q])  # (n, M, 3)
    load = origins[:, n_joints + 1]
    out = np.full(len(q), -1)
    # every joint origin from the arm's elbow (its third joint) on, and the load point
    low = np.minimum(origins[:, aux + 3:n_joints + 2, 2].min(axis=1), mpos[:, :, 2].min(axis=1))
    height_bad = (low < workspace.min_height_m) | (load[:, 2] > workspace.max_height_m)
    out[height_bad] = 0
    arm_axis = origins[:, aux + 1, :2]            # the arm's first axis (vertical), where a track put it
    reach_bad = np.hypot(*(load[:, :2] - arm_axis).T) < workspace.min_radius_m
    out[(out < 0) & reach_bad] = 1
    if workspace.base_p_tracker is not None:
        tracker = np.array(workspace.base_p_tracker)
        seg_a = origins[:, :n_joints]          # capsules: base-J1, J1-J2, ..., J(N-1)-JN
        seg_b = origins[:, 1:n_joints + 1]
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

    q: np.ndarray                         # (n, N)
    sampled: int                          # poses drawn
    accepted: int                         # of them respecting the workspace (the first n are kept)
    rejected: tuple[tuple[str, int], ...]  # (reason, count) of the others


def sample_candidates(robot: Robot, n: int, rng: np.random.Generator, workspace: Workspace,
                      markers: Sequence[str], *, max_sampled: int | None = None) -> Candidates:
    """``n`` poses drawn uniformly within the joint limits (q1, q4, q6 within
    +-pi) that respect ``workspace``; raises InputError when fewer than ``n``
    of ``max_sampled`` (default 50 n) draws do."""
    if n < 1:
        raise InputError(f"must be >= 1, got {n}", argument="candidates")
    lo = robot.lower.copy()
    hi = robot.upper.copy()
    for j in (0, 3, 5):             # the arm's first, fourth and sixth joints (after a track's)
        j += _auxiliary(robot)
        lo[j], hi[j] = max(lo[j], -math.pi), min(hi[j], math.pi)
    limit = max_sampled if max_sampled is not None else 50 * n
    kept: list[np.ndarray] = []
    counts = np.zeros(len(REJECTIONS), dtype=int)
    sampled = 0
    while len(kept) < n and sampled < limit:
        batch = min(max(2 * (n - len(kept)), 64), limit - sampled)
        q = rng.uniform(lo, hi, size=(batch, robot.n_joints))
        sampled += batch
        code = check_poses(robot, q, workspace, markers)
        for k in range(len(REJECTIONS)):
            counts[k] += int(np.sum(code == k))
        kept.extend(q[code < 0])
    if len(kept) < n:
        reasons = ", ".join(f"{c} {r}" for r, c in zip(REJECTIONS, counts) if c)
        raise InputError(f"only {len(kept)} of {sampled} sampled poses respect the workspace (rejected: {reasons}); "
                         "relax the constraints or check the tracker position", argument="candidates")
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
        raise InputError(f"must be one of {', '.join(DIRECTION_KINDS)}, got {kind!r}", argument="directions")
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
