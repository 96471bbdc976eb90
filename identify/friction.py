"""Joint friction from UV/VU runs (Yang §6, eq. 48, and beyond).

The same slow path is run forward (UV) and backward (VU). At one point of the
path the load torque a joint carries is the same both ways; friction resists the
motion, so the drive supplies it in the direction of motion and it changes sign
with the direction (docs/physics.md, the motor's torque balance; docs/formats.md §3:
``xi i = tau_load + f sign(dq)``, ``f > 0``)::

    xi (i_UV - i_VU) / 2 = +sign(dq_UV) f          (Y48, in torque)
    xi (i_UV + i_VU) / 2 = tau_load

with the friction model, per joint, the sum of the columns of the friction
effects in the model (each effect module's ``run_column``, identify/effects)::

    f = fc + fv |dq| + fl |tau_load|               (Coulomb, viscous, load-dependent)

``fv`` needs runs at two or more speeds, ``fl`` runs at two or more load
levels; both are linear, so each joint is one small least-squares problem on
the matched UV/VU samples, with the parameter covariance from the residuals.
No robot model is needed: gravity, payload and compensator cancel in the
half-difference.

A term the data cannot separate (one speed only, say) is left out for that
joint (its value NaN, listed in :attr:`FrictionFit.unidentified`), never
guessed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from elastocal.errors import InputError
from elastocal.model.effects import get_effect, run_effects
from elastocal.model.effects.base import Effect

#: the friction effects of the table (run_part "uv/vu"), Coulomb first; a term is the
#: effect's name without "_friction" (FrictionFit.terms, ``terms=``)
FRICTION_EFFECTS = run_effects("uv/vu")
TERM_EFFECT = {name.removesuffix("_friction"): name for name in FRICTION_EFFECTS}
FRICTION_TERMS = tuple(TERM_EFFECT)
#: parameter prefixes (docs/formats.md §4) and units of each term, from its effect module
TERM_PREFIX = {t: get_effect(e).run_prefix for t, e in TERM_EFFECT.items()}
TERM_UNIT = {t: get_effect(e).units[0] for t, e in TERM_EFFECT.items()}
#: a scaled design worse conditioned than this cannot separate its terms
MAX_CONDITION = 1e4


@dataclass(frozen=True, eq=False)
class PathMatch:
    """Where each point of path A lies on the polyline of path B."""

    index: np.ndarray      # (n,) segment start in B
    fraction: np.ndarray   # (n,) position on the segment, 0..1
    distance: np.ndarray   # (n,) joint-space distance from the polyline [rad]

    def interpolate(self, values_b: np.ndarray) -> np.ndarray:
        v = np.asarray(values_b, dtype=float)
        f = self.fraction.reshape((-1,) + (1,) * (v.ndim - 1))
        return (1.0 - f) * v[self.index] + f * v[self.index + 1]


def match_path(q_a: np.ndarray, q_b: np.ndarray) -> PathMatch:
    """Project each sample of ``q_a`` (n, d) on the polyline through ``q_b`` (m, d)."""
    qa = np.asarray(q_a, dtype=float)
    qb = np.asarray(q_b, dtype=float)
    if len(qb) < 2:
        raise InputError("a run needs at least 2 samples to be matched")
    _, nearest = cKDTree(qb).query(qa)
    best_idx = np.zeros(len(qa), dtype=int)
    best_frac = np.zeros(len(qa))
    best_dist = np.full(len(qa), np.inf)
    for seg_start in (nearest - 1, nearest):
        k = np.clip(seg_start, 0, len(qb) - 2)
        p0, p1 = qb[k], qb[k + 1]
        d = p1 - p0
        dd = np.einsum("ij,ij->i", d, d)
        frac = np.where(dd > 0, np.einsum("ij,ij->i", qa - p0, d) / np.where(dd > 0, dd, 1.0), 0.0)
        frac = np.clip(frac, 0.0, 1.0)
        dist = np.linalg.norm(qa - (p0 + frac[:, None] * d), axis=1)
        better = dist < best_dist
        best_idx[better], best_frac[better], best_dist[better] = k[better], frac[better], dist[better]
    return PathMatch(index=best_idx, fraction=best_frac, distance=best_dist)


@dataclass(frozen=True, eq=False)
class FrictionSamples:
    """Matched UV/VU samples: the half difference and half sum of Y48, in torque."""

    #: (n, N) sign(dq_UV) xi (i_UV - i_VU)/2 [N·m; N on a prismatic joint], > 0 for real friction;
    #: NaN where still
    friction: np.ndarray
    speed: np.ndarray      # (n, N) (|dq_UV| + |dq_VU|)/2 [rad/s; m/s]
    load_torque: np.ndarray  # (n, N) xi (i_UV + i_VU)/2 [N·m; N]
    pair: np.ndarray       # (n,) index of the UV/VU pair
    pairs: tuple[tuple[str, str], ...]  # (UV run, VU run) or (+ sweep, - sweep)
    #: (n,) variance of the interpolated backward reading per unit variance of one reading,
    #: ``(1 - f)^2 + f^2``: a half-difference's noise variance is ``xi^2 sigma^2 (1 + weight) / 4``
    weight: np.ndarray | None = None
    q: np.ndarray | None = None  # (n, N) joint values of the forward run's samples [rad; m]


@dataclass(frozen=True, eq=False)
class FrictionFit:
    """Per-joint friction parameters with their covariance."""

    terms: tuple[str, ...]           # fitted terms, order of values' columns
    values: np.ndarray               # (N, len(terms)); NaN where not identified
    covariance: np.ndarray           # (N, len(terms), len(terms))
    n: np.ndarray                    # (N,) matched samples used per joint
    residual_rms: np.ndarray         # (N,) [N·m; N]; NaN for a joint that did not move
    samples: FrictionSamples
    #: the effect of each term (the strategies that gave the columns), sized for the robot's
    #: joints when it was given (a prismatic joint's units in N, N*s/m)
    effects: tuple[Effect, ...] = ()

    def _effect(self, term: str) -> Effect:
        return self.effects[self.terms.index(term)] if self.effects else get_effect(TERM_EFFECT[term])

    @property
    def n_joints(self) -> int:
        return int(self.values.shape[0])

    def unit(self, term: str, joint: int) -> str:
        """The unit of ``term``'s parameter on joint ``joint`` (0-based; a prismatic joint's in N
        when the effects were sized for the robot)."""
        units = self._effect(term).units
        return units[joint] if joint < len(units) else units[0]

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.einsum("jii->ji", self.covariance))

    def term(self, name: str) -> np.ndarray:
        """Values (N,) of one term; NaN where not fitted or not identified."""
        if name not in self.terms:
            return np.full(self.n_joints, np.nan)
        return self.values[:, self.terms.index(name)]

    @property
    def coulomb(self) -> np.ndarray:
        return self.term("coulomb")

    @property
    def viscous(self) -> np.ndarray:
        return self.term("viscous")

    @property
    def load_dependent(self) -> np.ndarray:
        return self.term("load_dependent")

    @property
    def unidentified(self) -> tuple[str, ...]:
        """Parameter names (fc1, fv3, ...) the data could not determine."""
        out = []
        for k, term in enumerate(self.terms):
            for j in range(self.n_joints):
                if not np.isfinite(self.values[j, k]):
                    out.append(f"{self._effect(term).run_prefix}{j + 1}")
        return tuple(out)

    def parameters(self) -> dict[str, dict[str, float | str]]:
        """Identified parameters under docs/formats.md §4 names (fc1.., fv1.., fl1..)."""
        out: dict[str, dict[str, float | str]] = {}
        std = self.std
        for k, term in enumerate(self.terms):
            effect = self._effect(term)
            for j in range(self.n_joints):
                if np.isfinite(self.values[j, k]):
                    out[f"{effect.run_prefix}{j + 1}"] = {"value": float(self.values[j, k]),
                                                          "std": float(std[j, k]), "unit": self.unit(term, j)}
        return out

    def torque(self, dq: np.ndarray, load_torque: np.ndarray) -> np.ndarray:
        """Friction torque ``sign(dq) (fc + fv |dq| + fl |tau|)`` (n, N) the drive supplies on
        top of the load torque (``xi i = tau_load + torque``), with the identified terms
        (unidentified ones count as zero)."""
        dq = np.atleast_2d(dq)
        tau = np.atleast_2d(load_torque)
        size = np.zeros_like(dq, dtype=float)
        for term in self.terms:
            size += np.nan_to_num(self.term(term))[None, :] * self._effect(term).run_column(np.abs(dq), tau)
        return np.sign(dq) * size


def _run_speed(dq: np.ndarray) -> float:
    return float(np.median(np.max(np.abs(dq), axis=1)))


def _finite_difference_speed(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    if len(q) < 2 or np.any(np.diff(t) <= 0):
        raise InputError("a run without dq columns needs increasing times to derive the joint speeds")
    return np.gradient(q, t, axis=0)


#: forward direction -> its backward one: UV/VU pairs and +/- joint sweeps are both the same
#: path run forward and backward, so both give the friction half-differences
BACKWARD = {"UV": "VU", "+": "-"}


def _path_distance(q_a: np.ndarray, q_b: np.ndarray) -> float:
    """Median distance of the samples of path A from the polyline of path B [rad]."""
    return float(np.median(match_path(q_a, q_b).distance)) if len(q_b) >= 2 else float("inf")


def pair_runs(run: np.ndarray, direction: np.ndarray, load: np.ndarray, dq: np.ndarray,
              *, source: str | None = None, q: np.ndarray | None = None) -> tuple[tuple[str, str], ...]:
    """Pair each forward run (UV, ``+``) with a backward run (VU, ``-``) of the same load:
    of those on the same path (``q`` given: within 3 sample spacings), the one whose
    speed is closest."""
    run = np.asarray(run, dtype=str)
    direction = np.asarray(direction, dtype=str)
    forward = [r for r in dict.fromkeys(run[np.isin(direction, tuple(BACKWARD))])]
    if not forward:
        raise InputError("no UV runs: friction needs the same path run forward (UV, or + for a sweep) and "
                         "backward (VU, or -)", source=source, column="direction")
    pairs = []
    for r in forward:
        rm = run == r
        ld, back = load[rm][0], BACKWARD[direction[rm][0]]
        candidates = [v for v in dict.fromkeys(run[direction == back]) if load[run == v][0] == ld]
        if q is not None and candidates:
            qr = np.asarray(q, dtype=float)[rm]
            spacing = float(np.median(np.linalg.norm(np.diff(qr, axis=0), axis=1))) if len(qr) > 1 else 0.0
            candidates = [v for v in candidates
                          if _path_distance(qr, np.asarray(q, dtype=float)[run == v]) <= 3.0 * spacing + 1e-6]
        if not candidates:
            raise InputError(f"{'UV' if back == 'VU' else 'sweep'} run {r} (load {ld}) has no {back} run on its "
                             "path under the same load", source=source, column="run")
        speed = _run_speed(dq[rm])
        best = min(candidates, key=lambda v: abs(np.log(max(_run_speed(dq[run == v]), 1e-12) / max(speed, 1e-12))))
        pairs.append((r, best))
    return tuple(pairs)


def friction_samples(q: np.ndarray, dq: np.ndarray, currents: np.ndarray, run: np.ndarray, direction: np.ndarray,
                     load: np.ndarray, torque_constants: Sequence[float], *, t: np.ndarray | None = None,
                     min_speed_rad_s: float = 1e-3, source: str | None = None) -> FrictionSamples:
    """Match the UV and VU runs point by point along the path (Y48)."""
    q = np.asarray(q, dtype=float)
    currents = np.asarray(currents, dtype=float)
    run = np.asarray(run, dtype=str)
    direction = np.asarray(direction, dtype=str)
    load = np.asarray(load, dtype=str)
    xi = np.asarray(torque_constants, dtype=float)
    dq = np.array(dq, dtype=float)
    for r in dict.fromkeys(run):
        rm = run == r
        if not np.all(np.isfinite(dq[rm])):
            if t is None:
                raise InputError(f"run {r} has no joint speeds", source=source, column="dq1")
            dq[rm] = _finite_difference_speed(q[rm], np.asarray(t, dtype=float)[rm])
    pairs = pair_runs(run, direction, load, dq, source=source, q=q)
    fr, sp, tl, pair_idx, weight, q_fwd = [], [], [], [], [], []
    for k, (ru, rv) in enumerate(pairs):
        mu, mv = run == ru, run == rv
        if not np.all(np.isfinite(currents[mu])) or not np.all(np.isfinite(currents[mv])):
            raise InputError(f"runs {ru}/{rv} have empty currents; friction needs i1..i{currents.shape[1]}",
                             source=source, column="i1")
        qv = q[mv]
        match = match_path(q[mu], qv)
        spacing = float(np.median(np.linalg.norm(np.diff(qv, axis=0), axis=1)))
        on_path = match.distance <= 3.0 * spacing + 1e-6
        i_u, d_u = currents[mu][on_path], dq[mu][on_path]
        sub = PathMatch(match.index[on_path], match.fraction[on_path], match.distance[on_path])
        i_v, d_v = sub.interpolate(currents[mv]), sub.interpolate(dq[mv])
        s = np.sign(d_u)
        moving = (np.abs(d_u) >= min_speed_rad_s) & (np.abs(d_v) >= min_speed_rad_s) & (np.sign(d_v) == -s)
        # the drive supplies friction in the direction of motion: the forward current exceeds the
        # backward one by 2 f along the forward motion (docs/physics.md)
        half_diff = s * xi * (i_u - i_v) / 2.0
        fr.append(np.where(moving, half_diff, np.nan))
        sp.append(np.where(moving, (np.abs(d_u) + np.abs(d_v)) / 2.0, np.nan))
        tl.append(xi * (i_u + i_v) / 2.0)
        pair_idx.append(np.full(len(i_u), k))
        weight.append((1.0 - sub.fraction) ** 2 + sub.fraction ** 2)
        q_fwd.append(q[mu][on_path])
    return FrictionSamples(friction=np.vstack(fr), speed=np.vstack(sp), load_torque=np.vstack(tl),
                           pair=np.concatenate(pair_idx), pairs=pairs, weight=np.concatenate(weight),
                           q=np.vstack(q_fwd))


def _fit_joint(y: np.ndarray, columns: list[np.ndarray], names: list[str]) -> tuple[dict, dict, float]:
    """Least squares with terms dropped while the scaled design cannot separate them."""
    keep = list(range(len(columns)))
    while True:
        x = np.column_stack([columns[k] for k in keep])
        scale = np.linalg.norm(x, axis=0)
        scale[scale == 0] = 1.0
        xs = x / scale
        cond = np.linalg.cond(xs) if len(keep) > 1 else 1.0
        if cond <= MAX_CONDITION or len(keep) == 1:
            break
        # drop the term best explained by the others (largest variance inflation)
        inv = np.linalg.pinv(xs.T @ xs)
        worst = max(range(1, len(keep)), key=lambda c: inv[c, c])  # never drop Coulomb (column 0)
        keep.pop(worst)
    beta, *_ = np.linalg.lstsq(xs, y, rcond=None)
    beta = beta / scale
    res = y - x @ beta
    dof = len(y) - len(keep)
    s2 = float(res @ res) / dof if dof > 0 else np.nan
    cov = s2 * np.linalg.pinv(x.T @ x)
    values = {names[k]: float(beta[i]) for i, k in enumerate(keep)}
    covs = {(names[a], names[b]): float(cov[i, j]) for i, a in enumerate(keep) for j, b in enumerate(keep)}
    return values, covs, float(np.sqrt(np.mean(res ** 2)))


def friction_strategies(terms: Sequence[str] = FRICTION_TERMS, effects: Sequence[Effect] | None = None,
                        robot=None) -> tuple[tuple[str, ...], tuple[Effect, ...]]:
    """(terms, effects) of a friction model: ``effects`` injected as they are (the first
    must be the constant, Coulomb-like one: its column is never dropped), else the table's
    effects for ``terms`` in the table's order, sized for ``robot``'s joints."""
    if effects is not None:
        effects = tuple(effects)
        if not effects or any(e.run_column is None for e in effects):
            raise InputError("a friction model is a list of effects with a run_column, the constant one first")
        return tuple(e.name.removesuffix("_friction") for e in effects), effects
    terms = tuple(terms)
    for term in terms:
        if term not in FRICTION_TERMS:
            raise InputError(f"unknown friction term {term!r}; one of {', '.join(FRICTION_TERMS)}")
    if FRICTION_TERMS[0] not in terms:
        raise InputError("the friction model needs the Coulomb term")
    terms = tuple(t for t in FRICTION_TERMS if t in terms)
    return terms, tuple(get_effect(TERM_EFFECT[t], robot) for t in terms)


def identify_friction(samples: FrictionSamples, *, terms: Sequence[str] = FRICTION_TERMS,
                      effects: Sequence[Effect] | None = None, min_samples: int = 5, robot=None) -> FrictionFit:
    """Per-joint friction ``fc + fv |dq| + fl |tau|`` from matched UV/VU samples; the
    columns are the effects' own (``effects`` injected, else those of ``terms`` sized for
    ``robot``: a prismatic joint's parameters in N, N*s/m)."""
    terms, effects = friction_strategies(terms, effects, robot)
    nt = len(terms)
    nj = samples.friction.shape[1]
    values = np.full((nj, nt), np.nan)
    cov = np.full((nj, nt, nt), np.nan)
    n = np.zeros(nj, dtype=int)
    rms = np.full(nj, np.nan)
    for j in range(nj):
        ok = np.isfinite(samples.friction[:, j])
        n[j] = int(ok.sum())
        if n[j] < max(min_samples, nt + 1):
            continue
        y = samples.friction[ok, j]
        cols = [e.run_column(samples.speed[ok, j], samples.load_torque[ok, j]) for e in effects]
        vals, covs, rms[j] = _fit_joint(y, cols, list(terms))
        for a, ta in enumerate(terms):
            if ta in vals:
                values[j, a] = vals[ta]
                for b, tb in enumerate(terms):
                    if tb in vals:
                        cov[j, a, b] = covs[(ta, tb)]
    return FrictionFit(terms=terms, values=values, covariance=cov, n=n, residual_rms=rms, samples=samples,
                       effects=effects)


