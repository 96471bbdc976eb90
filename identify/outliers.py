"""Outliers: single tracker readings far off their repeats (docs/cli.md ``outliers``).

The readings that repeat ``(pose, load, marker)`` measure one position; a
reading far off the others (a beam break, a reflector knocked, a reading of the
wrong reflector) is found by a robust test:

* the scale is robust: the tracker's repeatability from the *median* over the
  repeat groups of their sample variance, corrected by the median of its
  chi-square distribution, so a few bad readings do not inflate it;
* each reading is compared with the mean of the *other* readings of its group
  (leave-one-out, variance ``sigma^2 (1 + 1/(n-1))`` per coordinate); the
  statistic is chi-square with 3 degrees of freedom under noise;
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
import scipy.stats

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


def _groups(table) -> list[np.ndarray]:
    keys: dict[tuple[str, str, str], list[int]] = {}
    for i, key in enumerate(zip(table.pose, table.load, table.marker)):
        keys.setdefault(key, []).append(i)
    return [np.array(v) for v in keys.values()]


def robust_sigma(xyz: np.ndarray, groups: list[np.ndarray]) -> float | None:
    """Tracker repeatability per coordinate [m] from the median group variance."""
    dof = np.array([3 * (len(g) - 1) for g in groups if len(g) > 1])
    s2 = np.array([float(((xyz[g] - xyz[g].mean(axis=0)) ** 2).sum()) / (3 * (len(g) - 1))
                   for g in groups if len(g) > 1])
    if s2.size == 0:
        return None
    # each s2 is sigma^2 chi2(dof)/dof: correct the median by that distribution's median
    median_scale = np.median(scipy.stats.chi2.median(dof) / dof)
    return float(np.sqrt(np.median(s2) / median_scale))


def find_outliers(table, *, alpha: float = ALPHA) -> tuple[Outlier, ...]:
    """Readings of a static table far off their repeats, worst first."""
    xyz = table.xyz
    groups = _groups(table)
    sigma = robust_sigma(xyz, groups)
    tested = sum(len(g) for g in groups if len(g) >= 3)
    if sigma is None or not sigma > 0 or tested == 0:
        return ()
    limit = alpha / tested
    found: list[Outlier] = []
    for g in groups:
        left = list(g)
        while len(left) >= 3:
            x = xyz[left]
            n = len(left)
            others = (x.sum(axis=0) - x) / (n - 1)
            d2 = ((x - others) ** 2).sum(axis=1) / (sigma**2 * (1.0 + 1.0 / (n - 1)))
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


def outlier_mask(n_rows: int, outliers) -> np.ndarray:
    """(n_rows,) bool: True at the outliers' rows."""
    mask = np.zeros(n_rows, dtype=bool)
    mask[[o.row for o in outliers]] = True
    return mask


def without_outliers(table):
    """(the table without its outliers, the outliers marked excluded)."""
    from dataclasses import replace

    found = find_outliers(table)
    if not found:
        return table, ()
    return table.subset(~outlier_mask(len(table), found)), tuple(replace(o, excluded=True) for o in found)
