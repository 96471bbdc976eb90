"""Diagnose run data stepwise, against their noise floor (docs/cli.md, ``diagnose --json``).

The run model (identify/runmodel.py) is fitted to the friction half-differences
of every forward/backward pair (UV/VU runs and ``+``/``-`` sweeps) and to the
joint-2 sweep means. Every run effect the model lacks is a candidate, fitted
with the model and tested by a likelihood ratio of Gaussian fits with the
variance estimated per part (each joint's half-differences, the sweep means):
chi-square with one degree of freedom per added parameter, ``delta_bic = -LR +
q ln n``, significant when p < 0.01 and delta_bic < -10 (the rule of
diagnose/verdict.py). As for static data the diagnosis is stepwise
(diagnose/stepwise.py): the best significant, plausible candidate is added and
the rest tested again, until none is; the verdict is the first step only when
the final model sits at the noise floor of the runs (current repeatability
through the half-differences and sweep means), otherwise it is None and
``unexplained`` says what remains.

The candidates are strategies: the friction effects are those whose module
declares ``run_part = "uv/vu"`` and a ``run_column``, the sweep effects those
with ``run_part = "sweep"`` and a ``sweep_term``. :func:`diagnose_runs` takes
both as arguments and never branches on an effect's name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.stats

from elastocal.errors import UnidentifiableError
from elastocal.model.effects import ALL_EFFECTS, get_effect, run_effects
from elastocal.model.effects.base import Effect
from elastocal.identify.runmodel import (
    REFERENCE_STIFFNESS,
    RunData,
    RunModelFit,
    StiffnessUsed,
    fit_run_model,
    prepare_run_data,
    with_rigid_bias,
)
from elastocal.identify.static import Parameter
from elastocal.diagnose.stepwise import EXCESS_P, Step, Unexplained, stepwise, unexplained_of, verdict_of
from elastocal.diagnose.verdict import VERDICT_DELTA_BIC, VERDICT_P, NotTestable
from elastocal.diagnose.where import GroupSummary, _bins

#: friction effects (each adds its column to the friction regression), then the sweep effects
FRICTION_EFFECTS = run_effects("uv/vu")
SWEEP_EFFECTS = run_effects("sweep")
RUN_EFFECTS = (*FRICTION_EFFECTS, *SWEEP_EFFECTS)
#: a feature the excess follows is reported below this p (rank correlation)
FEATURE_P = 1e-3
#: at most this many features the excess follows are listed (most significant first)
MAX_FOLLOWS = 4
#: rigid model: a sweep effect whose values differ from the description's by no more than
#: this many times the rigid model's bias (at REFERENCE_STIFFNESS) is not a finding: the
#: neglected deflection of a robot down to a third of that stiffness would explain it
RIGID_BIAS_FACTOR = 3.0


@dataclass(frozen=True, eq=False)
class RunCandidate:
    """One missing run-data effect, fitted with the model and tested (likelihood ratio, unknown noise)."""

    effect: str
    part: str                 # "uv/vu" (friction half-differences) or "sweep" (joint-2 sweep means)
    explanation: str
    evidence: str
    rms_before: float         # [N·m] of the part's torques
    rms_after: float
    delta_bic: float
    p_value: float
    statistic: float          # likelihood-ratio chi-square
    dof: int
    parameters: tuple[Parameter, ...]
    unidentifiable: tuple[str, ...]
    fit: RunModelFit | None = field(default=None, repr=False)   # the model with the candidate
    implausible: str | None = None

    @property
    def significant(self) -> bool:
        return self.p_value < VERDICT_P and self.delta_bic < VERDICT_DELTA_BIC

    @property
    def noise_floor_after(self) -> float | None:
        return None if self.fit is None else self.fit.noise_floor

    def to_json(self) -> dict:
        return {"effect": self.effect, "rms_after": self.rms_after, "delta_bic": self.delta_bic,
                "p_value": self.p_value, "evidence": self.evidence, "significant": self.significant,
                "part": self.part, "rms_before": self.rms_before, "unit": "N*m", "statistic": self.statistic,
                "dof": self.dof, "noise_floor_after": self.noise_floor_after,
                "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in self.parameters},
                "unidentifiable": list(self.unidentifiable), "explanation": self.explanation,
                **({"implausible": self.implausible} if self.implausible else {})}


@dataclass(frozen=True, eq=False)
class FrictionView:
    """Half-differences of the forward/backward pairs and what the models make of them (for plots)."""

    measured: np.ndarray      # (n, 6) friction torque sign(dq_fwd) xi (i_fwd - i_bwd)/2 [N·m]; NaN: joint still
    speed: np.ndarray         # (n, 6) [rad/s]
    load_torque: np.ndarray   # (n, 6) [N·m]
    pair: np.ndarray          # (n,) pair index
    pairs: tuple[tuple[str, str], ...]
    before: np.ndarray        # (n, 6) the model's friction
    after: np.ndarray | None  # (n, 6) the final model's (None when no step is a friction effect)


@dataclass(frozen=True, eq=False)
class SweepView:
    """Joint-2 sweep means and the model's residual (for plots)."""

    q2: np.ndarray            # (n,) [rad]
    sweep: np.ndarray         # (n,)
    residual_before: np.ndarray   # (n,) [N·m]
    residual_after: np.ndarray | None