def friction_from_run_table(table, torque_constants: Sequence[float], *, terms: Sequence[str] = FRICTION_TERMS,
                            effects: Sequence[Effect] | None = None, min_speed_rad_s: float = 1e-3,
                            robot=None) -> FrictionFit:
    """:func:`identify_friction` on the UV/VU runs and the ``+``/``-`` sweeps of a run table
    (docs/formats.md §3): both are the same path forward and backward."""
    samples = table_friction_samples(table, torque_constants, min_speed_rad_s=min_speed_rad_s)
    if samples is None:
        raise InputError("the table has no UV/VU runs and no +/- sweeps (the same path forward and backward)",
                         source=table.source, column="direction")
    return identify_friction(samples, terms=terms, effects=effects, robot=robot)


def table_friction_samples(table, torque_constants: Sequence[float], *,
                           min_speed_rad_s: float = 1e-3) -> FrictionSamples | None:
    """Matched samples of every forward/backward pair of a run table (UV/VU and +/-), None without one."""
    paired = np.isin(table.direction, (*BACKWARD, *BACKWARD.values()))
    if not np.any(paired):
        return None
    sub = table.subset(paired)
    return friction_samples(sub.q, sub.dq, sub.currents, sub.run, sub.direction, sub.load, torque_constants,
                            t=sub.t, min_speed_rad_s=min_speed_rad_s, source=table.source)
