"""Forward selection of the parameters of a selectable effect (located compliance).

An effect with many possible components (a spring at the base and at the end of
every link, two axes each) keeps only those the data support: starting from
the model without them, the component whose addition has the largest Wald
statistic is added when it passes the diagnosis' own test (p < 0.01 and
delta BIC < -10, docs/cli.md) and its value has the physical sign, and the rest are
tested again, until none passes.

The tests run on the linearisation of the fit with every component (its design
matrix and the noise covariance it knows), so one full fit serves the whole
selection: each subset is a small least-squares problem on precomputed
Gram matrices ``D'D``, ``D' Sigma D`` and ``D'y``. The covariance of a subset's
parameters is the sandwich ``(X'X)^-1 X' Sigma X (X'X)^-1`` scaled by the
dispersion the subset leaves (as in identify/static.py), or ``(X'X)^-1 s^2``
without repeated readings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.stats

#: the test of a component (docs/cli.md's verdict rule)
SELECT_P = 0.01
SELECT_DELTA_BIC = -10.0
#: a component this many std below zero has the wrong sign and is not kept
WRONG_SIGN_STD = 3.0
#: a component not kept whose addition moves a parameter of the model by more than this
#: many of its std is fitted as a control (its omission would bias that parameter)
CONTROL_SHIFT = 0.5
#: a control must have the physical sign (a compliance is positive)
CONTROL_SIGN = True
#: a fitted component swapped for a twin the data cannot tell from it (it fits as well, within the
#: test's threshold) that moves a joint spring by more than this many of its std leaves that spring
#: not determined by these data
TWIN_SHIFT = 2.0
#: a component left out for its sign lets a joint spring's honest 95 % interval (the profile likelihood with
#: the component free in [0, inf)) reach this many times as far as its printed one: that spring is the
#: physical bound's, not the data's. The honest reach grows from 1 with the spring's alias with the component
#: (about the factor its std would grow by were the component fitted); no rule derives the point where that
#: stops being an interval to state and becomes an undetermined spring. Measured (linearisation of the
#: selection): the six-joint golden fit's k2 2.2x, six-joint demo-like fits' k1 up to 7.7x (seeds 0-9),
#: the seven-joint track cell's k6 on seed 6 25.7x.
BOUND_REACH = 10.0
#: the interval the honest reach is measured at (chi-square 1 dof, 95 %)
BOUND_CHI2 = 3.841458820694124


@dataclass(frozen=True)
class Twin:
    """A joint spring the data do not determine: it follows which of two components the data
    cannot tell apart is fitted (``fitted`` is, ``twin`` in its place fits as well)."""

    spring: str             # the spring's reported name (k6)
    fitted: str
    twin: str
    shift_std: float        # how far the swap moves the spring, in its std

    @property
    def note(self) -> str:
        return (f"not determined by these data: they cannot tell {self.fitted} from {self.twin}, and "
                f"{self.spring} moves by {self.shift_std:.1f} std between the two")


@dataclass(frozen=True)
class AtBound:
    """A joint spring its printed std overstates: a component left out only for its sign (below zero
    within noise) still may be positive by what the data allow, and the spring moves with it."""

    spring: str
    component: str
    reach: float            # the honest 95 % interval's reach over the printed one's (1: as printed)

    @property
    def note(self) -> str:
        return (f"not determined by these data: {self.component} comes out below zero within noise and is left "
                f"out (a compliance is not negative), but at values the data still allow it {self.spring} moves "
                f"{self.reach:.0f} times as far as its 95 % interval says")


@dataclass(frozen=True)
class Selection:
    """What the data support of a selectable effect."""

    effect: str
    kept: tuple[str, ...]
    #: the best component not kept (None when every one was kept or none is identifiable)
    next_best: str | None
    next_statistic: float
    #: components not kept that are fitted all the same: leaving them out would move a
    #: parameter of the model (a joint spring) by more than CONTROL_SHIFT of its std
    #: (post-double selection, see confounders); fitted, never named as a finding
    controls: tuple[str, ...] = ()
    #: joint springs that follow the choice between a fitted component and its twin (:func:`twins`)
    twins: tuple[Twin, ...] = ()
    #: joint springs whose honest interval a component left out for its sign widens (:func:`at_bound`)
    at_bound: tuple[AtBound, ...] = ()

    def undetermined(self) -> dict[str, str]:
        """The springs these data do not determine, name -> why (twins first, both notes when both)."""
        out: dict[str, str] = {}
        for t in (*self.twins, *self.at_bound):
            out[t.spring] = f"{out[t.spring]}; {t.note}" if t.spring in out else t.note
        return out

    def fitted(self, kept: tuple[str, ...] | None = None) -> tuple[str, ...]:
        """The components a fit holds: ``kept`` (default the kept ones) and the controls."""
        kept = self.kept if kept is None else tuple(kept)
        return (*kept, *(c for c in self.controls if c not in kept))


def _sigma(fit) -> scipy.sparse.csr_matrix | None:
    if fit.noise_blocks is None:
        return None
    n = fit.n
    rows = np.concatenate([r for r, _ in fit.noise_blocks])
    stacked = scipy.sparse.block_diag([c for _, c in fit.noise_blocks], format="csr")
    order = np.empty(n, dtype=int)
    order[rows] = np.arange(len(rows))
    return stacked[order][:, order]


class _Linear:
    """The linearisation of a fit with every component: each subset of its columns
    is a small least-squares problem on precomputed Gram matrices."""

    def __init__(self, full_fit, components: tuple[str, ...]):
        self.names = list(full_fit.design_names)
        d = full_fit.design
        mask_beta = np.array([n in self.names for n in full_fit.beta_names])
        y = full_fit.residuals.reshape(-1) + d @ full_fit.beta[mask_beta]
        self.n = len(y)
        scale = np.linalg.norm(d, axis=0)
        scale[scale == 0] = 1.0
        ds = d / scale
        self.white = full_fit.whitening is not None
        if self.white:   # GLS: in the whitened metric the noise is white, the covariance (X'X)^-1
            ds, y = full_fit.whiten(ds), full_fit.whiten(y)
        self.gram = ds.T @ ds
        self.dy = ds.T @ y
        self.yy = float(y @ y)
        self.sigma = None if self.white else _sigma(full_fit)
        if self.sigma is not None:
            self.h = ds.T @ (self.sigma @ ds)
            self.tr_sigma = float(self.sigma.diagonal().sum())
        #: the model's own columns (every parameter outside the selectable effect)
        self.base = [i for i, nm in enumerate(self.names) if nm not in components]

    def solve(self, comps) -> tuple[np.ndarray, np.ndarray] | None:
        """(values, covariance) of the base columns and then ``comps``, in scaled units."""
        cols = self.base + [self.names.index(k) for k in comps]
        g = self.gram[np.ix_(cols, cols)]
        try:
            g_inv = np.linalg.inv(g)
        except np.linalg.LinAlgError:
            return None
        b = g_inv @ self.dy[cols]
        rss = max(self.yy - 2.0 * float(b @ self.dy[cols]) + float(b @ g @ b), 0.0)
        self.last_rss = rss
        n = self.n
        if self.white:
            cov = g_inv * max(1.0, rss / max(n - len(cols), 1))
        elif self.sigma is not None:
            meat = self.h[np.ix_(cols, cols)]
            expected = self.tr_sigma - float(np.trace(g_inv @ meat))
            cov = g_inv @ meat @ g_inv * (max(1.0, rss / expected) if expected > 0 else 1.0)
        else:
            cov = g_inv * rss / max(n - len(cols), 1)
        return b, cov

    def last(self, comps) -> tuple[float, float] | None:
        """(z, Wald statistic) of the last of ``comps`` fitted with the base and the others."""
        got = self.solve(comps)
        if got is None:
            return None
        b, cov = got
        var = float(cov[-1, -1])
        if not var > 0:
            return None
        return float(b[-1] / math.sqrt(var)), float(b[-1] ** 2 / var)


def forward_select(full_fit, effect: str, components: tuple[str, ...]) -> Selection:
    """Select among ``components`` (beta names of ``full_fit``) by forward selection;
    then the components to fit as controls (:func:`confounders`)."""
    lin = _Linear(full_fit, components)
    pool = [nm for nm in components if nm in lin.names]
    kept: list[str] = []
    limit = threshold(lin.n)
    next_best, next_stat = None, 0.0
    last = lin.last
    rounds = 0
    while pool:
        best, best_stat = None, -1.0
        for c in pool:
            got = last([*kept, c])
            if got is None or got[0] < -WRONG_SIGN_STD:
                continue
            if got[1] > best_stat:
                best, best_stat = c, got[1]
        if best is None:
            break
        if best_stat <= limit:
            next_best, next_stat = best, best_stat
            break
        kept.append(best)
        pool.remove(best)
        # backward: a component kept earlier that the later ones make redundant goes
        while len(kept) > 1:
            worst, worst_stat = None, math.inf
            for k in kept[:-1]:
                t = last([*(x for x in kept if x != k), k])
                stat = -1.0 if t is None or t[0] < -WRONG_SIGN_STD else t[1]
                if stat < worst_stat:
                    worst, worst_stat = k, stat
            if worst is None or worst_stat > limit:
                break
            kept.remove(worst)
            pool.append(worst)
        rounds += 1
        if rounds > 3 * len(components):      # never cycle
            break
    return Selection(effect, tuple(kept), next_best, next_stat,
                     controls=confounders(full_fit, tuple(kept), components, lin=lin))


def confounders(full_fit, kept: tuple[str, ...], components: tuple[str, ...], *,
                lin: _Linear | None = None) -> tuple[str, ...]:
    """The components not kept whose omission the data say would bias the model's
    own parameters (post-double selection).

    A component the test does not keep may still be there, below the test's
    threshold; when it is confounded with a joint spring, leaving it out moves
    that spring by the component's value times their alias, and the spring's
    reported std (which assumes the component is zero) is no longer honest. So a
    component is fitted as a control when adding it to the model moves some
    parameter of the model by more than CONTROL_SHIFT of that parameter's std,
    the largest first, until none does. A component whose value there is below
    zero is not one: with its physical sign (a compliance is positive) its
    least-squares value is zero, and it moves nothing. Controls are fitted, never
    named: the test and the words are the kept components'."""
    lin = _Linear(full_fit, components) if lin is None else lin
    nb = len(lin.base)
    pool = [nm for nm in components if nm in lin.names and nm not in kept]
    chosen: list[str] = []
    while pool:
        now = lin.solve([*kept, *chosen])
        if now is None:
            break
        std_now = np.sqrt(np.clip(np.diag(now[1])[:nb], 1e-300, None))
        best, best_shift = None, CONTROL_SHIFT
        for c in pool:
            got = lin.solve([*kept, *chosen, c])
            if got is None or (CONTROL_SIGN and got[0][-1] <= 0.0):
                continue        # a compliance below zero is at its physical bound: it moves nothing
            shift = float(np.max(np.abs(got[0][:nb] - now[0][:nb]) / std_now))
            if shift > best_shift:
                best, best_shift = c, shift
        if best is None:
            break
        chosen.append(best)
        pool.remove(best)
    return tuple(nm for nm in components if nm in chosen)


