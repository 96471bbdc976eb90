"""Diagnosis on the absolute positions (docs/cli.md, ``diagnose --json`` with absolute positions).

The deflection diagnosis (diagnose/static.py) finds what the elastic model
misses; this one compares the same model with the absolute marker positions and
tests ``kinematic_errors`` as a candidate like any other.

The registration of the tracker is part of every absolute comparison: the
comparison's model is the elastic model with ``tracker_frame``, fitted on the
absolute positions (identify/absolute.py). It must be: the absolute positions
carry the gravity sag, which pins the stiffness far better than the
deflections do, so an elastic model held at its deflection estimate would
leave a significant excess on complete data and make any refitted candidate
look significant. ``tracker_frame`` is therefore never a missing effect here
(``REGISTRATION_NOTE``).

``kinematic_errors`` is tested by the drop of the noise-weighted residual sum of
squares: a chi-square test (F with unknown noise) with as many degrees of
freedom as identifiable parameters it adds, and delta BIC. On a complete model
the drop is chi-square noise and the candidate is not significant.

The guards of the deflection side hold here too. The drop is divided by the
dispersion the augmented model still leaves, ``max(1, rss_w / (n - p))``, so a
candidate that only soaks up part of an effect outside the vocabulary is not
significant (an F test, as the deflection side's Wald test). A candidate whose
fitted values are implausible (diagnose/plausibility.py: a negative stiffness,
the effect module's own limits) is never a step. And its explanation must hold
across the data (:func:`explanation_holds`): what it explains, refitted on each
marker alone, on the first and the second half of the poses and on alternate
poses, must be the same within the noise; a drift with time that is really the
tracker creeping follows time in every marker and in every half, a "drift" that
takes up a pose-dependent error does not. Each step says what share of the
absolute excess over the floor it removed; steps are named to the user only
when the final absolute model leaves at most :data:`NAMED_RATIO` x its floor,
else they are reported as partial (they stay in the model compared, never as
an answer).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.linalg
import scipy.stats

from elastocal.errors import EffectRefused, InputError
from elastocal.formats.calibration import is_stiffness_name
from elastocal.identify.absolute import ABSOLUTE_EFFECTS, AbsoluteFit, identify_absolute
from elastocal.model.effects import get_effect, having
from elastocal.model.robot import Robot
from elastocal.identify.static import StaticDataset
from elastocal.diagnose.stepwise import FLOOR_RATIO
from elastocal.model.kinds import KinematicForm, TorqueSource

#: a candidate is significant below this p-value and delta BIC (docs/cli.md)
VERDICT_P = 0.01
VERDICT_DELTA_BIC = -10.0
#: steps are named to the user only when the final absolute model leaves at most this x its floor
NAMED_RATIO = 2.0
#: the explanation holds across the data unless a split disagrees below this p (over the splits)
HOLDS_P = 0.01
REGISTRATION_NOTE = ("the registration is part of every absolute comparison (fitted with the elastic model on the "
                      "absolute positions); it is never missing")


@dataclass(frozen=True, eq=False)
class AbsoluteCandidate:
    effect: str
    fitted_with: tuple[str, ...]
    explanation: str
    evidence: str
    rms_before: float
    rms_after: float
    max_after: float
    noise_floor_after: float | None
    delta_bic: float
    p_value: float
    statistic: float
    dof: int
    fit: AbsoluteFit = field(repr=False)
    #: max(1, rss_w / (n - p)) the augmented model leaves: the test's drop is divided by it
    dispersion: float = 1.0
    #: why the fitted values are implausible (never a step), None when plausible
    implausible: str | None = None
    #: why its explanation does not hold across the data (never a step), None when it holds
    does_not_hold: str | None = None
    #: share of the excess over the floor (mean square) of the model before it that it removes
    explained: float = 0.0

    @property
    def significant(self) -> bool:
        return self.p_value < VERDICT_P and self.delta_bic < VERDICT_DELTA_BIC

    @property
    def admissible(self) -> bool:
        """Can be a step: significant, plausible, and its explanation holds across the data."""
        return self.significant and self.implausible is None and self.does_not_hold is None

    def to_json(self) -> dict:
        return {"effect": self.effect, "data": "absolute", "with": list(self.fitted_with),
                "rms_before": self.rms_before, "rms_after": self.rms_after, "max_after": self.max_after,
                "delta_bic": self.delta_bic, "p_value": self.p_value, "evidence": self.evidence,
                "significant": self.significant, "statistic": self.statistic, "dof": self.dof,
                "dispersion": self.dispersion, "explained": self.explained,
                "noise_floor_after": self.noise_floor_after, "explanation": self.explanation,
                "unidentifiable": list(self.fit.unidentifiable),
                **({"implausible": self.implausible} if self.implausible else {}),
                **({"does_not_hold": self.does_not_hold} if self.does_not_hold else {})}

    def step_json(self, n: int) -> dict:
        """The step's ``absolute_steps`` entry: its residual and what it explained."""
        return {"effect": self.effect, "with": list(self.fitted_with),
                "residual": {"rms": self.rms_after, "max": self.max_after, "n": n, "unit": "m"},
                "noise_floor": self.noise_floor_after, "delta_bic": self.delta_bic, "p_value": self.p_value,
                "explained": self.explained, "evidence": self.evidence,
                "ratio": (self.rms_after / self.noise_floor_after if self.noise_floor_after else None)}


