"""Where the model fails: the residual by pose, marker, joint angle, load and time against
the noise floor, and the structure an unexplained excess follows; the noise algebra of the floor is here too, so that
the static and absolute diagnoses share one definition of it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse
import scipy.stats

from elastocal.model.robot import Robot
from elastocal.identify.static import StaticDataset, StaticFit


#: a feature the excess follows (rank correlation) is reported below this p
FEATURE_P = 5e-3
#: a pose holding more than this share of the excess is named
POSE_SHARE = 0.5


@dataclass(frozen=True)
class GroupSummary:
    """Residual rms per group of deflections (by pose, marker, load, ...)."""

    by: str
    labels: tuple[str, ...]
    rms: np.ndarray          # (G,) residual rms of the group's components [m]
    floor: np.ndarray | None  # (G,) rms that noise alone leaves there [m]
    n: np.ndarray            # (G,) components

    def to_json(self) -> dict:
        return {"by": self.by, "labels": list(self.labels), "rms": self.rms.tolist(),
                "floor": None if self.floor is None else self.floor.tolist(), "n": self.n.tolist(),
                "unit": "m"}


@dataclass(frozen=True, eq=False)
class Where:
    """Where a static fit fails: per-deflection features and group summaries."""

    pose: np.ndarray           # (D,) pose index
    pose_ids: tuple[str, ...]
    marker: np.ndarray         # (D,) marker index
    markers: tuple[str, ...]
    load: np.ndarray           # (D,) load-state id (str)
    q: np.ndarray              # (D, 6) commanded joint angles of the deflection's pose [rad]
    load_size: np.ndarray      # (D,) |F| [N] (or |dGamma| [N·m] without the wrench)
    load_unit: str
    t: np.ndarray              # (D,) time of the loaded readings [s], NaN if unknown
    measured: np.ndarray       # (D, 3) [m]
    predicted: np.ndarray      # (D, 3) [m]
    residual: np.ndarray       # (D, 3) [m]
    noise_var: np.ndarray | None  # (D,) variance noise alone leaves in |residual|^2 [m^2]
    groups: tuple[GroupSummary, ...]

    def group(self, by: str) -> GroupSummary:
        for g in self.groups:
            if g.by == by:
                return g
        raise KeyError(by)

    def to_json(self) -> dict:
        return {g.by: g.to_json() for g in self.groups}


# =================================================================== noise algebra
@dataclass(frozen=True, eq=False)
class _Noise:
    """Noise covariance of a fit's residual space: (I - H) Sigma."""

    cov: scipy.sparse.csr_matrix  # (n, n) Sigma
    basis: np.ndarray             # (n, p) orthonormal basis of the design's columns
    resid_var: np.ndarray         # (n,) diag((I - H) Sigma)
    mean: float                   # tr((I - H) Sigma)
    var: float                    # var of the rss under noise: 2 tr(((I - H) Sigma)^2)


def _noise(fit: StaticFit) -> _Noise:
    """The noise algebra of a fit that has a noise model (repeated readings).

    For a GLS fit the residual is ``L (I - QQ') L^-1 e`` (``Sigma = LL'``, ``Q``
    an orthonormal basis of the whitened design): its covariance is
    ``L (I - QQ') L'``; ``basis`` is then the whitened basis ``Q``."""
    if fit.noise_blocks is None:
        raise ValueError("the fit has no noise model (no repeated readings)")
    n = fit.n
    a = fit.design if fit.whitening is None else fit.whiten(fit.design)
    if a.shape[1]:
        u, s, _ = np.linalg.svd(a, full_matrices=False)
        basis = u[:, s > s[0] * 1e-12]
    else:
        basis = np.zeros((n, 0))
    rows = np.concatenate([r for r, _ in fit.noise_blocks])
    blocks = [c for _, c in fit.noise_blocks]
    stacked = scipy.sparse.block_diag(blocks, format="csr")
    order = np.empty(n, dtype=int)          # place the blocks at their rows
    order[rows] = np.arange(len(rows))
    cov = stacked[order][:, order]
    diag = cov.diagonal()
    if fit.whitening is not None:
        lq = fit.unwhiten(basis)
        resid_var = diag - np.einsum("ij,ij->i", lq, lq)
        mean = float(resid_var.sum())
        return _Noise(cov, basis, resid_var, mean, 2.0 * mean**2 / max(n - basis.shape[1], 1))
    sb = cov @ basis                        # Sigma Q
    bsb = basis.T @ sb                      # Q' Sigma Q
    resid_var = diag - np.einsum("ij,ij->i", basis, sb)
    mean = float(diag.sum() - np.trace(bsb))
    tr_s2 = float(sum((c * c).sum() for c in blocks))
    s2b = cov @ sb                          # Sigma^2 Q
    var = 2.0 * (tr_s2 - 2.0 * float(np.einsum("ij,ij->", basis, s2b)) + float((bsb * bsb).sum()))
    return _Noise(cov, basis, resid_var, mean, max(var, 1e-300))


