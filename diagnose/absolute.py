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
(``TRACKER_FRAME_NOTE``).

``kinematic_errors`` is tested by the drop of the noise-weighted residual sum of
squares: a chi-square test (F with unknown noise) with as many degrees of
freedom as identifiable parameters it adds, and delta BIC. On a complete model
the drop is chi-square noise and the candidate is not significant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.stats

from elastocal.errors import InputError
from elastocal.identify.absolute import ABSOLUTE_EFFECTS, AbsoluteFit, identify_absolute
from elastocal.model.effects import get_effect
from elastocal.model.robot import Robot
from elastocal.identify.static import StaticDataset
from elastocal.diagnose.stepwise import FLOOR_RATIO

#: a candidate is significant below this p-value and delta BIC (docs/cli.md)
VERDICT_P = 0.01
VERDICT_DELTA_BIC = -10.0
#: what each absolute candidate is fitted with (the registration is always in). Thermal drift
#: is a candidate here too: it moves every reading with time, and over a whole experiment
#: (hours) the absolute positions see far more of it than a deflection does (seconds apart)
CANDIDATE_MODELS = {"kinematic_errors": ("kinematic_errors", "tracker_frame"), "thermal_drift": ("thermal_drift",),
                    # on a table without loads (diagnose/absolute_only.py): the twist under the robot's own weight
                    "joint_stiffness": ("joint_stiffness",)}