@dataclass(frozen=True, eq=False)
class AbsoluteDiagnosis:
    base: AbsoluteFit
    candidates: tuple[AbsoluteCandidate, ...]      # tested against the base, best first
    steps: tuple[AbsoluteCandidate, ...]
    final: AbsoluteFit
    #: (effect, why) of the pool's effects these data cannot show (refused by the fit, by name)
    refused: tuple[tuple[str, str], ...] = ()

    @property
    def at_floor(self) -> bool:
        floor = self.final.noise_floor
        return floor is None or self.final.rms <= FLOOR_RATIO * floor

    @property
    def base_at_floor(self) -> bool:
        floor = self.base.noise_floor
        return floor is None or self.base.rms <= FLOOR_RATIO * floor

    @property
    def final_ratio(self) -> float | None:
        floor = self.final.noise_floor
        return self.final.rms / floor if floor else None

    @property
    def named_steps(self) -> tuple[AbsoluteCandidate, ...]:
        """The steps named to the user: all of them when the final model leaves at most
        NAMED_RATIO x its floor, else none (they are partial: ``partial_steps``)."""
        ratio = self.final_ratio
        return self.steps if ratio is None or ratio <= NAMED_RATIO else ()

    @property
    def partial_steps(self) -> tuple[AbsoluteCandidate, ...]:
        return () if self.named_steps else self.steps

    def to_json(self) -> dict:
        b, f = self.base, self.final
        return {"absolute_residual": {"rms": b.rms, "max": b.max, "n": b.n, "unit": "m"},
                "absolute_noise_floor": b.noise_floor,
                "absolute_steps": [s.step_json(b.n) for s in self.named_steps],
                "absolute_partial_steps": [s.step_json(b.n) for s in self.partial_steps],
                # parameters the absolute fit moves while it leaves a residual it cannot explain
                "sensitive": [m.to_json() for m in f.sensitivities()],
                "absolute_final": {"model": list(f.model),
                                   "residual": {"rms": f.rms, "max": f.max, "n": f.n, "unit": "m"},
                                   "noise_floor": f.noise_floor},
                "absolute_per_pose": b.per_pose(),
                **({"registration": b.json_fields()["registration"]} if b.tracker_prior is not None else {})}


def _dispersion(fit: AbsoluteFit) -> float:
    return max(1.0, fit.rss_whitened / max(fit.n - fit.n_params, 1))


