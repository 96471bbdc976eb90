"""The unloaded positions of a check against those of the calibration's own data (docs/check.md).

An unattended check has nobody to hang a load, so it cannot measure a deflection; what the robot
can do alone is go to the check poses and read its markers unloaded. Those readings are compared
with the unloaded readings of the same poses in the data the calibration was identified from:
a knocked link, a slipped joint zero or a bent marker mount moves them, an unchanged robot puts
the markers where they were, up to the tracker's noise and the tracker's placement (the tracker
may have been moved between the sessions, so a rigid motion is fitted and not compared).

Per (pose, marker) the repeated readings are averaged; the tracker's noise per axis is pooled
over all of them (each session its own), so the difference of two means has the variance
``s_b^2 / n_b + s_c^2 / n_c`` per axis. After the weighted rigid fit the residual ``r`` gives
``chi2 = sum r^2 / var`` on ``3 N - 6`` degrees of freedom. Like the absolute check, the
positions count as moved only when the difference is significant *and* its rms exceeds
:data:`FLOOR_RATIO` noise floors (the rms the noise alone leaves): a real robot's return to a
pose scatters a little more than a tracker's repeats show, which is not a change of the robot.

Pure: two static tables in, a frozen :class:`PositionCheck` out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from elastocal.errors import InputError
from elastocal.formats.tables import StaticTable

#: the positions count as moved beyond this many noise floors (as the absolute check's limit)
FLOOR_RATIO = 2.0
#: two readings are of the same pose when every joint agrees within this [rad or m]
SAME_POSE = 1e-3
UNLOADED = "0"


@dataclass(frozen=True, eq=False)
class PositionCheck:
    """Unloaded marker positions of a check against the calibration's data at the same poses."""

    poses: tuple[str, ...]       # the check's pose ids compared
    markers: int                 # (pose, marker) points compared
    rms_m: float                 # rms of the difference after the rigid fit (the tracker's placement)
    max_m: float
    noise_floor_m: float         # rms the tracker's noise alone gives the difference of two means
    chi2: float
    dof: int
    p_value: float
    alpha: float

    @property
    def passed(self) -> bool:
        return self.p_value >= self.alpha or self.rms_m <= FLOOR_RATIO * self.noise_floor_m

    def reason(self) -> str:
        head = (f"{self.rms_m * 1e6:.1f} µm rms (max {self.max_m * 1e6:.1f} µm) at {self.markers} markers of "
                f"{len(self.poses)} poses against the calibration's own readings, tracker placement fitted; "
                f"noise floor {self.noise_floor_m * 1e6:.1f} µm (chi2 {self.chi2:.1f} on {self.dof} dof, "
                f"p = {self.p_value:.2g})")
        if self.passed:
            return f"unloaded positions still valid: {head}"
        return (f"unloaded positions drifted by {self.rms_m * 1e6:.1f} µm rms, over {FLOOR_RATIO:g}x the noise "
                f"floor (the geometry, a joint zero or a marker moved): {head}")

    def to_json(self) -> dict:
        return {"passed": self.passed, "poses": list(self.poses), "n": self.markers, "rms": self.rms_m,
                "max": self.max_m, "noise_floor": self.noise_floor_m, "chi2": self.chi2, "dof": self.dof,
                "p_value": self.p_value, "alpha": self.alpha, "limit_ratio": FLOOR_RATIO, "unit": "m"}


@dataclass(frozen=True)
class _Means:
    keys: tuple[tuple[str, str], ...]     # (pose, marker)
    q: np.ndarray                         # (P, N)
    xyz: np.ndarray                       # (P, 3) mean
    n: np.ndarray                         # (P,) readings
    var: np.ndarray                       # (3,) pooled variance of one reading per axis, NaN without repeats


def _means(table: StaticTable) -> _Means:
    un = table.subset(table.load == UNLOADED)
    keys: dict[tuple[str, str], list[int]] = {}
    for i, key in enumerate(zip(un.pose.tolist(), un.marker.tolist())):
        keys.setdefault(key, []).append(i)
    q, xyz, n = [], [], []
    ss = np.zeros(3)
    dof = 0
    for rows in keys.values():
        x = un.xyz[rows]
        xyz.append(x.mean(axis=0))
        q.append(un.q[rows].mean(axis=0))
        n.append(len(rows))
        ss += np.sum((x - x.mean(axis=0)) ** 2, axis=0)
        dof += len(rows) - 1
    var = ss / dof if dof > 0 else np.full(3, np.nan)
    return _Means(tuple(keys), np.array(q).reshape(len(keys), -1), np.array(xyz).reshape(-1, 3),
                  np.array(n, dtype=float), var)


def check_positions(check: StaticTable, baseline: StaticTable, *, alpha: float = 1e-3) -> PositionCheck | None:
    """The check's unloaded positions against the baseline's at the same poses (the module
    docstring); None when fewer than three points of both share a pose and a marker."""
    from elastocal.identify.registration import kabsch

    c, b = _means(check), _means(baseline)
    if not (np.all(np.isfinite(c.var)) and np.all(np.isfinite(b.var))):
        raise InputError("the unloaded readings hold no repeats: comparing positions needs repeats >= 2 to know "
                         "the tracker's noise", source=check.source if not np.all(np.isfinite(c.var))
                         else baseline.source)
    pairs: list[tuple[int, int]] = []
    for i, (_, marker) in enumerate(c.keys):
        for k, (_, bm) in enumerate(b.keys):
            if bm == marker and c.q.shape[1] == b.q.shape[1] and np.max(np.abs(c.q[i] - b.q[k])) < SAME_POSE:
                pairs.append((i, k))
                break
    if len(pairs) < 3:
        return None
    ic, ib = (np.array(x) for x in zip(*pairs))
    var = b.var[None, :] / b.n[ib, None] + c.var[None, :] / c.n[ic, None]      # (P, 3)
    reg = kabsch(b.xyz[ib], c.xyz[ic], 1.0 / var.mean(axis=1))
    if reg is None:
        return None
    r = c.xyz[ic] - reg.apply(b.xyz[ib])
    chi2 = float(np.sum(r ** 2 / var))
    dof = 3 * len(pairs) - 6
    if dof < 1:
        return None
    return PositionCheck(poses=tuple(dict.fromkeys(c.keys[i][0] for i in ic)), markers=len(pairs),
                         rms_m=float(np.sqrt(np.mean(r ** 2))), max_m=float(np.max(np.linalg.norm(r, axis=1))),
                         noise_floor_m=float(math.sqrt(np.mean(var))), chi2=chi2, dof=dof,
                         p_value=float(stats.chi2.sf(chi2, dof)), alpha=alpha)
