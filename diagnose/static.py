"""Diagnose: where the model fails, and which missing effect explains it.

Pure functions: a robot and a static table (or dataset) in, a frozen
:class:`Diagnosis` out. For every effect of the table (identify/effects) that
the model lacks and the data can show, the augmented model is fitted (exact,
secant form by default) and tested against the model:

* **Wald test with the measured noise** (the nested-model test). The residuals
  of the deflections of one pose share the unloaded reference reading and the
  current noise, so they are correlated; the fit knows their covariance
  ``Sigma`` (tracker and current repeatability from repeated readings,
  propagated through the model: ``StaticFit.noise_blocks``). The added
  parameters ``gamma`` of the augmented fit have the sandwich covariance
  ``V = (A'A)^-1 A' Sigma A (A'A)^-1``, scaled by the dispersion ``phi =
  max(1, rss / expected_rss)`` that the augmented model still leaves; the
  statistic ``W = gamma' V^-1 gamma`` is chi-square with q (number of
  identifiable added parameters) degrees of freedom when the effect is absent.
  The dispersion makes a candidate that only soaks up part of another missing
  effect's residual "not significant", as in an F test.
* **BIC** of the same Gaussian likelihood: ``delta_bic = -W + q ln n`` (n the
  number of deflection components); negative favours the effect. The fits are
  generalised least squares weighted by the noise covariance
  (identify/static.py), so W is the likelihood ratio of the nested models.

Without repeated readings the noise level is unknown: the tests then assume
the structure of tracker noise (deflections of one marker share the reference
reading) at the level that makes the model's own residual what noise leaves,
which keeps the false-alarm rate near its nominal value but costs power; no
noise floor is reported.

The verdict (docs/cli.md) is the best candidate when its p < 0.01 and its
delta_bic < -10, else None. With q ln n in the BIC, a candidate of 3 to 6
parameters on the default 324 components needs W above 27 to 45: a false alarm
on complete data has probability below 1e-5 per candidate.

Residual structure no candidate explains is reported when the final model
(model plus verdict) still leaves significantly more than the noise
(``excess_p_value`` < 0.001, a Satterthwaite scaled chi-square of the
residual sum of squares): which poses, markers, joint angles, loads or times the
excess follows.

A parameter-free effect (complementary_stiffness) is embedded as lambda times
its change of the prediction: lambda = 0 is tested, delta_bic taken at 1.

Where the model fails (the residual by pose, marker, load, angle, time) is in
:mod:`elastocal.diagnose.where`, the verdict rule in :mod:`elastocal.diagnose.verdict`,
run data (friction terms on the UV/VU half-differences, compensator and gravity on
the joint-2 sweep means) in :mod:`elastocal.diagnose.runs`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
import scipy.sparse
import scipy.stats

from elastocal.errors import EffectRefused, UnidentifiableError
from elastocal.model.effects import ALL_EFFECTS, get_effect, having
from elastocal.model.robot import Robot
from elastocal.identify.static import (
    Parameter,
    StaticDataset,
    StaticFit,
    build_dataset,
    identify_static,
)
from elastocal.identify.outliers import without_outliers
from elastocal.diagnose.plausibility import implausible_reason
from elastocal.diagnose.stepwise import (
    EXCESS_P,
    Step,
    Unexplained,
    stepwise,
    unexplained_of,
    verdict_of,
)
from elastocal.formats.tables import StaticTable
from elastocal.diagnose.verdict import VERDICT_DELTA_BIC, VERDICT_P, NotTestable
from elastocal.diagnose.where import Where, _noise, excess_p_value, unexplained_structure, where_it_fails
from elastocal.model.kinds import KinematicForm, TorqueSource, expect


# =================================================================== results
@dataclass(frozen=True, eq=False)
class Candidate:
    """One missing effect, fitted and tested."""

    effect: str
    explanation: str
    evidence: str
    rms_after: float
    max_after: float
    noise_floor_after: float | None
    delta_bic: float
    p_value: float | None
    statistic: float           # Wald chi-square (or F * q without repeats)
    dof: int                   # identifiable added parameters
    dispersion: float          # phi of the augmented fit
    parameters: tuple[Parameter, ...]   # the added effect's identifiable parameters
    unidentifiable: tuple[str, ...]     # the added effect's parameters the data cannot separate
    rank: int                  # identifiable parameters of the augmented model
    n_model_parameters: int    # all parameters of the augmented model
    condition_number: float
    fit: StaticFit = field(repr=False)
    #: why the fitted values are physically implausible or the fit near-singular
    #: (never a step, diagnose/plausibility.py); None when plausible
    implausible: str | None = None

    @property
    def significant(self) -> bool:
        return (self.p_value is not None and self.p_value < VERDICT_P
                and self.delta_bic < VERDICT_DELTA_BIC)

    def to_json(self) -> dict:
        return {
            "effect": self.effect,
            "rms_after": self.rms_after,
            "delta_bic": self.delta_bic,
            "p_value": self.p_value,
            "evidence": self.evidence,
            "significant": self.significant,
            "statistic": self.statistic,
            "dof": self.dof,
            "noise_floor_after": self.noise_floor_after,
            "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in self.parameters},
            "unidentifiable": list(self.unidentifiable),
            "rank": self.rank,
            "n_parameters": self.n_model_parameters,
            "condition_number": _finite(self.condition_number),
            "explanation": self.explanation,
            **({"implausible": self.implausible} if self.implausible else {}),
        }


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """What ``elastocal diagnose`` finds (docs/cli.md, ``diagnose --json``)."""

    model: tuple[str, ...]
    torque: TorqueSource
    form: KinematicForm
    fit: StaticFit = field(repr=False)           # the model as given
    candidates: tuple[Candidate, ...]             # best first
    not_testable: tuple[NotTestable, ...]
    verdict: str | None
    final: StaticFit = field(repr=False)          # model + verdict (or the model)
    excess_p_value: float | None                  # does the final model leave more than noise?
    unexplained: tuple[str, ...]
    where: Where = field(repr=False)              # of the model as given
    where_final: Where = field(repr=False)
    #: False without repeated readings: the tests then assume tracker noise at
    #: the level the model's residual shows, and no noise floor is reported
    noise_known: bool = True
    #: effects added in order (diagnose/stepwise.py); final is the model with all of them
    steps: tuple[Step, ...] = ()
    #: what stays above the floor that no candidate explains (None when nothing does)
    unexplained_detail: Unexplained | None = None
    #: readings far off their repeats (identify/outliers.py), left out of the noise floor
    outliers: tuple = ()
    #: the comparison with the absolute positions (diagnose/absolute.py); None without them
    absolute: object | None = None
    #: every side (deflections, absolute positions) that stays above its floor, in that order
    #: (diagnose/unexplained.py): the one ``unexplained`` object of the JSON and the text
    unexplained_sides: tuple = ()

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque, "torque")
        expect(KinematicForm, self.form, "form")

    @property
    def noise_floor(self) -> float | None:
        return self.fit.noise_floor if self.noise_known else None

    @property
    def verdict_candidate(self) -> Candidate | None:
        if self.verdict is None or not self.steps or self.steps[0].effect != self.verdict:
            return None        # no verdict, or one of the absolute positions (``absolute.steps``)
        return self.steps[0].candidate

    def to_json(self) -> dict:
        f = self.fit
        return {
            "model": list(self.model),
            "torque": self.torque,
            "form": self.form,
            "residual": {"rms": f.rms, "max": f.max, "n": f.n, "unit": "m"},
            "noise_floor": self.noise_floor,
            "candidates": [c.to_json() for c in self.candidates],
            "verdict": self.verdict,
            "not_testable": [{"effect": n.effect, "reason": n.reason} for n in self.not_testable],
            "steps": [{"effect": st.effect,
                       "residual": {"rms": st.rms_after, "max": st.candidate.max_after, "n": f.n, "unit": "m"},
                       "noise_floor": st.noise_floor_after if self.noise_known else None,
                       "delta_bic": st.candidate.delta_bic, "p_value": st.candidate.p_value,
                       "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit}
                                      for p in st.candidate.parameters}}
                      for st in self.steps],
            "final": {"model": list(self.final.model),
                      "residual": {"rms": self.final.rms, "max": self.final.max, "n": self.final.n, "unit": "m"},
                      "noise_floor": self.final.noise_floor if self.noise_known else None,
                      "excess_p_value": self.excess_p_value},
            "unexplained": self.unexplained_json(),
            "outliers": [o.to_json() for o in self.outliers],
            "where": self.where.to_json(),
            **self._absolute_json(),
        }

    def unexplained_json(self) -> dict | None:
        """The one ``unexplained`` object (diagnose/unexplained.py): the first side above its floor
        at the top level, every side in ``sides``, the sentences; null when nothing stays."""
        from elastocal.diagnose.unexplained import unexplained_json

        if self.unexplained_sides:
            return unexplained_json(self.unexplained_sides, self.unexplained)
        if self.unexplained_detail is None:
            return None
        return {**self.unexplained_detail.to_json(), "sentences": list(self.unexplained)}

    def _absolute_json(self) -> dict:
        """absolute_residual, absolute_noise_floor and the absolute candidates (docs/cli.md)."""
        if self.absolute is None:
            return {}
        return {**self.absolute.to_json(),
                "absolute_candidates": [c.to_json() for c in self.absolute.candidates]}


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


# =================================================================== tests
def _wald(aug: StaticFit, names: Sequence[str], reported: Sequence[str] | None = None) -> tuple[float, int, float, float]:
    """Statistic, dof, p-value and delta BIC of the added parameters ``names``
    (beta names; ``reported``: the names they are reported under) from the
    augmented fit's sandwich covariance with the noise model, scaled by its
    dispersion."""
    reported = names if reported is None else reported
    idx = [aug.beta_names.index(nm) for nm, rn in zip(names, reported) if rn not in aug.unidentifiable]
    q = len(idx)
    gamma = aug.beta[idx]
    cov = aug.beta_cov[np.ix_(idx, idx)]
    scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    cs = cov / np.outer(scale, scale)
    gs = gamma / scale
    stat = float(gs @ np.linalg.lstsq(cs, gs, rcond=None)[0])
    return stat, q, float(scipy.stats.chi2.sf(stat, q)), -stat + q * math.log(aug.n)


def _assumed_noise(robot: Robot, ds: StaticDataset, model, torque: TorqueSource, form: KinematicForm) -> StaticDataset:
    """Without repeated readings the noise level is unknown. Take the structure
    of tracker noise (the deflections of one marker share its reference reading)
    with the level that makes the model's residual what noise leaves."""
    unit = 1e-5
    fit = identify_static(robot, replace(ds, sigma_tracker=unit), model=model, torque=torque, form=form)
    return replace(ds, sigma_tracker=unit * math.sqrt(fit.rss / fit.expected_rss))