def twins(full_fit, sel: Selection, components: tuple[str, ...], springs: dict[str, str]) -> tuple[Twin, ...]:
    """The joint springs the data do not determine because a fitted component has a twin.

    Two components the data cannot tell apart (a forearm's torsion and the hand's bending under
    loads that twist both alike) fit equally well; the selection keeps one, and a spring that
    aliases with one but not the other follows the choice. A component not fitted is a twin of a
    fitted one when, put in its place, the residual grows by less than the test's threshold (the
    data do not prefer the fitted one as the test would need) and its value there is not of the
    wrong sign beyond noise. The spring follows the choice when that swap, for a kept component,
    moves it (``springs``: beta name -> reported name) by more than TWIN_SHIFT of its std. The fit
    keeps its values; the spring is reported not determined. The largest shift per spring.

    (A twin of a control is not looked for: a control is no finding, and swapping one insignificant
    control for another moved k1, k2 by 2-3.5 std on six-joint fits whose springs are right.)"""
    lin = _Linear(full_fit, components)
    fitted = [nm for nm in sel.fitted() if nm in lin.names]
    now = lin.solve(fitted)
    if now is None or not fitted:
        return ()
    rss_now, nb = lin.last_rss, len(lin.base)
    dof = max(lin.n - nb - len(fitted), 1)
    s2 = max(rss_now / dof, 1.0) if lin.white else rss_now / dof
    if not s2 > 0:
        return ()
    std_now = np.sqrt(np.clip(np.diag(now[1])[:nb], 1e-300, None))
    rows = [(i, springs[lin.names[c]]) for i, c in enumerate(lin.base) if lin.names[c] in springs]
    limit = threshold(lin.n)
    pool = [nm for nm in components if nm in lin.names and nm not in fitted]
    best: dict[str, Twin] = {}

    def note(fitted_one: str, c: str, b: np.ndarray) -> None:
        for i, spring in rows:
            shift = float(abs(b[i] - now[0][i]) / std_now[i])
            if shift > TWIN_SHIFT and (spring not in best or shift > best[spring].shift_std):
                best[spring] = Twin(spring, fitted_one, c, shift)

    def z_last(got) -> float:
        var = float(got[1][-1, -1])
        return got[0][-1] / math.sqrt(var) if var > 0 else -math.inf

    for c in pool:
        for k in (nm for nm in sel.kept if nm in fitted):
            got = lin.solve([*(x for x in fitted if x != k), c])
            if got is not None and (lin.last_rss - rss_now) / s2 < limit and z_last(got) >= -WRONG_SIGN_STD:
                note(k, c, got[0])          # in place of the kept one it fits as well: which is there?
    return tuple(best[s] for _, s in rows if s in best)