def excess_p_value(fit: StaticFit) -> float | None:
    """P-value of the residual sum of squares under noise alone (scaled
    chi-square matched to its mean and variance); None without repeats."""
    if fit.noise_blocks is None:
        return None
    if fit.rss_whitened is not None:       # GLS: chi-square with n - p degrees of freedom
        return float(scipy.stats.chi2.sf(fit.rss_whitened, max(fit.n - fit.n_params, 1)))
    nz = _noise(fit)
    g = nz.var / (2.0 * nz.mean)
    h = 2.0 * nz.mean**2 / nz.var
    return float(scipy.stats.chi2.sf(fit.rss / g, h))


# =================================================================== where
def _load_sizes(robot: Robot, ds: StaticDataset) -> tuple[np.ndarray, str]:
    sl, sr = ds.defl_state, ds.defl_ref
    if ds.has_wrench:
        return np.linalg.norm(ds.state_wrench[sl, :3] - ds.state_wrench[sr, :3], axis=1), "N"
    d_tau = (ds.state_currents[sl] - ds.state_currents[sr]) * robot.torque_constants
    return np.linalg.norm(d_tau, axis=1), "N*m"


def _bins(values: np.ndarray, n_bins: int, unit: str, fmt: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """Equal-width bins over the range of ``values``: (bin index per value, labels)."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if hi - lo <= 0.0:
        return np.zeros(len(values), dtype=int), (f"{lo:{fmt}} {unit}",)
    edges = np.linspace(lo, hi, n_bins + 1)
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n_bins - 1)
    labels = tuple(f"{edges[k]:{fmt}}..{edges[k + 1]:{fmt}} {unit}" for k in range(n_bins))
    used = np.unique(idx)
    remap = {old: new for new, old in enumerate(used)}
    return np.array([remap[i] for i in idx]), tuple(labels[i] for i in used)


def where_it_fails(robot: Robot, fit: StaticFit, *, n_bins: int = 6, noise: bool = True) -> Where:
    """Residual summaries of a static fit by pose, marker, load state, joint
    angle (each of q1..qN), load size and time; with ``noise`` (and repeated
    readings), what noise alone leaves in each group."""
    ds = fit.dataset
    pose = ds.state_pose[ds.defl_state]
    q = ds.q[pose]
    load_size, load_unit = _load_sizes(robot, ds)
    resid = fit.residuals
    sq = (resid**2).sum(axis=1)
    noise_var = None
    if noise and fit.noise_blocks is not None:
        noise_var = _noise(fit).resid_var.reshape(-1, 3).sum(axis=1)

    def summary(by: str, index: np.ndarray, labels: Sequence[str]) -> GroupSummary:
        g = len(labels)
        n = np.bincount(index, minlength=g) * 3
        ss = np.bincount(index, weights=sq, minlength=g)
        rms = np.sqrt(ss / np.maximum(n, 1))
        floor = None
        if noise_var is not None:
            floor = np.sqrt(np.bincount(index, weights=noise_var, minlength=g) / np.maximum(n, 1))
        return GroupSummary(by, tuple(labels), rms, floor, n)

    groups = [
        summary("pose", pose, ds.pose_ids),
        summary("marker", ds.defl_marker, ds.markers),
    ]
    loads = tuple(dict.fromkeys(ds.state_load[ds.defl_state]))
    groups.append(summary("load", np.array([loads.index(x) for x in ds.state_load[ds.defl_state]]), loads))
    for j in range(q.shape[1]):
        idx, labels = _bins(q[:, j], n_bins, robot.joints[j].unit, ".2f" if robot.joints[j].unit == "rad" else ".3f")
        groups.append(summary(f"q{j + 1}", idx, labels))
    idx, labels = _bins(load_size, n_bins, load_unit, ".0f")
    groups.append(summary("load_size", idx, labels))
    if np.all(np.isfinite(ds.defl_t)):
        idx, labels = _bins(ds.defl_t, n_bins, "s", ".0f")
        groups.append(summary("time", idx, labels))
    return Where(pose=pose, pose_ids=ds.pose_ids, marker=ds.defl_marker, markers=ds.markers,
                 load=ds.state_load[ds.defl_state], q=q, load_size=load_size, load_unit=load_unit,
                 t=ds.defl_t, measured=ds.dP, predicted=fit.predicted, residual=resid,
                 noise_var=noise_var, groups=tuple(groups))


def unexplained_structure(where: Where) -> tuple[str, ...]:
    """What the excess of the residual over the noise follows: sentences.

    Uses the excess ratio of each deflection (|r|^2 over what noise leaves
    there) and rank correlations: with each joint angle over poses, with the
    load size and the time over load states; the share of the excess at the
    worst pose and marker."""
    if where.noise_var is None:
        return ()
    ratio = (where.residual**2).sum(axis=1) / where.noise_var
    excess = np.maximum(ratio - 1.0, 0.0) * where.noise_var
    total = float(excess.sum())
    if total <= 0.0:
        return ()
    found: list[tuple[float, str]] = []
    n_pose = len(where.pose_ids)
    pose_ratio = np.array([ratio[where.pose == p].mean() for p in range(n_pose)])
    if n_pose >= 5:
        for j in range(where.q.shape[1]):         # every joint of the chain
            qj = np.array([where.q[where.pose == p][0, j] for p in range(n_pose)])
            if np.ptp(qj) == 0.0:
                continue
            rho, p = scipy.stats.spearmanr(qj, pose_ratio)
            if np.isfinite(p) and p < FEATURE_P:
                word = "grows" if rho > 0 else "falls"
                found.append((p, f"residual {word} with q{j + 1} (rank correlation {rho:+.2f} over "
                                 f"{n_pose} poses)"))
    states = sorted({(int(a), str(b)) for a, b in zip(where.pose, where.load)})
    if len(states) >= 5:
        st_ratio, st_load, st_t = [], [], []
        for pose, load in states:
            m = (where.pose == pose) & (where.load == load)
            st_ratio.append(ratio[m].mean())
            st_load.append(where.load_size[m][0])
            st_t.append(where.t[m].mean())
        st_ratio = np.array(st_ratio)
        for name, values in (("the load", np.array(st_load)), ("time", np.array(st_t))):
            if not np.all(np.isfinite(values)) or np.ptp(values) == 0.0:
                continue
            rho, p = scipy.stats.spearmanr(values, st_ratio)
            if np.isfinite(p) and p < FEATURE_P:
                word = "grows" if rho > 0 else "falls"
                found.append((p, f"residual {word} with {name} (rank correlation {rho:+.2f} over "
                                 f"{len(states)} load states)"))
    if len(where.markers) > 1:
        groups = [ratio[where.marker == m] for m in range(len(where.markers))]
        if all(len(g) > 1 for g in groups):
            _, p = scipy.stats.kruskal(*groups)
            if np.isfinite(p) and p < FEATURE_P:
                worst = int(np.argmax([g.mean() for g in groups]))
                m = where.marker == worst
                ratio_rms = math.sqrt(float((where.residual[m] ** 2).sum() / where.noise_var[m].sum()))
                found.append((p, f"residual is largest at marker {where.markers[worst]} "
                                 f"({ratio_rms:.1f}x the noise rms there)"))
    pose_excess = np.array([excess[where.pose == p].sum() for p in range(n_pose)])
    worst = int(np.argmax(pose_excess))
    if n_pose > 2 and pose_excess[worst] > POSE_SHARE * total:
        found.append((0.0, f"{100 * pose_excess[worst] / total:.0f} % of the excess is at pose "
                           f"{where.pose_ids[worst]}: check that pose's readings"))
    found.sort(key=lambda x: x[0])
    return tuple(text for _, text in found)