@dataclass(frozen=True, eq=False)
class RunDiagnosis:
    """What ``elastocal diagnose`` finds in run data."""

    model: tuple[str, ...]
    n: int                          # torque samples tested (moving joint samples + sweep means)
    residual_rms: float | None      # [N·m] of the model over the tested parts
    residual_max: float | None
    candidates: tuple[RunCandidate, ...]   # tested against the model as given, best first
    not_testable: tuple[NotTestable, ...]
    verdict: str | None
    friction: FrictionView | None = field(repr=False)
    sweeps: SweepView | None = field(repr=False)
    #: torque residual rms [N·m] of the model by joint and by forward/backward pair
    #: (friction), and of the joint-2 sweep means by q2 and by sweep, with the noise floor of each
    groups: tuple[GroupSummary, ...] = ()
    base: RunModelFit | None = field(default=None, repr=False)
    final: RunModelFit | None = field(default=None, repr=False)
    steps: tuple[Step, ...] = ()
    unexplained: tuple[str, ...] = ()
    unexplained_detail: Unexplained | None = None
    stiffness: StiffnessUsed | None = None
    current_noise: np.ndarray | None = None     # (6,) [A]

    @property
    def noise_floor(self) -> float | None:
        return None if self.base is None else self.base.noise_floor

    @property
    def excess_p_value(self) -> float | None:
        return None if self.final is None else self.final.excess_p

    def to_json(self) -> dict:
        final = self.final
        return {"model": list(self.model),
                "where": {g.by: {**g.to_json(), "unit": "N*m"} for g in self.groups},
                "residual": {"rms": self.residual_rms, "max": self.residual_max, "n": self.n, "unit": "N*m"},
                "noise_floor": self.noise_floor,
                "candidates": [c.to_json() for c in self.candidates],
                "verdict": self.verdict,
                "not_testable": [{"effect": n.effect, "reason": n.reason} for n in self.not_testable],
                "steps": [{"effect": st.effect,
                           "residual": {"rms": st.rms_after, "max": st.candidate.fit.max, "n": st.candidate.fit.n,
                                        "unit": "N*m"},
                           "noise_floor": st.noise_floor_after, "delta_bic": st.candidate.delta_bic,
                           "p_value": st.candidate.p_value,
                           "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit}
                                          for p in st.candidate.parameters}} for st in self.steps],
                "final": None if final is None else {**final.to_json(), "model": list(
                    dict.fromkeys((*self.model, *(st.effect for st in self.steps))))},
                "unexplained": None if self.unexplained_detail is None else {
                    **self.unexplained_detail.to_json(), "sentences": list(self.unexplained)},
                "current_noise": None if self.current_noise is None else {
                    "values": [None if not np.isfinite(s) else float(s) for s in self.current_noise], "unit": "A"},
                "stiffness": None if self.stiffness is None else self.stiffness.to_json()}