TRACKER_FRAME_NOTE = ("the registration is part of every absolute comparison (fitted with the elastic model on the "
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

    @property
    def significant(self) -> bool:
        return self.p_value < VERDICT_P and self.delta_bic < VERDICT_DELTA_BIC

    def to_json(self) -> dict:
        return {"effect": self.effect, "data": "absolute", "with": list(self.fitted_with),
                "rms_before": self.rms_before, "rms_after": self.rms_after, "max_after": self.max_after,
                "delta_bic": self.delta_bic, "p_value": self.p_value, "evidence": self.evidence,
                "significant": self.significant, "statistic": self.statistic, "dof": self.dof,
                "noise_floor_after": self.noise_floor_after, "explanation": self.explanation,
                "unidentifiable": list(self.fit.unidentifiable)}


@dataclass(frozen=True, eq=False)
class AbsoluteDiagnosis:
    base: AbsoluteFit
    candidates: tuple[AbsoluteCandidate, ...]      # tested against the base, best first
    steps: tuple[AbsoluteCandidate, ...]
    final: AbsoluteFit

    @property
    def at_floor(self) -> bool:
        floor = self.final.noise_floor
        return floor is None or self.final.rms <= FLOOR_RATIO * floor

    @property
    def base_at_floor(self) -> bool:
        floor = self.base.noise_floor
        return floor is None or self.base.rms <= FLOOR_RATIO * floor

    def to_json(self) -> dict:
        b, f = self.base, self.final
        return {"absolute_residual": {"rms": b.rms, "max": b.max, "n": b.n, "unit": "m"},
                "absolute_noise_floor": b.noise_floor,
                "absolute_steps": [{"effect": s.effect, "with": list(s.fitted_with),
                                    "residual": {"rms": s.rms_after, "max": s.max_after, "n": b.n, "unit": "m"},
                                    "noise_floor": s.noise_floor_after, "delta_bic": s.delta_bic,
                                    "p_value": s.p_value} for s in self.steps],
                "absolute_final": {"model": list(f.model),
                                   "residual": {"rms": f.rms, "max": f.max, "n": f.n, "unit": "m"},
                                   "noise_floor": f.noise_floor},
                "absolute_per_pose": b.per_pose(),
                **({"registration": b.json_fields()["registration"]} if b.tracker_prior is not None else {})}


def _test(base: AbsoluteFit, aug: AbsoluteFit) -> tuple[float, float, float, int]:
    """(statistic, p, delta BIC, dof) of ``aug`` against ``base``."""
    dof = max(aug.n_params - base.n_params, 1)
    n = aug.n
    drop = max(base.rss_whitened - aug.rss_whitened, 0.0)
    var = base.static.dataset.abs_var
    if var is not None and base.static.dataset.sigma_tracker is None and base.noise_floor is not None:
        # readings weighted with their stated noise plus each fit's own excess: compared under the stated noise
        drop = max(float(np.sum(base.residuals ** 2 / var)) - float(np.sum(aug.residuals ** 2 / var)), 0.0)
    if base.noise_floor is not None:         # known noise: chi-square
        stat = drop
        p = float(scipy.stats.chi2.sf(stat, dof))
        dbic = -drop + dof * math.log(n)
    else:                                    # unknown level: F
        s2 = aug.rss_whitened / max(n - aug.n_params, 1)
        stat = drop / dof / s2 if s2 > 0 else math.inf
        p = float(scipy.stats.f.sf(stat, dof, max(n - aug.n_params, 1)))
        dbic = n * math.log(max(aug.rss_whitened, 1e-300) / max(base.rss_whitened, 1e-300)) + dof * math.log(n)
    return float(stat), p, float(dbic), dof


def _evidence(effect: str, before: AbsoluteFit, after: AbsoluteFit) -> str:
    text = (f"absolute positions {before.rms * 1e6:.1f} → {after.rms * 1e6:.1f} µm rms "
            f"(max {before.max * 1e3:.2f} mm → {after.max * 1e6:.1f} µm)")
    if effect == "kinematic_errors":
        big = sorted((p for p in after.parameters if p.name in after.kinematic_names and p.std > 0),
                     key=lambda p: -abs(p.value) / p.std)[:3]
        text += "; clearest: " + ", ".join(f"{p.name} = {p.value:.3g} {p.unit}" for p in big)
    return text


def diagnose_absolute(robot: Robot, ds: StaticDataset, model: Sequence[str], *, torque: str = "current",
                      form: str = "exact", pool: Sequence[str] = ABSOLUTE_EFFECTS,
                      tracker_prior: Sequence[float] | None = None) -> AbsoluteDiagnosis:
    """Compare ``model`` (with its registration) with the absolute positions and
    test the absolute effects it lacks; ``tracker_prior`` (base coordinates [m]) is a
    prior on the registration of every fit."""
    base = identify_absolute(robot, ds, model=tuple(dict.fromkeys([*model, "tracker_frame"])), torque=torque,
                             form=form, tracker_prior=tracker_prior)
    pool = tuple(p for p in pool if p in CANDIDATE_MODELS)
    first: tuple[AbsoluteCandidate, ...] | None = None
    steps: list[AbsoluteCandidate] = []
    fit = base
    while True:
        cands = []
        for name in pool:
            if name in fit.model:
                continue
            names = tuple(dict.fromkeys([*fit.model, *CANDIDATE_MODELS[name]]))
            try:
                aug = identify_absolute(robot, ds, model=names, torque=torque, form=form,
                                        tracker_prior=tracker_prior)
            except InputError as exc:       # the data cannot show it (no times for a drift)
                if exc.argument != "model":  # a refusal of the model, typed; anything else is an error
                    raise
                continue
            stat, p, dbic, dof = _test(fit, aug)
            eff = get_effect(name)
            cands.append(AbsoluteCandidate(
                effect=name, fitted_with=CANDIDATE_MODELS[name][1:], explanation=eff.explanation,
                evidence=_evidence(name, fit, aug), rms_before=fit.rms, rms_after=aug.rms, max_after=aug.max,
                noise_floor_after=aug.noise_floor, delta_bic=dbic, p_value=p, statistic=stat, dof=dof, fit=aug))
        cands.sort(key=lambda c: (c.delta_bic, c.rms_after))
        if first is None:
            first = tuple(cands)
        best = next((c for c in cands if c.significant), None)
        if best is None:
            break
        steps.append(best)
        fit = best.fit
    return AbsoluteDiagnosis(base=base, candidates=first or (), steps=tuple(steps), final=fit)


def combined_verdict(deflection_verdict: str | None, deflection_steps: int, deflection_unexplained: bool,
                     absolute: AbsoluteDiagnosis | None) -> str | None:
    """The verdict over deflections and absolute positions: the deflection
    verdict when there is one; else the first absolute step when the deflection
    model is complete and the absolute positions reach their floor with it."""
    if deflection_verdict is not None or absolute is None:
        return deflection_verdict
    if deflection_steps or deflection_unexplained or not absolute.steps or not absolute.at_floor:
        return None
    return absolute.steps[0].effect


def absolute_unexplained(absolute: AbsoluteDiagnosis | None) -> str | None:
    """What stays above the absolute floor that no absolute candidate explains (None when nothing)."""
    if absolute is None or absolute.at_floor:
        return None
    f = absolute.final
    added = " after " + ", ".join(s.effect for s in absolute.steps) if absolute.steps else ""
    return (f"absolute positions stay {f.rms / f.noise_floor:.2f}x their noise floor{added} "
            f"({f.rms * 1e6:.1f} µm rms, floor {f.noise_floor * 1e6:.1f} µm)")

