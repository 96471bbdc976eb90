"""Poses that make the kinematic set observable too.

The stiffness plan (design/search.py) minimises the industry measure K40 at
the test pose. An absolute calibration also identifies the geometry and the
tracker registration (identify/absolute.py) from the unloaded absolute
positions, whose information about the identifiable kinematic set
(identify/kinematics.py) is, per pose,

    K_i = J_i^T J_i / (sigma^2 / repeats),   J_i = d p_markers / d (frame, kinematic parameters)

with the angular parameters scaled by :data:`LENGTH_SCALE_M` (a radian
becomes the metres it moves a point that far away), so that all columns are
metres. Two standard measures of a pose set are reported next to K40:

* the observability index O1 (Borm and Menq): the geometric mean of the
  singular values of the scaled regressor over the square root of its rows;
* the A-optimal criterion ``trace(M_k^-1)``, ``M_k = sum K_i``: the summed
  variance of the scaled parameters [m^2].

:func:`plan_for_geometry` starts from the stiffness plan and exchanges poses
(Fedorov, the loads fixed) to minimise ``K40 / K40_start + trace(M_k^-1) /
trace(M_k,start^-1)``: both measures relative to the stiffness plan, equal
weight, so the geometry gains what it can for little K40.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from elastocal.identify import kinematics as kin
from elastocal.design.search import (
    ExperimentDesign,
    _combo_info,
    _phi,
    _weight,
    _weighted_info_parts,
)
from elastocal.design.candidates import Candidates, TestPose, Workspace, load_directions
from elastocal.design.measures import (
    DEFAULT_PRIOR_STIFFNESS,
    NoiseModel,
    a0_matrix,
    evaluate_design,
)
from elastocal.model.robot import Robot

#: a radian of a joint zero or twist counts as the metres it moves a point this far
LENGTH_SCALE_M = 1.0
FRAME = ("rx", "ry", "rz", "tx", "ty", "tz")


@dataclass(frozen=True)
class GeometryQuality:
    """How well a pose set determines the kinematic set and the registration."""

    o1: float                       # observability index of the scaled regressor [m]
    a_optimal_m2: float             # trace(M_k^-1) [m^2]
    max_std_m: float                # largest predicted std of a scaled parameter [m]
    parameters: tuple[str, ...]     # the identifiable set (frame and kinematic)
    unidentifiable: tuple[str, ...]


def _regressors(robot: Robot, q: np.ndarray, markers: Sequence[str]) -> tuple[np.ndarray, tuple[str, ...]]:
    """Scaled regressors (n, 3M, p) of the unloaded marker positions in the frame's
    six and every kinematic parameter (base axes; the frame as small rotations
    about and translations along them)."""
    names = kin.parameter_names(robot, markers)
    out = np.empty((len(q), 3 * len(markers), 6 + len(names)))
    data = robot.create_data()
    for i, qi in enumerate(q):
        theta = robot.theta(qi)
        pos, jac = kin.position_jacobian(robot, theta, list(markers), names, data=data)
        rows = np.zeros((len(markers), 3, 6 + len(names)))
        for m, p in enumerate(pos):
            rows[m, :, :3] = -np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
            rows[m, :, 3:6] = np.eye(3)
        rows[:, :, 6:] = jac
        out[i] = rows.reshape(3 * len(markers), -1)
    angular = np.array([True] * 3 + [False] * 3 + [kin.unit_of(n) == "rad" for n in names])
    out[:, :, angular] *= LENGTH_SCALE_M
    return out, (*FRAME, *names)


def _identifiable(regressors: np.ndarray, names: Sequence[str]) -> np.ndarray:
    stacked = regressors.reshape(-1, regressors.shape[2])
    kinematic = [n for n in names if n not in FRAME]
    priority = list(FRAME) + [n for n in kinematic if n.startswith(("dx_", "dy_", "dz_"))]
    return kin.identifiable_set(stacked, names, priority).keep


def geometry_quality(regressors: np.ndarray, names: Sequence[str], keep: np.ndarray,
                     noise: NoiseModel) -> GeometryQuality:
    a = regressors[:, :, keep].reshape(-1, int(keep.sum()))
    sv = np.linalg.svd(a, compute_uv=False)
    o1 = float(np.exp(np.mean(np.log(np.maximum(sv, 1e-300)))) / np.sqrt(a.shape[0]))
    var = noise.tracker_m ** 2 / noise.repeats
    try:
        cov = np.linalg.inv(a.T @ a) * var
        a_opt, max_std = float(np.trace(cov)), float(np.sqrt(np.max(np.diag(cov))))
    except np.linalg.LinAlgError:
        a_opt = max_std = float("inf")
    return GeometryQuality(o1=o1, a_optimal_m2=a_opt, max_std_m=max_std,
                           parameters=tuple(n for n, k in zip(names, keep) if k),
                           unidentifiable=tuple(n for n, k in zip(names, keep) if not k))


@dataclass(frozen=True, eq=False)
class GeometryPlan:
    design: ExperimentDesign            # the poses for stiffness and geometry
    quality: GeometryQuality
    stiffness_only_k40: float           # K40 of the stiffness plan it started from
    stiffness_only: GeometryQuality     # that plan's geometry measures
    random: tuple[GeometryQuality, ...]  # random pose sets of the same size
    exchanges: int

    def to_json(self) -> dict:
        o1r = [g.o1 for g in self.random]
        ar = [g.a_optimal_m2 for g in self.random]
        return {"o1": self.quality.o1, "o1_stiffness_only": self.stiffness_only.o1,
                "o1_random_median": float(np.median(o1r)),
                "a_optimal": {"value": self.quality.a_optimal_m2, "unit": "m^2"},
                "a_optimal_stiffness_only": {"value": self.stiffness_only.a_optimal_m2, "unit": "m^2"},
                "a_optimal_random_median": {"value": float(np.median(ar)), "unit": "m^2"},
                "max_std": {"value": self.quality.max_std_m, "unit": "m"},
                "k40_stiffness_only": self.stiffness_only_k40, "identifiable": list(self.quality.parameters),
                "unidentifiable": list(self.quality.unidentifiable), "exchanges": self.exchanges}


def plan_for_geometry(robot: Robot, candidates: Candidates, design: ExperimentDesign, test: TestPose, *,
                      workspace: Workspace, markers: Sequence[str],
                      prior_stiffness: Sequence[float] = DEFAULT_PRIOR_STIFFNESS, noise: NoiseModel = NoiseModel(),
                      rng: np.random.Generator, random_draws: int = 20, max_sweeps: int = 6) -> GeometryPlan:
    """Exchange the stiffness plan's poses for ones that also observe the
    kinematic set (module docstring); the loads stay those of ``design``."""
    c_prior = 1.0 / np.asarray(prior_stiffness, dtype=float)
    dirs = load_directions(workspace.directions, robot.gravity)
    chosen = [int(np.argmin(np.linalg.norm(workspace.f_max_n * dirs - f, axis=1))) for f in design.forces]
    h, gamma = _weighted_info_parts(robot, candidates.q, markers, workspace.f_max_n * dirs, c_prior, noise)
    pose_el = _combo_info(h, gamma, chosen)
    weight = _weight(a0_matrix(robot, test) * c_prior[None, :])
    regs, names = _regressors(robot, candidates.q, markers)
    keep = _identifiable(regs, names)
    var = noise.tracker_m ** 2 / noise.repeats
    pose_k = np.einsum("nri,nrj->nij", regs[:, :, keep], regs[:, :, keep]) / var
    sel = np.array(design.candidate_index, dtype=int)
    n_el = pose_el.shape[-1]            # one compliance per joint
    ridge_el = 1e-9 * float(np.mean(np.trace(pose_el, axis1=-2, axis2=-1))) / n_el * np.eye(n_el)
    ridge_k = 1e-9 * float(np.mean(np.trace(pose_k, axis1=-2, axis2=-1))) / len(pose_k[0]) * np.eye(len(pose_k[0]))
    eye_k = np.eye(len(pose_k[0]))
    m_el = ridge_el + pose_el[sel].sum(axis=0)
    m_k = ridge_k + pose_k[sel].sum(axis=0)
    phi_el0 = float(_phi(m_el, weight))
    phi_k0 = float(_phi(m_k, eye_k))
    current = 2.0
    exchanges = 0
    for _ in range(max_sweeps):
        changed = False
        for k in range(len(sel)):
            rest_el = m_el - pose_el[sel[k]]
            rest_k = m_k - pose_k[sel[k]]
            val = _phi(rest_el + pose_el, weight) / phi_el0 + _phi(rest_k + pose_k, eye_k) / phi_k0
            val[sel] = np.inf
            j = int(np.argmin(val))
            if val[j] < current * (1.0 - 1e-9):
                sel[k] = j
                m_el, m_k = rest_el + pose_el[j], rest_k + pose_k[j]
                current = float(val[j])
                exchanges += 1
                changed = True
        if not changed:
            break
    q = candidates.q[sel]
    quality = evaluate_design(robot, q, [np.concatenate([design.forces, np.zeros_like(design.forces)], axis=1)]
                              * len(q), test, markers, prior_stiffness=prior_stiffness, noise=noise)
    new = replace(design, q=q, candidate_index=sel.copy(), quality=quality, exchanges=design.exchanges + exchanges)
    random = tuple(geometry_quality(regs[rng.choice(len(candidates.q), len(sel), replace=False)], names, keep, noise)
                   for _ in range(random_draws))
    return GeometryPlan(design=new, quality=geometry_quality(regs[sel], names, keep, noise),
                        stiffness_only_k40=design.quality.k40,
                        stiffness_only=geometry_quality(regs[design.candidate_index], names, keep, noise),
                        random=random, exchanges=exchanges)