def _embedding(base: StaticFit, aug: StaticFit) -> tuple[float, float | None, float]:
    """Test of a parameter-free effect: embed it as lambda * (its change of the
    prediction) and test lambda = 0 (Wald); delta BIC at lambda = 1."""
    nz = _noise(base)
    d = (aug.predicted - base.predicted).reshape(-1)
    r = base.residuals.reshape(-1)
    if base.whitening is not None:      # in the whitened metric the noise is white
        d, r = base.whiten(d), base.whiten(r)
    d_perp = d - nz.basis @ (nz.basis.T @ d)
    dd = float(d_perp @ d_perp)
    if dd <= 0.0:
        return 0.0, 1.0, 0.0
    lam = float(d_perp @ r) / dd
    if base.whitening is not None:
        var = 1.0 / dd * _dispersion(aug)
    else:
        var = float(d_perp @ (nz.cov @ d_perp)) / dd**2 * _dispersion(aug)
    stat = lam**2 / var
    p = float(scipy.stats.chi2.sf(stat, 1))
    dbic = -(2.0 * lam - 1.0) / var
    return stat, p, dbic


def _dispersion(fit: StaticFit) -> float:
    return fit.dispersion


def _evidence(effect, params: Sequence[Parameter], fallback: str) -> str:
    detail = getattr(effect, "describe", None)
    if detail is None or not params:
        return fallback
    return detail(tuple(p.name for p in params), np.array([p.value for p in params]),
                  np.array([p.std for p in params])) or fallback