def _lr(rss0: np.ndarray, rss1: np.ndarray, n: np.ndarray, q: int) -> tuple[float, float, float]:
    """Likelihood ratio of Gaussian fits with unknown variance per group:
    statistic, p (chi-square, q dof) and delta BIC."""
    ok = n > 0
    stat = float(np.sum(n[ok] * np.log(np.maximum(rss0[ok], 1e-300) / np.maximum(rss1[ok], 1e-300))))
    stat = max(stat, 0.0)
    p = float(scipy.stats.chi2.sf(stat, q)) if q else 1.0
    return stat, p, -stat + q * math.log(max(int(n[ok].sum()), 2))


def _evidence(eff: Effect, params: Sequence[Parameter], nominal: bool | None) -> str:
    if not params:
        return eff.evidence
    if eff.run_part == "uv/vu":
        best = max(params, key=lambda p_: abs(p_.value) / p_.std if p_.std > 0 else 0.0)
        unit = "" if best.unit == "1" else f" {best.unit}"
        return f"{eff.evidence} (joint {best.name[2:]}: {best.name} = {best.value:.3g}{unit})"
    if len(params) > 3:
        return f"{eff.evidence} ({len(params)} parameters the sweeps excite)"
    base = "the robot description's nominal values" if nominal else "none in the model"
    return f"{eff.evidence}: {', '.join(f'{p.name} = {p.value:.4g} {p.unit}' for p in params)} instead of {base}"


def _implausible(eff: Effect, params: Sequence[Parameter]) -> str | None:
    if eff.plausibility is None or not params:
        return None
    return eff.plausibility(tuple(p.name for p in params), np.array([p.value for p in params]),
                            np.array([p.std for p in params]))


def _within_rigid_bias(data: RunData, eff: Effect, params: Sequence[Parameter]) -> str | None:
    """Why a sweep candidate's change from the description's values is no finding with the rigid model."""
    term = data.sweep_terms.get(eff.name)
    bias = dict(data.stiffness.bias_parameters)
    if data.stiffness.source != "rigid" or term is None or term.nominal is None or not bias:
        return None
    shifts = []
    for p, nom in zip(params, term.nominal):
        if p.name not in bias or nom == 0.0:
            return None
        rel = (p.value - nom) / nom
        if abs(rel) > RIGID_BIAS_FACTOR * abs(bias[p.name]):
            return None
        shifts.append(f"{p.name} {100 * rel:+.2g} %")
    words = ", ".join(f"{n} {100 * v:+.2g} %" for n, v in data.stiffness.bias_parameters)
    return (f"its change from the description's values ({', '.join(shifts)}) is within {RIGID_BIAS_FACTOR:g}x the "
            f"rigid model's bias ({words} at {REFERENCE_STIFFNESS:.0e} N*m/rad): give robot.toml the joint "
            "stiffness or a static table")


