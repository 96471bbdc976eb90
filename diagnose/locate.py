"""Where an unexplained residual sits: the readings it concentrates in, named.

A residual the model cannot explain is located by grouping the readings (or
deflections) by marker, pose, time, joint angle, region of the workspace and by
their products: a marker's readings after a time (a reflector bumped at that
time moves every later reading of that marker), a load's deflections after a
time (a stiffness that changes over the procedure). Each group's excess over the
noise, ``Σ max(|r|² − v, 0)`` (``v`` what noise alone leaves there), is compared
with its share of the readings; the strongest place is the one whose excess is
most concentrated, ``share² / fraction`` among the groups that hold at least
:data:`MIN_SHARE` of the excess and leave significantly more than noise. Its
words name it the way a user would look for it: "R2's readings after 14:05".

Times are the table's ``t`` [s]: a clock time (UTC) when they are Unix times,
else seconds from the table's origin.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
import scipy.stats

#: a place must hold at least this share of the excess to be named
MIN_SHARE = 0.3
#: and leave more than noise there at this p-value
PLACE_P = 1e-3
#: a marker's excess level changes at a time when the two segments differ at this p (Welch)
CHANGE_P = 1e-6
#: among places that hold the excess as concentrated, the more specific is named
SPECIFIC = {"marker x time": 0, "load x time": 1, "marker x pose": 2, "marker": 3, "pose": 4, "time": 5}
#: time values above this are Unix times (after 1973)
UNIX_TIME_S = 1e8


@dataclass(frozen=True)
class Place:
    """One group of readings and how much of the unexplained excess it holds."""

    by: str               # what groups it: marker, pose, time, marker x time, load x time, q3, x, ...
    label: str            # the group's label ("R2 after 14:05")
    words: str            # how a sentence names it ("R2's readings after 14:05")
    share: float          # share of the excess over the noise there
    fraction: float       # share of the readings there
    ratio: float          # rms over the noise rms there
    n: int                # readings (or deflections)
    p_value: float        # its whitened sum of squares under noise alone
    since_s: float | None = None    # the time after which it holds (a change), when it is one

    @property
    def score(self) -> float:
        return self.share ** 2 / max(self.fraction, 1e-12)

    def to_json(self) -> dict:
        out = {"by": self.by, "label": self.label, "words": self.words, "share": self.share,
               "fraction": self.fraction, "ratio": self.ratio, "n": self.n, "p_value": self.p_value}
        if self.since_s is not None:
            out["since_t"] = self.since_s
            out["since"] = clock(self.since_s)
        return out


_NONE = Place("", "", "", 0.0, 1.0, 0.0, 0, 1.0)


def clock(t_s: float) -> str:
    """A time as a user reads it: HH:MM (UTC) for Unix times, else seconds."""
    if t_s > UNIX_TIME_S:
        return _dt.datetime.fromtimestamp(t_s, tz=_dt.timezone.utc).strftime("%H:%M")
    return f"t = {t_s:.0f} s"


@dataclass(frozen=True, eq=False)
class Readings:
    """The readings to locate in: residual (N, 3), noise variance of |r|² (N,), and features."""

    residual: np.ndarray
    noise_var: np.ndarray
    marker: np.ndarray                 # (N,) str
    pose: np.ndarray                   # (N,) str
    t: np.ndarray                      # (N,) s, NaN when unknown
    q: np.ndarray                      # (N, J) rad
    load: np.ndarray | None = None     # (N,) str (deflections)
    base_p: np.ndarray | None = None   # (N, 3) where the reading is, base frame [m] (absolute)
    #: (N, 3, 3) how each reading moves with its marker's place on the tool (the fit's own marker
    #: offsets), None when the fit has none: a knocked reflector is a change of that place
    marker_jac: np.ndarray | None = None


def _place(by, label, words, mask, sq, var, excess, total, n_all, since=None) -> Place | None:
    n = int(mask.sum())
    if n == 0 or n == n_all:
        return None
    share = float(excess[mask].sum() / total)
    w = float((sq[mask] / var[mask]).sum())
    p = float(scipy.stats.chi2.sf(w * 3.0, 3 * n))      # |r|²/v sums 3 components per reading
    ratio = float(np.sqrt(sq[mask].sum() / var[mask].sum()))
    return Place(by, label, words, share, n / n_all, ratio, n, p, since)


def _bins(values: np.ndarray, n_bins: int) -> list[tuple[float, float, np.ndarray]]:
    lo, hi = float(np.min(values)), float(np.max(values))
    if not hi > lo:
        return []
    edges = np.linspace(lo, hi, n_bins + 1)
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n_bins - 1)
    return [(edges[k], edges[k + 1], idx == k) for k in range(n_bins)]


def _moved_at(r: Readings, within: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(time, readings at or after it) at which ``within``'s readings are best explained by the
    marker having moved on the tool (its place refitted before and after; the drop of the
    noise-weighted sum of squares, chi-square with 3 dof), None when no split is significant."""
    if r.marker_jac is None:
        return None
    idx = np.flatnonzero(within & np.isfinite(r.t))
    times = np.unique(r.t[idx])
    if len(times) < 2:
        return None
    w = 1.0 / np.sqrt(np.maximum(r.noise_var[idx], 1e-300) / 3.0)
    jac = r.marker_jac[idx] * w[:, None, None]
    res = r.residual[idx] * w[:, None]

    def ss(mask: np.ndarray) -> float:
        a, b = jac[mask].reshape(-1, 3), res[mask].reshape(-1)
        x = np.linalg.lstsq(a, b, rcond=None)[0]
        return float(((b - a @ x) ** 2).sum())

    whole = ss(np.ones(len(idx), dtype=bool))
    best, best_ts = 0.0, None
    for ts in times[1:]:
        after = r.t[idx] >= ts
        if after.sum() < 2 or (~after).sum() < 2:
            continue
        drop = whole - ss(after) - ss(~after)
        if drop > best:
            best, best_ts = drop, float(ts)
    n_splits = max(len(times) - 1, 1)
    if best_ts is None or scipy.stats.chi2.sf(best, 3) * n_splits >= CHANGE_P:
        return None
    return best_ts, within & (r.t >= best_ts)