# =================================================================== diagnose
def test_candidates(robot: Robot, ds: StaticDataset, base: StaticFit, pool: Sequence[str], *, torque: TorqueSource,
                    form: KinematicForm, noise_known: bool, work=None,
                    progress=None) -> tuple[list[Candidate], list[NotTestable]]:
    """Fit ``base``'s model plus each effect of ``pool`` it lacks and test it
    against ``base``: candidates best first, and the effects these data cannot show. ``work``: the
    diagnosis' Pinocchio work buffers (``robot.create_data()``), shared by its fits. ``progress``:
    called ``progress(done, label, total=...)`` before each effect's fit (elastocal/progress.py)."""
    model_names = base.model
    candidates: list[Candidate] = []
    skipped: list[NotTestable] = []
    todo = [name for name in pool if name not in model_names]
    for i, name in enumerate(todo):
        if progress is not None:
            progress(i, f"testing {name} against {' + '.join(model_names)}", total=len(todo))
        eff = get_effect(name)
        given = base.effects or model_names      # restricted effects stay as they were selected
        try:
            aug = identify_static(robot, ds, model=(*given, name), torque=torque, form=form, work=work)
            fitted = next(e for e in aug.effects if e.name == name) if aug.effects else eff
            sel = next((sl for sl in aug.selections if sl.effect == name), None)
            # the controls are fitted (the joint springs stay honest) but neither tested nor named
            controls = () if sel is None else sel.controls
            if sel is not None and not sel.kept and sel.next_best is not None:
                controls = ()
                # nothing passes: test the best component, to say how far it is from passing
                fitted = eff.restricted((sel.next_best,))
                aug = identify_static(robot, ds, model=(*given, fitted), torque=torque, form=form, work=work)
        except EffectRefused as exc:       # the effect module's own reason, typed
            skipped.append(NotTestable(exc.effect, exc.reason))
            continue
        except UnidentifiableError as exc:       # its own words, without the data's name
            skipped.append(NotTestable(name, exc.detail))
            continue
        added = list(fitted.parameters)
        reported = list(fitted.reported_names)
        if controls:
            added = [nm for nm in added if nm not in controls]
            reported = [nm for nm in reported if nm not in controls]
        unident = tuple(nm for nm in reported if nm in aug.unidentifiable)
        if eff.selectable and not added:
            skipped.append(NotTestable(name, "none of its components can be separated from the model's parameters "
                                             "in these data"))
            continue
        if added and len(unident) == len(added):
            skipped.append(NotTestable(name, "these data cannot separate its parameters from the model's "
                                             f"(rank {aug.n_params} of {len(aug.beta_names)} parameters, "
                                             f"condition number {aug.condition_number:.3g})"))
            continue
        if added:
            stat, dof, p, dbic = _wald(aug, added, reported)
        else:
            stat, p, dbic = _embedding(base, aug)
            dof = 1
        params = tuple(pp for pp in aug.parameters if pp.name in reported)
        candidates.append(Candidate(
            effect=name, explanation=eff.explanation, evidence=_evidence(eff, params, eff.evidence),
            rms_after=aug.rms, max_after=aug.max, noise_floor_after=aug.noise_floor if noise_known else None,
            delta_bic=float(dbic),
            p_value=p, statistic=float(stat), dof=dof, dispersion=_dispersion(aug), parameters=params,
            unidentifiable=unident, rank=aug.n_params, n_model_parameters=len(aug.beta_names),
            condition_number=aug.condition_number, fit=aug,
            implausible=implausible_reason(eff, aug, params)))
    candidates.sort(key=lambda c: (c.delta_bic, c.rms_after))
    return candidates, skipped