def _test_one(data: RunData, fit: RunModelFit, model_effects: Sequence[Effect], eff: Effect,
              constant: Effect) -> RunCandidate | NotTestable:
    """The candidate ``eff`` fitted with the model of ``fit`` and tested against it."""
    if eff.run_part == "uv/vu":
        if data.friction is None:
            return NotTestable(eff.name, "the runs hold no UV/VU pair or +/- sweep (the same path forward and "
                                         "backward)")
    elif data.sweeps is None:
        return NotTestable(eff.name, f"the runs hold no joint-{data.robot.sweep_joint} sweep (direction + and -)")
    elif eff.name in data.sweep_refused:
        return NotTestable(eff.name, data.sweep_refused[eff.name])
    try:
        aug = fit_run_model(data, (*model_effects, eff), constant=constant)
    except UnidentifiableError as exc:
        return NotTestable(eff.name, str(exc))
    if eff.run_part == "uv/vu":
        tested = np.append(aug.friction_columns[eff.name], False)
        q = int(tested.sum())
        if q == 0:
            return NotTestable(eff.name, f"these runs cannot separate it from {constant.name}; it needs "
                                         f"{eff.run_needs}")
        unident = tuple(u for u in aug.unidentifiable if u.startswith(eff.run_prefix)
                        and u not in fit.unidentifiable)
        nominal = None
    else:
        tested = np.append(np.zeros(len(fit.friction_rss), dtype=bool), True)
        q = len(data.sweep_terms[eff.name].names)
        unident = ()
        nominal = data.sweep_terms[eff.name].nominal is not None
    rss0, rss1, n = fit.group_rss(), aug.group_rss(), aug.group_n()
    stat, p, dbic = _lr(rss0[tested], rss1[tested], n[tested], q)
    before = {x.name for x in fit.parameters}
    params = tuple(pm for pm in aug.parameters if pm.name not in before)
    part = eff.run_part
    rb = math.sqrt(rss0[tested].sum() / max(n[tested].sum(), 1))
    ra = math.sqrt(rss1[tested].sum() / max(n[tested].sum(), 1))
    implausible = _implausible(eff, params) or (_within_rigid_bias(data, eff, params) if part == "sweep" else None)
    return RunCandidate(eff.name, part, eff.explanation, _evidence(eff, params, nominal), rb, ra, dbic, p, stat, q,
                        params, unident, fit=aug, implausible=implausible)


def _run_structure(data: RunData, fit: RunModelFit) -> tuple[str, ...]:
    """What the excess of the final model's residual over the noise follows: sentences."""
    found: list[tuple[float, str]] = []
    joints: list[tuple[float, int]] = []      # (residual / noise, joint) of the joints above their noise
    if data.friction is not None and data.friction_var is not None and fit.friction_residual is not None:
        r, var, s = fit.friction_residual, data.friction_var, data.friction
        for j in range(r.shape[1]):
            ok = np.isfinite(r[:, j]) & np.isfinite(var[:, j])
            dof = fit.friction_n[j] - fit.friction_p[j]
            if ok.sum() < 5 or dof <= 0:
                continue
            chi2 = float(np.sum(r[ok, j] ** 2 / var[ok, j]))
            p = float(scipy.stats.chi2.sf(chi2, dof))
            if p >= FEATURE_P:
                continue
            joints.append((math.sqrt(chi2 / dof), j + 1))
            ratio_i = r[ok, j] ** 2 / var[ok, j]
            for name, values in (("speed", s.speed[ok, j]), ("the load torque", np.abs(s.load_torque[ok, j]))):
                if np.ptp(values) == 0.0:
                    continue
                rho, pr = scipy.stats.spearmanr(values, ratio_i)
                if np.isfinite(pr) and pr < FEATURE_P:
                    found.append((pr, f"it {'grows' if rho > 0 else 'falls'} with {name} on joint {j + 1} "
                                      f"(rank correlation {rho:+.2f} over {int(ok.sum())} samples)"))
            if s.q is not None and np.ptp(s.q[ok, j]) > 0.0:     # any pattern in the angle, not only a trend
                idx, labels = _bins(s.q[ok, j], 6, "m" if data.robot.prismatic[j] else "rad", ".2f")
                groups = [r[ok, j][idx == b] for b in range(len(labels))]
                if len(groups) > 1 and all(len(g) > 1 for g in groups):
                    _, pk = scipy.stats.kruskal(*groups)
                    if np.isfinite(pk) and pk < FEATURE_P:
                        found.append((pk, f"it follows the angle of joint {j + 1} (the residual changes "
                                          f"across q{j + 1}, Kruskal-Wallis p {pk:.1g})"))
    if fit.sweep is not None and data.sweep_var is not None and fit.sweep_n:
        dof = fit.sweep_n - fit.sweep.n_parameters
        if dof > 0:
            p = float(scipy.stats.chi2.sf(fit.sweep_chi2, dof))
            if p < FEATURE_P:
                j = data.sweeps.joint + 1
                found.append((0.0, f"joint-{j} sweep means stay {math.sqrt(fit.sweep_chi2 / dof):.1f}x their noise "
                                 f"(they follow q{j}: see where['sweep q2'], the swept joint's angle)"))
    found.sort(key=lambda x: x[0])
    head = ()
    if joints:
        joints.sort(reverse=True)
        head = ("friction residual above its noise on joint" + ("s " if len(joints) > 1 else " ")
                + ", ".join(f"{j} ({r:.1f}x)" for r, j in joints),)
    return (*head, *(text for _, text in found[:MAX_FOLLOWS]))