def _test(base: AbsoluteFit, aug: AbsoluteFit) -> tuple[float, float, float, int]:
    """(statistic, p, delta BIC, dof) of ``aug`` against ``base``; with known noise the drop
    is divided by the dispersion ``aug`` still leaves (an F test when it leaves more than noise)."""
    dof = max(aug.n_params - base.n_params, 1)
    n = aug.n
    drop = max(base.rss_whitened - aug.rss_whitened, 0.0)
    var = base.static.dataset.stated_variance
    if var is not None and base.static.dataset.sigma_tracker is None and base.noise_floor is not None:
        # readings weighted with their stated noise plus each fit's own excess: compared under the stated noise
        drop = max(float(np.sum(base.residuals ** 2 / var)) - float(np.sum(aug.residuals ** 2 / var)), 0.0)
    if base.noise_floor is not None:         # known noise: chi-square, scaled by what is left
        stat = drop / _dispersion(aug)
        p = float(scipy.stats.chi2.sf(stat, dof))
        dbic = -stat + dof * math.log(n)
    else:                                    # unknown level: F
        s2 = aug.rss_whitened / max(n - aug.n_params, 1)
        stat = drop / dof / s2 if s2 > 0 else math.inf
        p = float(scipy.stats.f.sf(stat, dof, max(n - aug.n_params, 1)))
        dbic = n * math.log(max(aug.rss_whitened, 1e-300) / max(base.rss_whitened, 1e-300)) + dof * math.log(n)
    return float(stat), p, float(dbic), dof


def _splits(ds: StaticDataset, n_states: int, n_markers: int) -> list[tuple[str, list[tuple[str, np.ndarray]]]]:
    """The splits an explanation must survive: (what is split, [(part name, (S, M) mask)])."""
    out = []
    if n_markers > 1:
        out.append(("markers", [(f"marker {m}", np.broadcast_to(np.arange(n_markers)[None, :] == k,
                                                               (n_states, n_markers)))
                                for k, m in enumerate(ds.markers)]))
    pose = np.asarray(ds.state_pose)
    n_poses = len(ds.pose_ids)
    if n_poses >= 4:
        # poses in the order they were measured (by their mean reading time where known)
        t = ds.abs_t
        when = np.array([np.nanmean(t[pose == p]) if t is not None and np.any(np.isfinite(t[pose == p]))
                         else p for p in range(n_poses)])
        rank = np.empty(n_poses, dtype=int)
        rank[np.argsort(when, kind="stable")] = np.arange(n_poses)
        early = rank[pose] < n_poses // 2
        even = rank[pose] % 2 == 0
        full = np.ones((1, n_markers), dtype=bool)
        out.append(("halves of the poses", [("the first half of the poses", early[:, None] & full),
                                            ("the second half", ~early[:, None] & full)]))
        out.append(("alternate poses", [("the odd poses", even[:, None] & full),
                                        ("the even poses", ~even[:, None] & full)]))
    return out