def _deflection_unexplained(base: StaticFit, steps, final: StaticFit, floor, excess, where_final,
                            ds: StaticDataset):
    """(sentences, detail) of what the deflections' final model leaves above the noise floor;
    ((), None) when it leaves only noise."""
    if excess is None or excess >= EXCESS_P:
        return (), None
    unexplained = unexplained_structure(where_final)
    detail = unexplained_of(base.rms, steps, final.rms, floor, excess, unexplained)
    if detail is None:
        return unexplained, None
    if not unexplained:
        unexplained = (f"residual stays {detail.ratio:.2f}x the noise floor with no pattern in pose, "
                       "marker, joint angle, load or time",)
    kept = [o for o in ds.outliers if not o.excluded]
    if kept:
        unexplained = (f"{len(kept)} reading(s) far off their repeats (lines "
                       f"{', '.join(str(o.line) for o in kept)}) are in the fit: diagnose again leaving "
                       "them out", *unexplained)
    return unexplained, replace(detail, follows=unexplained)


def _where_absolute_sits(unexplained: tuple[str, ...], sides) -> tuple[str, ...]:
    """The last sentence (the absolute side's) says where its excess sits, when it is located."""
    abs_side = next((sd for sd in sides if sd.side == "absolute" and sd.where is not None), None)
    if abs_side is None or not unexplained:
        return unexplained
    w = abs_side.where
    return (*unexplained[:-1], f"{unexplained[-1]}; it sits in {w.words} ({100 * w.share:.0f} % of "
                               f"the excess in {100 * w.fraction:.0f} % of the readings)")