def diagnose_runs(robot, table, *, model: Sequence[str] = ("joint_stiffness",),
                  stiffness: Sequence[float] | None = None, friction_effects: Sequence[Effect] | None = None,
                  sweep_effects: Sequence[Effect] | None = None) -> RunDiagnosis:
    """Test the run-data effects the model lacks, stepwise, against the runs' noise floor.

    ``stiffness`` (k1..kN [N·m/rad, N/m], from a static fit) puts the sweeps at the deflected
    configuration; without it robot.toml's nominal stiffness, else the rigid model with its
    bias stated (identify/runmodel.py). ``friction_effects`` (default: the table's "uv/vu"
    effects, the constant one first) and ``sweep_effects`` (default: the "sweep" effects)
    are the candidates' strategies; effects of ``model`` outside them are fitted with the model.
    """
    model = tuple(dict.fromkeys(["joint_stiffness", *model]))
    model_effects_all = [get_effect(name, robot) for name in model]
    friction_effects = tuple(get_effect(e, robot) for e in FRICTION_EFFECTS) if friction_effects is None \
        else tuple(friction_effects)
    sweep_effects = tuple(get_effect(e, robot) for e in SWEEP_EFFECTS) if sweep_effects is None \
        else tuple(sweep_effects)
    constant = friction_effects[0] if friction_effects else get_effect(FRICTION_EFFECTS[0], robot)
    pool = (*friction_effects, *sweep_effects)
    in_model = [e for e in model_effects_all if e.run_part is not None]
    by_name = {e.name: e for e in (*pool, *in_model)}
    sweep_all = tuple(dict.fromkeys([e for e in (*in_model, *sweep_effects) if e.run_part == "sweep"]))
    data = prepare_run_data(robot, table, stiffness=stiffness, sweep_effects=sweep_all)
    # the bias of the nonlinear sweep candidates (their physical parameters), fitted with the model's
    data = with_rigid_bias(data, table, sweep_all, [e.name for e in sweep_all if e.name in model or (
        e.name in data.sweep_terms and not data.sweep_terms[e.name].linear)])
    base = fit_run_model(data, in_model, constant=constant)
    first_skipped: list[NotTestable] = []

    def test(fit: RunModelFit, added: Sequence[str]) -> list[RunCandidate]:
        effects = [*in_model, *(by_name[a] for a in added)]
        out: list[RunCandidate] = []
        for eff in pool:
            if eff.name in fit.model or eff.name in model:
                continue
            found = _test_one(data, fit, effects, eff, constant)
            if isinstance(found, NotTestable):
                if not added:
                    first_skipped.append(found)
            else:
                out.append(found)
        out.sort(key=lambda c: (c.delta_bic, c.rms_after))
        return out

    candidates, steps, final, _ = stepwise(base, test)
    floor = final.noise_floor
    verdict = verdict_of(steps, final.rms, floor, final.excess_p)
    unexplained: tuple[str, ...] = ()
    detail = None
    if final.excess_p is not None and final.excess_p < EXCESS_P:
        unexplained = _run_structure(data, final)
        detail = unexplained_of(base.rms, steps, final.rms, floor, final.excess_p, unexplained, unit="N*m")
        if detail is not None and not unexplained:
            unexplained = (f"residual stays {detail.ratio:.2f}x the noise floor with no pattern in joint, speed, "
                           "load torque or position",)
            detail = Unexplained(detail.rms, detail.noise_floor, detail.unit, unexplained, detail.explained)
    skipped = list(first_skipped)
    tested_here = {e.name for e in pool}
    for name in ALL_EFFECTS:
        if name in model or name in RUN_EFFECTS or name in tested_here:
            continue
        if "runs" in get_effect(name).seen_in:
            skipped.append(NotTestable(name, "the run diagnosis tests torque effects; test it on a static table"))
    step_names = {st.effect for st in steps}
    friction_view = sweep_view = None
    if data.friction is not None:
        s = data.friction
        after = final.friction_pred if any(by_name[e].run_part == "uv/vu" for e in step_names) else None
        friction_view = FrictionView(s.friction, s.speed, s.load_torque, s.pair, s.pairs,
                                     np.where(np.isfinite(s.friction), base.friction_pred, np.nan), after)
    if data.sweeps is not None and base.sweep is not None:
        after = final.sweep.residuals if any(by_name[e].run_part == "sweep" for e in step_names) else None
        sweep_view = SweepView(data.sweeps.q2, data.sweeps.sweep, base.sweep.residuals, after)
    n = base.n
    return RunDiagnosis(model=model, n=n, residual_rms=base.rms if n else None, residual_max=base.max if n else None,
                        candidates=tuple(candidates), not_testable=tuple(skipped), verdict=verdict,
                        friction=friction_view, sweeps=sweep_view, groups=_run_groups(data, base), base=base,
                        final=final, steps=steps, unexplained=unexplained, unexplained_detail=detail,
                        stiffness=data.stiffness if data.sweeps is not None else None,
                        current_noise=data.current_noise)