def honest_reach(z: float, r: float, rho: float) -> float:
    """How far a spring's honest 95 % interval reaches over its printed one, when a component left out
    at its bound (its value ``z`` of its std beside the fitted ones, ``z <= 0``) is free in [0, inf).

    The printed interval is the fit without the component (the constrained estimate: c = 0), half-width
    ``sqrt(q)`` of the spring's std. With the component free the spring's std is ``r`` times that and its
    correlation with the component ``rho``; the profile deviance, against the constrained maximum (which
    lies ``z**2`` above the free one), reaches ``q`` where the free fit's deviance is ``q + z**2``, on the
    side where the component grows; the free estimate sits ``|rho| |z|`` of its std on the other side of the
    constrained one. Where the component at that end would be below zero the bound holds it, and the
    interval is the printed one."""
    q, z, rho = BOUND_CHI2, min(z, 0.0), abs(rho)
    wide = math.sqrt(q + z * z)
    if rho * wide < abs(z):             # the end lies where the component is held at zero
        return 1.0
    return max(r * (wide - rho * abs(z)) / math.sqrt(q), 1.0)


def at_bound(full_fit, sel: Selection, components: tuple[str, ...], springs: dict[str, str]) -> tuple[AtBound, ...]:
    """The joint springs a component left out for its sign leaves undetermined.

    A component not fitted whose value beside the fitted ones is below zero (within noise: beyond
    WRONG_SIGN_STD it is no compliance at all) is left out because a compliance is not negative: the
    constrained estimate is zero, and the spring's printed std is the fit's without it. But the data still
    allow the component positive values, up to about its estimate plus two of its std, and a spring that
    aliases with it moves with it: its honest interval (:func:`honest_reach`) reaches beyond the printed
    one on that side. When it reaches more than BOUND_REACH times as far, the spring is reported not
    determined. The largest reach per spring."""
    lin = _Linear(full_fit, components)
    fitted = [nm for nm in sel.fitted() if nm in lin.names]
    now = lin.solve(fitted)
    if now is None:
        return ()
    nb = len(lin.base)
    std_now = np.sqrt(np.clip(np.diag(now[1])[:nb], 1e-300, None))
    rows = [(i, springs[lin.names[c]]) for i, c in enumerate(lin.base) if lin.names[c] in springs]
    best: dict[str, AtBound] = {}
    for c in (nm for nm in components if nm in lin.names and nm not in fitted):
        got = lin.solve([*fitted, c])
        if got is None:
            continue
        b, cov = got
        var_c = float(cov[-1, -1])
        if not var_c > 0:
            continue
        z = float(b[-1]) / math.sqrt(var_c)
        if z > 0.0 or z < -WRONG_SIGN_STD:
            continue            # not left out for its sign (the test's and the controls' business), or no compliance
        for i, spring in rows:
            var_k = float(cov[i, i])
            if not var_k > 0:
                continue
            reach = honest_reach(z, math.sqrt(var_k) / std_now[i], float(cov[i, -1]) / math.sqrt(var_k * var_c))
            if reach > BOUND_REACH and (spring not in best or reach > best[spring].reach):
                best[spring] = AtBound(spring, c, float(reach))
    return tuple(best[s] for _, s in rows if s in best)


def threshold(n: int) -> float:
    """Wald statistic a component needs: p < SELECT_P and delta BIC < SELECT_DELTA_BIC."""
    return max(float(scipy.stats.chi2.isf(SELECT_P, 1)), math.log(max(n, 2)) - SELECT_DELTA_BIC)


def confirm_selection(sel: Selection, fit_with, *, n: int) -> Selection:
    """Backward check in the fit's own form (the selection ran on the first-order
    linearisation): drop the weakest kept component while it fails the test."""
    from dataclasses import replace

    kept = list(sel.kept)
    limit = threshold(n)
    while kept:
        fit = fit_with(tuple(kept))
        stats = []
        for name in kept:
            i = fit.beta_names.index(name)
            var = float(fit.beta_cov[i, i])
            z = fit.beta[i] / math.sqrt(var) if var > 0 else 0.0
            stats.append(-1.0 if z < -WRONG_SIGN_STD else z * z)
        weakest = int(np.argmin(stats))
        if stats[weakest] > limit:
            break
        kept.pop(weakest)
    return replace(sel, kept=tuple(kept))