def explanation_holds(aug: AbsoluteFit, names: Sequence[str], ds: StaticDataset) -> str | None:
    """Why what the parameters ``names`` of ``aug`` explain does not hold across the data,
    or None when it holds (or there is nothing to split).

    The signal they carry, ``r + J θ`` (the residual plus their part of the prediction), is
    refitted on each part of each split (:func:`_splits`) with the other parameters held,
    weighted by the readings' noise; the parts' estimates must agree: a heterogeneity
    chi-square ``Σ (θ_k − θ̄)ᵀ C_k⁻¹ (θ_k − θ̄)``, (K − 1) q degrees of freedom, p below
    HOLDS_P (Bonferroni over the splits) says they do not. The noise is the readings' own
    (not inflated by what the model leaves): a candidate that takes up part of a structured
    residual is pulled differently by each part."""
    if aug.design is None or aug.noise_floor is None:
        return None
    cols = [i for i, n in enumerate(aug.design_names) if n in names]
    if not cols:
        return None
    jac = aug.design[..., cols]                                   # (S, M, 3, q)
    theta = aug.design_values[cols]
    signal = aug.residuals + jac @ theta                          # (S, M, 3)
    n_s, n_m = signal.shape[:2]
    q = len(cols)
    splits = _splits(ds, n_s, n_m)
    worst: tuple[float, str] | None = None
    for what, parts in splits:
        ests = []
        for label, mask in parts:
            a_rows, b_rows = [], []
            for s_ in range(n_s):
                ms = np.flatnonzero(mask[s_])
                if ms.size == 0:
                    continue
                rows = (3 * ms[:, None] + np.arange(3)).reshape(-1)
                chol = np.linalg.cholesky(aug.state_cov[s_][np.ix_(rows, rows)])
                a_rows.append(scipy.linalg.solve_triangular(chol, jac[s_, ms].reshape(-1, q), lower=True))
                b_rows.append(scipy.linalg.solve_triangular(chol, signal[s_, ms].reshape(-1), lower=True))
            a, b = np.vstack(a_rows), np.concatenate(b_rows)
            info = a.T @ a
            if a.shape[0] <= q or np.linalg.matrix_rank(info) < q:
                break                 # a part that cannot fix the parameters: this split says nothing
            cov = np.linalg.inv(info)
            ests.append((label, cov @ (a.T @ b), cov))
        else:
            w = [np.linalg.inv(c) for _, _, c in ests]
            mean = np.linalg.solve(sum(w), sum(wk @ e for wk, (_, e, _) in zip(w, ests)))
            stat = float(sum((e - mean) @ wk @ (e - mean) for wk, (_, e, _) in zip(w, ests)))
            p = float(scipy.stats.chi2.sf(stat, (len(ests) - 1) * q))
            if worst is None or p < worst[0]:
                far = max(ests, key=lambda x: float((x[1] - mean) @ np.linalg.solve(x[2], x[1] - mean)))
                worst = (p, f"what it explains differs between {what} (p {p:.1g}; {far[0]} the farthest)")
    if worst is not None and worst[0] < HOLDS_P / max(len(splits), 1):
        return worst[1]
    return None


def _implausible(effect, aug: AbsoluteFit, added: Sequence[str]) -> str | None:
    """Why the candidate's fitted values are implausible (diagnose/plausibility.py's rules), or None."""
    neg = [p.name for p in aug.parameters if is_stiffness_name(p.name) and not p.value > 0]
    if neg:
        return f"the fit makes the joint stiffness {', '.join(neg)} negative"
    check = getattr(effect, "plausibility", None)
    params = [p for p in aug.parameters if p.name in added]
    if check is None or not params:
        return None
    return check(tuple(p.name for p in params), np.array([p.value for p in params]),
                 np.array([p.std for p in params]))


def _explained(before: AbsoluteFit, after: AbsoluteFit) -> float:
    """Share of ``before``'s excess over its floor (mean square) that ``after`` removes."""
    floor = before.noise_floor or 0.0
    excess = before.rms ** 2 - floor ** 2
    if excess <= 0:
        return 0.0
    return float(min(max(before.rms ** 2 - after.rms ** 2, 0.0) / excess, 1.0))


def _evidence(effect: str, before: AbsoluteFit, after: AbsoluteFit) -> str:
    text = (f"absolute positions {before.rms * 1e6:.1f} → {after.rms * 1e6:.1f} µm rms "
            f"(max {before.max * 1e3:.2f} mm → {after.max * 1e6:.1f} µm)")
    if get_effect(effect).geometry:
        big = sorted((p for p in after.parameters if p.name in after.kinematic_names and p.std > 0),
                     key=lambda p: -abs(p.value) / p.std)[:3]
        text += "; clearest: " + ", ".join(f"{p.name} = {p.value:.3g} {p.unit}" for p in big)
    return text