def _after(t: np.ndarray, within: np.ndarray, level: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """(time, mask) of the change point of ``within``'s readings: the split in time at which
    the mean of ``level`` (each reading's |r|²/v) changes most (the two-segment fit's drop of
    the sum of squares, n_b n_a / n (mean_a − mean_b)²); the readings at or after it."""
    idx = np.flatnonzero(within & np.isfinite(t))
    times = np.unique(t[idx])
    if len(times) < 2:
        return []
    best, best_ts = -1.0, None
    for ts in times[1:]:
        after = t[idx] >= ts
        n_a, n_b = int(after.sum()), int((~after).sum())
        d = level[idx][after].mean() - level[idx][~after].mean()
        stat = n_a * n_b / (n_a + n_b) * d * d
        if stat > best:
            best, best_ts = stat, float(ts)
    return [(best_ts, within & (t >= best_ts))]


def locate(r: Readings, *, n_bins: int = 4) -> tuple[Place, ...]:
    """Every place that holds at least MIN_SHARE of the excess and leaves significantly
    more than noise, strongest (most concentrated) first."""
    sq = (r.residual ** 2).sum(axis=1)
    var = np.maximum(r.noise_var, 1e-300)
    excess = np.maximum(sq - var, 0.0)
    total = float(excess.sum())
    n_all = len(sq)
    if total <= 0.0 or n_all < 4:
        return ()
    found: list[Place | None] = []
    level = sq / var

    def add(by, label, words, mask, since=None):
        found.append(_place(by, label, words, mask, sq, var, excess, total, n_all, since))

    markers = list(dict.fromkeys(r.marker.tolist()))
    for m in markers:
        add("marker", m, f"marker {m}'s readings", r.marker == m)
    poses = list(dict.fromkeys(r.pose.tolist()))
    for p in poses:
        add("pose", p, f"pose {p}", r.pose == p)
    if len(markers) > 1:
        for m in markers:
            for p in poses:
                add("marker x pose", f"{m} at pose {p}", f"{m}'s readings at pose {p}", (r.marker == m) & (r.pose == p))
    timed = np.all(np.isfinite(r.t))
    if timed:
        for ts, mask in _after(r.t, np.ones(n_all, dtype=bool), level):
            add("time", f"after {clock(ts)}", f"the readings after {clock(ts)}", mask, ts)
        if len(markers) > 1:
            for m in markers:
                own = r.marker == m
                moved = _moved_at(r, own)
                splits = [moved] if moved is not None else [
                    (ts, mask) for ts, mask in _after(r.t, own, level) if _changed(level, mask, own & ~mask)]
                for ts, mask in splits:
                    # a change at ts explains the whole marker's excess (a reflector knocked then:
                    # the fit's marker offset sits between before and after)
                    found.append(replace(_place("marker x time", f"{m} after {clock(ts)}",
                                                f"{m}'s readings after {clock(ts)}", own, sq, var, excess,
                                                total, n_all, ts) or _NONE, n=int(mask.sum())))
        if r.load is not None:
            for ld in dict.fromkeys(r.load.tolist()):
                for ts, mask in _after(r.t, r.load == ld, level):
                    add("load x time", f"load {ld} after {clock(ts)}",
                        f"the deflections under load {ld} after {clock(ts)}", mask, ts)
    for j in range(r.q.shape[1]):
        for lo, hi, mask in _bins(r.q[:, j], n_bins):
            add(f"q{j + 1}", f"q{j + 1} {lo:.2f}..{hi:.2f} rad", f"the poses with q{j + 1} in {lo:.2f}..{hi:.2f} rad",
                mask)
    if r.base_p is not None:
        for a, axis in enumerate("xyz"):
            for lo, hi, mask in _bins(r.base_p[:, a], n_bins):
                add(axis, f"{axis} {lo:.2f}..{hi:.2f} m", f"the readings at {axis} {lo:.2f}..{hi:.2f} m (base frame)",
                    mask)
    places = [p for p in found if p is not None and p is not _NONE and p.share >= MIN_SHARE
              and p.p_value < PLACE_P]
    places.sort(key=lambda p: (-round(p.score, 9), SPECIFIC.get(p.by, len(SPECIFIC))))
    return tuple(places)


def _changed(level: np.ndarray, after: np.ndarray, before: np.ndarray) -> bool:
    """The readings' excess level changes between ``before`` and ``after`` (Welch's t test)."""
    if after.sum() < 3 or before.sum() < 3:
        return False
    _, p = scipy.stats.ttest_ind(level[after], level[before], equal_var=False)
    return bool(np.isfinite(p) and p < CHANGE_P)


def strongest(places: Sequence[Place]) -> Place | None:
    return places[0] if places else None


def deflection_readings(where) -> Readings | None:
    """The deflections of a :class:`~elastocal.diagnose.where.Where` to locate in (None without a noise model)."""
    if where.noise_var is None:
        return None
    return Readings(residual=where.residual, noise_var=where.noise_var,
                    marker=np.asarray(where.markers, dtype=object)[where.marker].astype(str),
                    pose=np.asarray(where.pose_ids, dtype=object)[where.pose].astype(str),
                    t=np.asarray(where.t, dtype=float), q=where.q, load=np.asarray(where.load).astype(str))


def absolute_readings(fit) -> Readings | None:
    """The mean readings of an absolute fit (identify/absolute.py) to locate in: each state's
    markers, the noise of each from the fit's covariance, where it is in base coordinates."""
    if fit.state_cov is None or fit.noise_floor is None:
        return None
    ds = fit.dataset
    n_s, n_m = fit.residuals.shape[:2]
    var = np.einsum("sii->si", fit.state_cov).reshape(n_s, n_m, 3).sum(axis=2)
    pose = np.asarray(ds.pose_ids, dtype=object)[ds.state_pose].astype(str)
    t = ds.abs_t if ds.abs_t is not None else np.full((n_s, n_m), np.nan)
    reg = fit.registration
    base_p = (fit.measured - reg.translation) @ reg.rotation          # R^T (p - t), row vectors
    mjac = None
    names = list(fit.design_names)
    if fit.design is not None and all(f"d{a}_{m}" in names for m in ds.markers for a in "xyz"):
        mjac = np.zeros((n_s, n_m, 3, 3))
        for k, m in enumerate(ds.markers):
            mjac[:, k] = fit.design[:, k][..., [names.index(f"d{a}_{m}") for a in "xyz"]]
        mjac = mjac.reshape(-1, 3, 3)
    return Readings(residual=fit.residuals.reshape(-1, 3), noise_var=var.reshape(-1),
                    marker=np.tile(np.asarray(ds.markers, dtype=str), n_s), pose=np.repeat(pose, n_m),
                    t=np.asarray(t, dtype=float).reshape(-1), q=np.repeat(ds.q[ds.state_pose], n_m, axis=0),
                    base_p=base_p.reshape(-1, 3), marker_jac=mjac)
