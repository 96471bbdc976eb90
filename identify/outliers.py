"""Outliers: single tracker readings far off their repeats (docs/cli.md ``outliers``).

The readings that repeat ``(pose, load, marker)`` measure one position; a
reading far off the others (a beam break, a reflector knocked, a reading of the
wrong reflector) is found by a robust test:

* the scale is the tracker's noise law where there is one
  (model/tracker_noise.py: a constant plus a part growing with range, along
  and across the beam; estimated from the repeats or stated by the cell), so
  a far reading is judged by the noise at its range; else it is robust: the
  tracker's repeatability from the *median* over the repeat groups of their
  sample variance, corrected by the median of its chi-square distribution, so
  a few bad readings do not inflate it;
* each reading is compared with the mean of the *other* readings of its group
  (leave-one-out, covariance ``Sigma (1 + 1/(n-1))``, ``Sigma`` the law's at the
  group's position or ``sigma^2 I``); the statistic is chi-square with 3 degrees of freedom under noise;
* the worst reading of a group is flagged when its p-value is below
  ``ALPHA / N`` (Bonferroni over the N readings tested: the chance that a
  complete dataset shows any outlier is below ``ALPHA``), then removed and the
  rest of its group tested again while three or more readings remain.

A group needs three readings or more (two readings cannot tell which one is
off). Outliers are left out of the noise-floor estimate always
(identify/static.py ``build_dataset``) and out of the fit with
``--exclude-outliers``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.identify.grouping import combine, first_seen, group_count, group_sum, sums_per_group

#: chance that a complete dataset shows any outlier (Bonferroni over its readings)
ALPHA = 1e-3


@dataclass(frozen=True)
class Outlier:
    """One reading far off its repeats."""

    row: int            # index in the table
    line: int           # 1-based line of the input file (header = 1)
    pose: str
    load: str
    marker: str
    residual: float     # distance from the mean of its repeats [m]
    p_value: float
    excluded: bool = False   # left out of the fit (--exclude-outliers)

    def to_json(self) -> dict:
        return {"line": self.line, "pose": self.pose, "load": self.load, "marker": self.marker,
                "residual": self.residual, "p_value": self.p_value, "excluded": self.excluded}


def _group_codes(table) -> tuple[np.ndarray, int]:
    """(code per row, number of groups): the (pose, load, marker) repeat groups numbered in
    order of first appearance (identify/grouping.py)."""
    key = combine(first_seen(table.pose)[0], first_seen(table.load)[0], first_seen(table.marker)[0])
    code, first = first_seen(key)
    return code, len(first)


def robust_sigma(xyz: np.ndarray, groups: list[np.ndarray]) -> float | None:
    """Tracker repeatability per coordinate [m] from the median group variance."""
    dof = np.array([3 * (len(g) - 1) for g in groups if len(g) > 1])
    s2 = np.array([float(((xyz[g] - xyz[g].mean(axis=0)) ** 2).sum()) / (3 * (len(g) - 1))
                   for g in groups if len(g) > 1])
    if s2.size == 0:
        return None
    import scipy.stats  # imported where used: scipy.stats costs the commands that never test a quarter second

    # each s2 is sigma^2 chi2(dof)/dof: correct the median by that distribution's median
    median_scale = np.median(scipy.stats.chi2.median(dof) / dof)
    return float(np.sqrt(np.median(s2) / median_scale))


def _robust_sigma_grouped(xyz: np.ndarray, code: np.ndarray, n_groups: int) -> float | None:
    """robust_sigma over the groups numbered by ``code``, in one grouped pass."""
    n = group_count(code, n_groups)
    repeated = n > 1
    if not np.any(repeated):
        return None
    mean = group_sum(code, xyz, n_groups) / np.maximum(n, 1)[:, None]
    rows = np.flatnonzero(repeated[code])
    rows = rows[np.argsort(code[rows], kind="stable")]
    dof = 3 * (n[repeated] - 1)
    s2 = sums_per_group((xyz[rows] - mean[code[rows]]) ** 2, n[repeated]) / dof
    import scipy.stats  # imported where used: scipy.stats costs the commands that never test a quarter second

    # each s2 is sigma^2 chi2(dof)/dof: correct the median by that distribution's median
    median_scale = np.median(scipy.stats.chi2.median(dof) / dof)
    return float(np.sqrt(np.median(s2) / median_scale))


def _inverse_covariances(xyz: np.ndarray, code: np.ndarray, n_groups: int, noise, sigma: float | None):
    """(G, 3, 3) inverse covariance of one reading of each group: the law's at the group's
    mean position, else ``I / sigma^2``."""
    if noise is None:
        return np.broadcast_to(np.eye(3) / sigma**2, (n_groups, 3, 3))
    n = np.maximum(group_count(code, n_groups), 1)
    return np.linalg.inv(noise.covariance(group_sum(code, xyz, n_groups) / n[:, None]))


def find_outliers(table, *, alpha: float = ALPHA, noise=None) -> tuple[Outlier, ...]:
    """Readings of a static table far off their repeats, worst first; ``noise`` the
    tracker's law (:class:`~elastocal.model.tracker_noise.TrackerNoise`) or None (a robust
    constant from the repeats).

    The first test of every group is one grouped pass over the rows; only the groups whose
    worst reading fails it are tested again reading by reading."""
    xyz = table.xyz
    code, n_groups = _group_codes(table)
    sigma = _robust_sigma_grouped(xyz, code, n_groups) if noise is None else 1.0
    n = group_count(code, n_groups)
    tested = int(n[n >= 3].sum())
    if sigma is None or not sigma > 0 or tested == 0:
        return ()
    import scipy.stats  # imported where used: scipy.stats costs the commands that never test a quarter second

    w = _inverse_covariances(xyz, code, n_groups, noise, sigma)
    limit = alpha / tested
    big = n >= 3
    rows = np.flatnonzero(big[code])
    g = code[rows]
    x = xyz[rows]
    ng = n[g][:, None]
    others = (group_sum(g, x, n_groups)[g] - x) / (ng - 1)
    e = x - others
    d2 = np.einsum("ni,nij,nj->n", e, w[g], e) / (1.0 + 1.0 / (ng[:, 0] - 1))
    worst = np.full(n_groups, -np.inf)
    np.maximum.at(worst, g, d2)
    candidates = np.flatnonzero(big & (scipy.stats.chi2.sf(np.where(big, worst, 0.0), 3) < limit * (1 + 1e-6)))
    found: list[Outlier] = []
    if candidates.size:
        members = np.argsort(code, kind="stable")
        starts = np.concatenate([[0], np.cumsum(n)])
        for c in candidates:
            left = list(members[starts[c]:starts[c + 1]])
            while len(left) >= 3:
                x = xyz[left]
                m = len(left)
                others = (x.sum(axis=0) - x) / (m - 1)
                e = x - others
                d2 = np.einsum("ni,ij,nj->n", e, w[c], e) / (1.0 + 1.0 / (m - 1))
                k = int(np.argmax(d2))
                p = float(scipy.stats.chi2.sf(d2[k], 3))
                if p >= limit:
                    break
                i = left.pop(k)
                found.append(Outlier(row=int(i), line=int(table.line[i]), pose=str(table.pose[i]),
                                     load=str(table.load[i]), marker=str(table.marker[i]),
                                     residual=float(np.linalg.norm(x[k] - others[k])), p_value=p))
    found.sort(key=lambda o: -o.residual)
    return tuple(found)


def tracker_noise_of(table, stated=None):
    """The tracker's noise law for a table: estimated from its repeats where they are
    enough (identify/trackernoise.py: a first estimate, the outliers it shows left out, and
    estimated again), else ``stated`` (cell.toml ``[tracker] noise``), else None."""
    from elastocal.identify.trackernoise import estimate_tracker_noise

    first = estimate_tracker_noise(table)
    if first is None:
        return stated
    bad = find_outliers(table, noise=first)
    return estimate_tracker_noise(table, exclude=outlier_mask(len(table), bad)) if bad else first


def outlier_mask(n_rows: int, outliers) -> np.ndarray:
    """(n_rows,) bool: True at the outliers' rows."""
    mask = np.zeros(n_rows, dtype=bool)
    mask[[o.row for o in outliers]] = True
    return mask


def without_outliers(table, *, noise=None):
    """(the table without its outliers, the outliers marked excluded); ``noise`` the
    tracker's law stated by the cell (estimated from the repeats where they are enough)."""
    from dataclasses import replace

    found = find_outliers(table, noise=tracker_noise_of(table, noise if noise is not None else table.tracker_noise))
    if not found:
        return table, ()
    return table.subset(~outlier_mask(len(table), found)), tuple(replace(o, excluded=True) for o in found)