def diagnose_static(robot: Robot, data: StaticTable | StaticDataset, *,
                    model: Sequence[str] = ("joint_stiffness",), torque: TorqueSource = TorqueSource.CURRENT,
                    form: KinematicForm = KinematicForm.EXACT, effects: Sequence[str] | None = None,
                    exclude_outliers: bool = False, tracker_prior: Sequence[float] | None = None,
                    progress=None) -> Diagnosis:
    """Fit ``model``, test each effect it lacks, and diagnose stepwise (docs/cli.md).

    ``candidates`` are the effects tested against the model as given, best
    first; the best significant, plausible one is added and the rest tested
    again until none is (diagnose/stepwise.py). The verdict is the first step
    when the final model sits at the noise floor, else None with what stays
    unexplained. ``effects``: the candidate effects to try (default: every
    effect of the table). Effects these data cannot show are listed in
    ``not_testable`` with the reason. Readings far off their repeats are listed
    in ``outliers`` and left out of the noise floor; ``exclude_outliers`` (a
    table only) refits without them. ``tracker_prior``: where the tracker stands
    in base coordinates [m] (cell.toml), a prior on the absolute comparison's
    registration (identify/absolute.py). ``progress``: told of each effect's fit, as
    ``progress(done, label, total=...)`` (elastocal/progress.py).
    """
    excluded: tuple = ()
    if exclude_outliers and isinstance(data, StaticTable):
        data, excluded = without_outliers(data)
    from elastocal.identify.absolute import ABSOLUTE_EFFECTS, has_absolute_positions, split_model
    from elastocal.diagnose.absolute import (
        REGISTRATION_NOTE,
        absolute_unexplained,
        combined_verdict,
        diagnose_absolute,
    )

    ds = data if isinstance(data, StaticDataset) else build_dataset(data)
    absolute = has_absolute_positions(robot, ds)     # absolute effects are tested on absolute positions
    model, absolute_model = split_model(model)
    noise_known = ds.sigma_tracker is not None
    if not noise_known:
        ds = _assumed_noise(robot, ds, model, torque, form)
    work = robot.create_data()        # one computation: its fits share the work buffers
    base = identify_static(robot, ds, model=model, torque=torque, form=form, work=work)
    ds_abs = ds
    ds = base.dataset          # the deflections turned to base axes once: every candidate sees the same data
    pool = ALL_EFFECTS if effects is None else tuple(effects)
    absolute_pool = tuple(e for e in pool if e in ABSOLUTE_EFFECTS or get_effect(e).absolute_shows_more) \
        if absolute else ()
    pool = tuple(e for e in pool if e not in ABSOLUTE_EFFECTS or not absolute)
    skipped_first: list[NotTestable] = []

    def test(fit: StaticFit, added: Sequence[str]) -> list[Candidate]:
        cands, skipped = test_candidates(robot, ds, fit, pool, torque=torque, form=form, noise_known=noise_known,
                                         work=work, progress=progress)
        if not added:
            skipped_first.extend(skipped)
        return cands

    candidates, steps, final, _ = stepwise(base, test)
    excess = excess_p_value(final) if noise_known else None
    floor = final.noise_floor if noise_known else None
    verdict = verdict_of(steps, final.rms, floor, excess) if noise_known else (steps[0].effect if steps else None)
    where = where_it_fails(robot, base, noise=noise_known)
    where_final = where_it_fails(robot, final, noise=noise_known) if final is not base else where
    unexplained, detail = _deflection_unexplained(base, steps, final, floor, excess, where_final, ds)
    abs_diag = None
    if absolute:     # the deflection model's final form against the absolute positions
        if progress is not None:
            progress(0, "the absolute positions", total=1)
        abs_diag = diagnose_absolute(robot, ds_abs, (*final.model, *absolute_model), torque=torque, form=form,
                                     pool=absolute_pool, tracker_prior=tracker_prior)
        verdict = combined_verdict(verdict, len(steps), detail is not None, abs_diag)
        skipped_first += [NotTestable(e, REGISTRATION_NOTE) for e in having("registration", absolute_pool)
                          if e not in absolute_model]
        extra = absolute_unexplained(abs_diag) if noise_known else None
        if extra:
            unexplained = (*unexplained, extra)
    sides = _unexplained_sides(detail, where_final, abs_diag if noise_known else None)
    unexplained = _where_absolute_sits(unexplained, sides)
    return Diagnosis(unexplained_sides=sides, model=(*base.model, *absolute_model), torque=torque, form=form, fit=base,
                     candidates=tuple(candidates),
                     not_testable=tuple(skipped_first), verdict=verdict, final=final, excess_p_value=excess,
                     unexplained=unexplained, where=where, where_final=where_final, noise_known=noise_known,
                     steps=steps, unexplained_detail=detail, outliers=(*excluded, *ds.outliers), absolute=abs_diag)




def _unexplained_sides(detail, where, abs_diag) -> tuple:
    """The sides that stay above their floor (diagnose/unexplained.py), each located
    (diagnose/locate.py): the deflections' excess, then the absolute positions'."""
    from elastocal.diagnose.locate import absolute_readings, deflection_readings, locate, strongest
    from elastocal.diagnose.unexplained import SideUnexplained

    sides = []
    if detail is not None:
        readings = deflection_readings(where)
        sides.append(SideUnexplained("deflections", detail.rms, detail.noise_floor, detail.unit, detail.follows,
                                     tuple((e, s, True) for e, s in detail.explained),
                                     None if readings is None else strongest(locate(readings))))
    if abs_diag is not None and not abs_diag.at_floor:
        f = abs_diag.final
        readings = absolute_readings(f)
        named = bool(abs_diag.named_steps)
        sides.append(SideUnexplained("absolute", f.rms, f.noise_floor, "m", (),
                                     tuple((st.effect, st.explained, named) for st in abs_diag.steps),
                                     None if readings is None else strongest(locate(readings))))
    return tuple(sides)