def _run_groups(data: RunData, fit: RunModelFit) -> tuple[GroupSummary, ...]:
    """Residual rms (and what noise alone leaves) by joint, pair, q2 and sweep."""
    def summary(by: str, index: np.ndarray, values: np.ndarray, var: np.ndarray | None,
                labels: Sequence[str]) -> GroupSummary:
        g = len(labels)
        n = np.bincount(index, minlength=g)
        ss = np.bincount(index, weights=values ** 2, minlength=g)
        floor = None
        if var is not None and np.all(np.isfinite(var)):
            floor = np.sqrt(np.bincount(index, weights=var, minlength=g) / np.maximum(n, 1))
        return GroupSummary(by, tuple(labels), np.sqrt(ss / np.maximum(n, 1)), floor, n)

    out = []
    if data.friction is not None and fit.friction_residual is not None:
        resid = fit.friction_residual
        moving = np.isfinite(resid)
        var = data.friction_var[moving] if data.friction_var is not None else None
        joint = np.nonzero(moving)[1]
        out.append(summary("joint", joint, resid[moving], var, [f"j{j + 1}" for j in range(resid.shape[1])]))
        pair = np.broadcast_to(data.friction.pair[:, None], resid.shape)[moving]
        out.append(summary("uv/vu pair", pair, resid[moving], var, [f"{u}/{v}" for u, v in data.friction.pairs]))
    if fit.sweep is not None and len(fit.sweep.residuals):
        r = fit.sweep.residuals
        idx, labels = _bins(data.sweeps.q2, 6, "rad", ".2f")
        out.append(summary("sweep q2", idx, r, data.sweep_var, labels))
        ids = np.unique(data.sweeps.sweep)
        out.append(summary("sweep", np.searchsorted(ids, data.sweeps.sweep), r, data.sweep_var,
                           [f"sweep {k + 1}" for k in range(len(ids))]))
    return tuple(out)