def diagnose_absolute(robot: Robot, ds: StaticDataset, model: Sequence[str], *,
                      torque: TorqueSource = TorqueSource.CURRENT, form: KinematicForm = KinematicForm.EXACT,
                      pool: Sequence[str] = ABSOLUTE_EFFECTS,
                      tracker_prior: Sequence[float] | None = None) -> AbsoluteDiagnosis:
    """Compare ``model`` (with its registration) with the absolute positions and
    test the absolute effects it lacks; ``tracker_prior`` (base coordinates [m]) is a
    prior on the registration of every fit."""
    base = identify_absolute(robot, ds, model=tuple(dict.fromkeys([*model, *having("registration")])), torque=torque,
                             form=form, tracker_prior=tracker_prior)
    # every effect of the pool is a candidate (each fitted with what its module says,
    # Effect.fitted_with) but the registration: it is in every fit
    pool = tuple(p for p in pool if not get_effect(p).registration)
    first: tuple[AbsoluteCandidate, ...] | None = None
    steps: list[AbsoluteCandidate] = []
    refused: dict[str, str] = {}
    fit = base
    while True:
        cands = []
        for name in pool:
            if name in fit.model:
                continue
            names = tuple(dict.fromkeys([*fit.model, name, *get_effect(name).fitted_with]))
            try:
                aug = identify_absolute(robot, ds, model=names, torque=torque, form=form,
                                        tracker_prior=tracker_prior)
            except InputError as exc:       # the data cannot show it (no times for a drift)
                if exc.argument != "model":  # a refusal of the model, typed; anything else is an error
                    raise
                refused.setdefault(name, exc.reason if isinstance(exc, EffectRefused) else str(exc))
                continue
            stat, p, dbic, dof = _test(fit, aug)
            eff = get_effect(name, robot)       # its parameters sized for this robot's joints (b1..bN)
            implausible = _implausible(eff, aug, eff.parameters)
            holds = None
            if p < VERDICT_P and dbic < VERDICT_DELTA_BIC and implausible is None:
                holds = explanation_holds(aug, eff.parameters, aug.dataset)
            cands.append(AbsoluteCandidate(
                effect=name, fitted_with=get_effect(name).fitted_with, explanation=eff.explanation,
                evidence=_evidence(name, fit, aug), rms_before=fit.rms, rms_after=aug.rms, max_after=aug.max,
                noise_floor_after=aug.noise_floor, delta_bic=dbic, p_value=p, statistic=stat, dof=dof, fit=aug,
                dispersion=_dispersion(aug), implausible=implausible, does_not_hold=holds,
                explained=_explained(fit, aug)))
        cands.sort(key=lambda c: (c.delta_bic, c.rms_after))
        if first is None:
            first = tuple(cands)
        best = next((c for c in cands if c.admissible), None)
        if best is None:
            break
        steps.append(best)
        fit = best.fit
    return AbsoluteDiagnosis(base=base, candidates=first or (), steps=tuple(steps), final=fit,
                             refused=tuple(refused.items()))


def combined_verdict(deflection_verdict: str | None, deflection_steps: int, deflection_unexplained: bool,
                     absolute: AbsoluteDiagnosis | None) -> str | None:
    """The verdict over deflections and absolute positions: the deflection
    verdict when there is one; else the first absolute step when the deflection
    model is complete and the absolute positions reach their floor with it."""
    if deflection_verdict is not None or absolute is None:
        return deflection_verdict
    if deflection_steps or deflection_unexplained or not absolute.named_steps or not absolute.at_floor:
        return None
    return absolute.named_steps[0].effect


def absolute_unexplained(absolute: AbsoluteDiagnosis | None) -> str | None:
    """What stays above the absolute floor that no absolute candidate explains (None when nothing)."""
    if absolute is None or absolute.at_floor:
        return None
    f = absolute.final
    text = (f"absolute positions stay {f.rms / f.noise_floor:.2f}x their noise floor "
            f"({f.rms * 1e6:.1f} µm rms, floor {f.noise_floor * 1e6:.1f} µm)")
    if absolute.steps:
        text += "; " + ", ".join(f"{s.effect} took up {100 * s.explained:.0f} % of the excess before it"
                                 for s in absolute.steps)
        if not absolute.named_steps:
            text += f", not named: more than {NAMED_RATIO:g}x the floor remains"
    return text

