"""The tracker's noise law estimated from repeated readings (model/tracker_noise.py).

Readings that repeat ``(pose, load, marker)`` measure one position; their spread
along the beam (the direction from the tracker head, the origin of the tracker's
measurement frame) and across it, group by group at each group's range, is what
fixes the law ``sigma(R) = a + b·R`` in each direction. Each group's sum of
squares along the beam is ``sigma_along(R)² chi²(n−1)``, across it
``sigma_across(R)² chi²(2(n−1))``: the estimate is the maximum of that
likelihood over ``a, b >= 0`` (scipy, bounded), a few groups whose spread is far
beyond the first fit's law (a beam break inside a group) left out and the law
fitted again, so one bad reading does not set it.

A law is estimated only where the repeats are enough (:data:`MIN_REPEAT_DOF`
degrees of freedom along the beam); else the law the cell states
(cell.toml ``[tracker] noise``) is used, else none (docs/physics.md: "Weights,
floors and outlier tests use that law where readings are not repeated enough to
estimate it").
"""

from __future__ import annotations

import numpy as np

from elastocal.identify.blas import one_blas_thread
from elastocal.identify.grouping import combine, first_seen, group_count, group_sum
from elastocal.model.tracker_noise import TrackerNoise

#: degrees of freedom along the beam (repeated readings beyond each group's first) a law needs
MIN_REPEAT_DOF = 40
#: a group whose spread has this small a p-value under the first fit is left out of the second
TRIM_P = 1e-4


def repeat_groups(table) -> tuple[np.ndarray, int]:
    """(code per row, number of groups): the (pose, load, marker) repeat groups, in order
    of first appearance."""
    key = combine(first_seen(table.pose)[0], first_seen(table.load)[0], first_seen(table.marker)[0])
    code, first = first_seen(key)
    return code, len(first)


def _spread(xyz: np.ndarray, code: np.ndarray, n_groups: int):
    """Per repeated group: range [m], along-beam and across-beam sums of squares [m²], n − 1."""
    n = group_count(code, n_groups)
    mean = group_sum(code, xyz, n_groups) / np.maximum(n, 1)[:, None]
    rng = np.linalg.norm(mean, axis=1)
    u = mean / np.where(rng > 0, rng, 1.0)[:, None]
    e = xyz - mean[code]
    along = np.einsum("ij,ij->i", e, u[code])
    ss_al = group_sum(code, along ** 2, n_groups)
    ss_ac = group_sum(code, np.einsum("ij,ij->i", e, e), n_groups) - ss_al
    rep = n > 1
    return rng[rep], ss_al[rep], np.maximum(ss_ac[rep], 0.0), (n[rep] - 1).astype(float)


def _fit_law(rng: np.ndarray, ss: np.ndarray, dof: np.ndarray) -> tuple[float, float]:
    """(a, b) >= 0 maximising the chi-square likelihood of ``ss ~ (a + b R)² chi²(dof)``."""
    import scipy.optimize  # imported where used: tables without repeats never fit a law

    s0 = float(np.sqrt(np.sum(ss) / np.sum(dof)))
    if not s0 > 0:
        return 0.0, 0.0
    r_scale = float(np.median(rng)) if np.median(rng) > 0 else 1.0
    x_scale = np.array([s0, s0 / r_scale])

    def nll(x: np.ndarray) -> tuple[float, np.ndarray]:
        a, b = x * x_scale
        sig = np.maximum(a + b * rng, 1e-12 * s0)
        v = sig ** 2
        f = float(np.sum(dof * np.log(v) + ss / v))
        dv = dof / v - ss / v ** 2                     # d f / d v
        dsig = dv * 2.0 * sig
        return f, np.array([np.sum(dsig), np.sum(dsig * rng)]) * x_scale

    best = None
    for start in ((1.0, 0.0), (0.5, 0.5), (0.0, 1.0)):
        res = scipy.optimize.minimize(nll, np.array(start), jac=True, method="L-BFGS-B",
                                      bounds=[(0.0, None), (0.0, None)])
        if best is None or res.fun < best.fun:
            best = res
    a, b = best.x * x_scale
    return float(a), float(b)


@one_blas_thread          # hundreds of tiny L-BFGS-B steps: BLAS threads only wait on each other
def estimate_tracker_noise(table, *, exclude: np.ndarray | None = None,
                           min_dof: int = MIN_REPEAT_DOF) -> TrackerNoise | None:
    """The law from the table's repeated readings (rows ``exclude`` left out), or None
    when they are not enough (fewer than ``min_dof`` repeats along the beam)."""
    code, n_groups = repeat_groups(table)
    keep = np.ones(len(code), dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    xyz = np.asarray(table.xyz, dtype=float)
    keep &= np.all(np.isfinite(xyz), axis=1)
    code_k, n_k = first_seen(code[keep])
    rng, ss_al, ss_ac, dof = _spread(xyz[keep], code_k, len(n_k))
    if dof.sum() < min_dof:
        return None
    import scipy.stats  # imported where used: scipy.stats costs the commands that never test a quarter second

    law = None
    use = np.ones(len(rng), dtype=bool)
    for _ in range(2):          # fit, leave out the groups far beyond it, fit again
        a_al, b_al = _fit_law(rng[use], ss_al[use], dof[use])
        a_ac, b_ac = _fit_law(rng[use], ss_ac[use], 2 * dof[use])
        if a_al + b_al <= 0 or a_ac + b_ac <= 0:
            return None         # readings repeated to the last bit: no noise to model
        law = TrackerNoise(a_al, b_al, a_ac, b_ac, source=f"estimated from {int(use.sum())} repeat groups")
        v_al, v_ac = law.sigma_along(rng) ** 2, law.sigma_across(rng) ** 2
        p = scipy.stats.chi2.sf(ss_al / v_al + ss_ac / v_ac, 3 * dof)
        use = p >= TRIM_P
        if use.all() or use.sum() < 0.5 * len(use):
            break
    return law
