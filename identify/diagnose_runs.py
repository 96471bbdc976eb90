"""Diagnose run data: friction terms on the UV/VU half-differences, compensator and
gravity on the joint-2 sweep means, each a likelihood-ratio test with the noise variance
estimated per joint (split out of :mod:`elastocal.identify.diagnose`).

The effects are strategies, as in the static diagnosis: the friction candidates are
the effects whose module declares ``run_part = "uv/vu"`` and a ``run_column`` (the
regression of each joint's half-differences is the sum of the columns of the model's
friction effects), and the sweep candidates are :class:`SweepTest` objects, one per
effect with ``run_part = "sweep"`` (:data:`SWEEP_TESTS`). :func:`diagnose_runs`
takes both as arguments and never branches on an effect's name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, Sequence

import numpy as np
import scipy.sparse
import scipy.stats

from elastocal.errors import InputError, UnidentifiableError
from elastocal.identify.effects import ALL_EFFECTS, get_effect, run_effects
from elastocal.identify.effects.base import Effect
from elastocal.identify.robot import Robot
from elastocal.identify.static import Parameter
from elastocal.identify.verdict import VERDICT_DELTA_BIC, VERDICT_P, NotTestable
from elastocal.identify.where import GroupSummary, _bins


# =================================================================== run data
#: friction effects (each adds its column to the friction regression), then the sweep effects
FRICTION_EFFECTS = run_effects("uv/vu")
SWEEP_EFFECTS = run_effects("sweep")
RUN_EFFECTS = (*FRICTION_EFFECTS, *SWEEP_EFFECTS)
#: a scaled friction design worse conditioned than this cannot separate a term from Coulomb
MAX_FRICTION_CONDITION = 1e4


#: relative singular value below which a gravity combination counts as not excited
GRAVITY_RANK_TOL = 1e-8


@dataclass(frozen=True, eq=False)
class RunCandidate:
    """One missing run-data effect, fitted and tested (likelihood ratio, unknown noise)."""

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

    @property
    def significant(self) -> bool:
        return self.p_value < VERDICT_P and self.delta_bic < VERDICT_DELTA_BIC

    def to_json(self) -> dict:
        return {"effect": self.effect, "rms_after": self.rms_after, "delta_bic": self.delta_bic,
                "p_value": self.p_value, "evidence": self.evidence, "significant": self.significant,
                "part": self.part, "rms_before": self.rms_before, "unit": "N*m", "statistic": self.statistic,
                "dof": self.dof,
                "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in self.parameters},
                "unidentifiable": list(self.unidentifiable), "explanation": self.explanation}


@dataclass(frozen=True, eq=False)
class FrictionView:
    """UV/VU half-differences and what the models make of them (for plots)."""

    measured: np.ndarray      # (n, 6) friction torque -sign(dq_UV) xi (i_UV - i_VU)/2 [N·m]; NaN: joint still
    speed: np.ndarray         # (n, 6) [rad/s]
    load_torque: np.ndarray   # (n, 6) [N·m]
    pair: np.ndarray          # (n,) UV/VU pair index
    pairs: tuple[tuple[str, str], ...]
    before: np.ndarray        # (n, 6) the model's friction
    after: np.ndarray | None  # (n, 6) model + verdict (None without a friction verdict)


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
    candidates: tuple[RunCandidate, ...]
    not_testable: tuple[NotTestable, ...]
    verdict: str | None
    friction: FrictionView | None = field(repr=False)
    sweeps: SweepView | None = field(repr=False)
    #: torque residual rms [N·m] of the model by joint and by UV/VU pair (direction-
    #: dependent part: friction), and of the joint-2 sweep means by q2 and by sweep
    groups: tuple[GroupSummary, ...] = ()

    def to_json(self) -> dict:
        return {"model": list(self.model),
                "where": {g.by: {**g.to_json(), "unit": "N*m"} for g in self.groups},
                "residual": {"rms": self.residual_rms, "max": self.residual_max, "n": self.n, "unit": "N*m"},
                "noise_floor": None,
                "candidates": [c.to_json() for c in self.candidates],
                "verdict": self.verdict,
                "not_testable": [{"effect": n.effect, "reason": n.reason} for n in self.not_testable]}


def _lr(rss0: np.ndarray, rss1: np.ndarray, n: np.ndarray, q: int) -> tuple[float, float, float]:
    """Likelihood ratio of Gaussian fits with unknown variance per group:
    statistic, p (chi-square, q dof) and delta BIC."""
    ok = n > 0
    stat = float(np.sum(n[ok] * np.log(np.maximum(rss0[ok], 1e-300) / np.maximum(rss1[ok], 1e-300))))
    stat = max(stat, 0.0)
    p = float(scipy.stats.chi2.sf(stat, q)) if q else 1.0
    return stat, p, -stat + q * math.log(max(int(n[ok].sum()), 2))


def _friction_columns(speed: np.ndarray, load: np.ndarray, effects: Sequence[Effect]) -> dict[str, np.ndarray]:
    """Each friction effect's column of the regression (its module's ``run_column``)."""
    return {e.name: e.run_column(speed, load) for e in effects}


def _lstsq(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    if x.shape[1] == 0:
        return np.zeros(0), np.zeros((0, 0)), float(y @ y)
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    res = y - x @ beta
    rss = float(res @ res)
    s2 = rss / max(len(y) - x.shape[1], 1)
    return beta, s2 * np.linalg.pinv(x.T @ x), rss


def _scaled_condition(x: np.ndarray) -> float:
    scale = np.linalg.norm(x, axis=0)
    if np.any(scale == 0):
        return float("inf")
    return float(np.linalg.cond(x / scale))


def _diagnose_friction(samples, model: tuple[str, ...], effects: Sequence[Effect]):
    """Candidates among the friction ``effects`` (the first is the constant, Coulomb-like
    one) from matched UV/VU samples."""
    by_name = {e.name: e for e in effects}
    names = tuple(by_name)
    have = [e for e in names if e in model]
    cols_all = _friction_columns(samples.speed, samples.load_torque, effects)
    rss0 = np.zeros(6)
    n = np.zeros(6, dtype=int)
    before = np.full(samples.friction.shape, np.nan)
    for j in range(6):
        ok = np.isfinite(samples.friction[:, j])
        n[j] = int(ok.sum())
        if n[j] == 0:
            continue
        y = samples.friction[ok, j]
        x = np.column_stack([cols_all[e][ok, j] for e in have]) if have else np.zeros((n[j], 0))
        beta, _, rss0[j] = _lstsq(x, y)
        before[ok, j] = x @ beta if have else 0.0
    out: list[tuple[RunCandidate, np.ndarray]] = []
    skipped: list[NotTestable] = []
    for eff_name in names:
        if eff_name in have:
            continue
        eff = by_name[eff_name]
        rss1 = rss0.copy()
        after = before.copy()
        params, unident, tested = [], [], []
        for j in range(6):
            if n[j] == 0:
                continue
            ok = np.isfinite(samples.friction[:, j])
            y = samples.friction[ok, j]
            terms = [*have, eff_name]
            x = np.column_stack([cols_all[e][ok, j] for e in terms])
            check = terms if names[0] in terms else [names[0], *terms]
            xc = np.column_stack([cols_all[e][ok, j] for e in check])
            name = f"{eff.run_prefix}{j + 1}"
            if n[j] <= len(check) + 1 or _scaled_condition(xc) > MAX_FRICTION_CONDITION:
                unident.append(name)
                continue
            beta, cov, rss1[j] = _lstsq(x, y)
            after[ok, j] = x @ beta
            params.append(Parameter(name, float(beta[-1]), float(np.sqrt(max(cov[-1, -1], 0.0))),
                                    eff.units[0]))
            tested.append(j)
        if not tested:
            skipped.append(NotTestable(eff_name, f"these runs cannot separate it from Coulomb friction; "
                                                 f"it needs {eff.run_needs}"))
            continue
        idx = np.array(tested)
        stat, p, dbic = _lr(rss0[idx], rss1[idx], n[idx], len(idx))
        before_rms = float(np.sqrt(rss0[idx].sum() / n[idx].sum()))
        after_rms = float(np.sqrt(rss1[idx].sum() / n[idx].sum()))
        strongest_p = max(params, key=lambda p_: abs(p_.value) / p_.std if p_.std > 0 else 0.0)
        unit = "" if strongest_p.unit == "1" else f" {strongest_p.unit}"
        evidence = (f"{eff.evidence} (joint {strongest_p.name[2:]}: {strongest_p.name} = "
                    f"{strongest_p.value:.3g}{unit})")
        out.append((RunCandidate(eff_name, "uv/vu", eff.explanation, evidence, before_rms, after_rms, dbic, p, stat,
                                 len(idx), tuple(params), tuple(unident)), after))
    return out, skipped, before, rss0, n


def _gravity_regressor2(robot: Robot, theta: np.ndarray) -> np.ndarray:
    """Joint-2 rows of Pinocchio's joint-torque regressor at rest (g2 = Y2 pi)."""
    import pinocchio as pin

    model = robot.model
    data = model.createData()
    zero = np.zeros(model.nv)
    return np.array([pin.computeJointTorqueRegressor(model, data, th, zero, zero)[1].copy() for th in theta])


@dataclass(frozen=True, eq=False)
class SweepData:
    """Joint-2 sweep means and the torque the model leaves (``y`` = -M(q2) - gravity error)."""

    robot: Robot
    means: object                 # identify.compensator.SweepMeans
    y: np.ndarray                 # (n,) [N·m]
    theta: np.ndarray             # (n, 6) deflected link-side configurations


class SweepTest(Protocol):
    """A sweep effect as a strategy of the run diagnosis (pysindy style)."""

    effect: str

    def model_torque(self, data: SweepData, in_model: bool) -> np.ndarray:
        """What the effect adds to ``y`` in the model (in it: fitted; else its nominal part)."""

    def test(self, data: SweepData, r0: np.ndarray) -> tuple[RunCandidate, np.ndarray] | NotTestable:
        """The effect fitted to the model's residual ``r0``: candidate and new residual, or why not."""

    def refusal(self, data: SweepData) -> NotTestable | None:
        """Why these data cannot hold the effect at all, whether or not the model has it."""


class CompensatorSweepTest:
    """The compensator's geometry (identify/compensator.py) on the sweep means."""

    effect = "compensator"

    def model_torque(self, data: SweepData, in_model: bool) -> np.ndarray:
        from elastocal.identify.compensator import identify_compensator

        spec = data.robot.compensator
        nominal = spec.nominal_parameters() if spec is not None else None
        if spec is not None and in_model:
            return spec.torque(data.means.q2, identify_compensator(data.robot, data.means, gravity="model").values)
        if spec is not None and nominal is not None:
            return spec.torque(data.means.q2, nominal)
        return np.zeros_like(data.y)

    def refusal(self, data: SweepData) -> NotTestable | None:
        if data.robot.compensator is None:
            return NotTestable("compensator", "the robot description has no [compensator]")
        return None

    def test(self, data: SweepData, r0: np.ndarray) -> tuple[RunCandidate, np.ndarray] | NotTestable:
        from elastocal.identify.compensator import identify_compensator

        spec = data.robot.compensator
        try:
            fit = identify_compensator(data.robot, data.means, gravity="model")
        except (InputError, UnidentifiableError) as exc:
            return NotTestable("compensator", str(exc))
        n = np.array([len(r0)])
        rss0 = float(r0 @ r0)
        r1 = fit.residuals
        stat, p, dbic = _lr(np.array([rss0]), np.array([float(r1 @ r1)]), n, 2)
        params = tuple(Parameter(nm, float(v), float(s), u)
                       for nm, v, s, u in zip(fit.names, fit.values, fit.std, fit.units))
        base = ("the robot description's nominal values" if spec.nominal_parameters() is not None
                else "no compensator")
        eff = get_effect("compensator")
        evidence = (f"{eff.evidence}: {', '.join(f'{p_.name} = {p_.value:.4g} {p_.unit}' for p_ in params)} "
                    f"instead of {base}")
        return (RunCandidate("compensator", "sweep", eff.explanation, evidence,
                             float(np.sqrt(rss0 / n[0])), fit.rms, dbic, p, stat, 2, params, ()), r1)


class GravitySweepTest:
    """Corrections to the links' mass moments: Pinocchio's joint-2 regressor rows."""

    effect = "gravity"

    def model_torque(self, data: SweepData, in_model: bool) -> np.ndarray:
        return np.zeros_like(data.y)      # the description's masses are always in the torque model

    def refusal(self, data: SweepData) -> NotTestable | None:
        return None

    def test(self, data: SweepData, r0: np.ndarray) -> tuple[RunCandidate, np.ndarray] | NotTestable:
        if not data.robot.has_masses:
            return NotTestable("gravity", "the robot description gives no link masses to correct")
        n = np.array([len(r0)])
        rss0 = float(r0 @ r0)
        reg = _gravity_regressor2(data.robot, data.theta)
        scale = np.linalg.norm(reg, axis=0)
        used = scale > 0
        _, s, vt = np.linalg.svd(reg[:, used], full_matrices=False)
        rank = int(np.sum(s > GRAVITY_RANK_TOL * s[0])) if s.size and s[0] > 0 else 0
        if rank == 0 or len(r0) <= rank + 1:
            return NotTestable("gravity", "the sweeps excite no gravity parameter")
        phi = reg[:, used] @ vt[:rank].T
        beta, cov, rss1 = _lstsq(phi, r0)
        r1 = r0 - phi @ beta
        stat, p, dbic = _lr(np.array([rss0]), np.array([rss1]), n, rank)
        eff = get_effect("gravity")
        params = tuple(Parameter(f"g{k + 1}", float(b), float(np.sqrt(max(cov[k, k], 0.0))), "N*m")
                       for k, b in enumerate(beta))
        return (RunCandidate("gravity", "sweep", eff.explanation,
                             f"{eff.evidence} ({rank} mass-moment combinations the sweeps excite)",
                             float(np.sqrt(rss0 / n[0])), float(np.sqrt(rss1 / n[0])), dbic, p, stat, rank,
                             params, ()), r1)


#: the sweep strategies of the effect table, in its order (one per effect with run_part "sweep")
SWEEP_TESTS: tuple[SweepTest, ...] = (CompensatorSweepTest(), GravitySweepTest())


def _diagnose_sweeps(robot: Robot, table, model: tuple[str, ...], stiffness: np.ndarray,
                     tests: Sequence[SweepTest] = SWEEP_TESTS):
    """Candidates among the sweep ``tests`` from joint-2 sweep means."""
    from elastocal.identify.compensator import sweep_means

    sub = table.subset(np.isin(table.direction, ("+", "-")))
    means = sweep_means(robot, sub.q, sub.currents, sub.direction, sub.load, sub.wrench, stiffness=stiffness,
                        source=table.source)
    theta = means.theta
    ext = np.array([(robot.jacobians(th, ["load_point"])[0].T @ w)[1] if np.any(w) else 0.0
                    for th, w in zip(theta, means.wrench)])
    g2 = np.array([robot.gravity_torque(th)[1] for th in theta])
    y = means.torque - ext + g2                       # = -M(q2) - (gravity error)
    data = SweepData(robot=robot, means=means, y=y, theta=theta)
    m_model = np.zeros_like(y)
    for t in tests:
        m_model = m_model + t.model_torque(data, t.effect in model)
    r0 = y + m_model
    candidates: list[tuple[RunCandidate, np.ndarray]] = []
    skipped: list[NotTestable] = []
    for t in tests:
        refused = t.refusal(data)
        if refused is not None:
            skipped.append(refused)
            continue
        if t.effect in model:
            continue
        found = t.test(data, r0)
        if isinstance(found, NotTestable):
            skipped.append(found)
        else:
            candidates.append(found)
    return candidates, skipped, means, r0


def diagnose_runs(robot: Robot, table, *, model: Sequence[str] = ("joint_stiffness",),
                  stiffness: Sequence[float] | None = None, friction_effects: Sequence[Effect] | None = None,
                  sweep_tests: Sequence[SweepTest] = SWEEP_TESTS) -> RunDiagnosis:
    """Test the run-data effects the model lacks: friction terms on the UV/VU
    half-differences (identify/friction.py matching), the compensator and the
    gravity on the joint-2 sweep means (identify/compensator.py).

    The noise level of run torques is unknown (no repeats): each test is a
    likelihood ratio of Gaussian fits with the variance estimated per joint,
    chi-square with one degree of freedom per tested joint (friction) or per
    parameter (sweeps); delta_bic = -LR + q ln n.

    ``stiffness`` (k1..k6 [N·m/rad], from a static fit) puts the sweeps at the
    deflected configuration; the joint-2 torque there differs from the
    commanded one by more than the current noise, so without it the sweep
    effects are not tested (they would absorb the deflection).

    ``friction_effects`` (default: the table's "uv/vu" effects, the constant one first)
    and ``sweep_tests`` (default :data:`SWEEP_TESTS`) are the candidates' strategies.
    """
    from elastocal.identify.friction import friction_samples

    model = tuple(dict.fromkeys(["joint_stiffness", *model]))
    for name in model:
        get_effect(name)
    friction_effects = tuple(get_effect(e) for e in FRICTION_EFFECTS) if friction_effects is None \
        else tuple(friction_effects)
    sweep_tests = tuple(sweep_tests)
    tested_here = {e.name for e in friction_effects} | {t.effect for t in sweep_tests}
    candidates: list[tuple[RunCandidate, object]] = []
    skipped: list[NotTestable] = []
    friction_view = None
    sweep_view = None
    pieces_rss, pieces_n, pieces_max = 0.0, 0, 0.0
    uvvu = np.isin(table.direction, ("UV", "VU"))
    friction_out = None
    if np.any(uvvu):
        sub = table.subset(uvvu)
        samples = friction_samples(sub.q, sub.dq, sub.currents, sub.run, sub.direction, sub.load,
                                   robot.torque_constants, t=sub.t, source=table.source)
        found, skip, before, rss0, n = _diagnose_friction(samples, model, friction_effects)
        candidates += found
        skipped += skip
        friction_out = (samples, before)
        pieces_rss += float(rss0.sum())
        pieces_n += int(n.sum())
        resid = samples.friction - before
        if np.any(np.isfinite(resid)):
            pieces_max = max(pieces_max, float(np.nanmax(np.abs(resid))))
    else:
        for eff in friction_effects:
            if eff.name not in model:
                skipped.append(NotTestable(eff.name, "the runs hold no UV/VU pairs (the same path forward and "
                                                     "backward)"))
    sweep_out = None
    has_sweeps = bool(np.any(np.isin(table.direction, ("+", "-"))))
    if has_sweeps and stiffness is None:
        for t in sweep_tests:
            if t.effect not in model:
                skipped.append(NotTestable(t.effect, "the sweep torques need the joint stiffness to place the arm "
                                                     "at its deflected configuration: give the static table too"))
    elif has_sweeps:
        found, skip, means, r0 = _diagnose_sweeps(robot, table, model, np.asarray(stiffness, dtype=float),
                                                  sweep_tests)
        candidates += found
        skipped += skip
        sweep_out = (means, r0)
        pieces_rss += float(r0 @ r0)
        pieces_n += len(r0)
        pieces_max = max(pieces_max, float(np.max(np.abs(r0))) if len(r0) else 0.0)
    else:
        for t in sweep_tests:
            if t.effect not in model:
                skipped.append(NotTestable(t.effect, "the runs hold no joint-2 sweep (direction + and -)"))
    for name in ALL_EFFECTS:
        if name in model or name in RUN_EFFECTS or name in tested_here:
            continue
        eff = get_effect(name)
        if "runs" in eff.seen_in:
            skipped.append(NotTestable(name, "the run diagnosis tests torque effects; "
                                             "test it on a static table"))
    candidates.sort(key=lambda c: (c[0].delta_bic, c[0].rms_after))
    verdict = candidates[0][0].effect if candidates and candidates[0][0].significant else None
    if friction_out is not None:
        samples, before = friction_out
        after = None
        if verdict in {e.name for e in friction_effects}:
            after = candidates[0][1]
        friction_view = FrictionView(samples.friction, samples.speed, samples.load_torque, samples.pair,
                                     samples.pairs, before, after)
    if sweep_out is not None:
        means, r0 = sweep_out
        after = candidates[0][1] if verdict in {t.effect for t in sweep_tests} else None
        sweep_view = SweepView(means.q2, means.sweep, r0, after)
    rms = float(np.sqrt(pieces_rss / pieces_n)) if pieces_n else None
    return RunDiagnosis(model=model, n=pieces_n, residual_rms=rms, residual_max=pieces_max if pieces_n else None,
                        candidates=tuple(c for c, _ in candidates), not_testable=tuple(skipped), verdict=verdict,
                        friction=friction_view, sweeps=sweep_view, groups=_run_groups(friction_view, sweep_view))


def _run_groups(friction: FrictionView | None, sweeps: SweepView | None) -> tuple[GroupSummary, ...]:
    def summary(by: str, index: np.ndarray, values: np.ndarray, labels: Sequence[str]) -> GroupSummary:
        g = len(labels)
        n = np.bincount(index, minlength=g)
        ss = np.bincount(index, weights=values**2, minlength=g)
        return GroupSummary(by, tuple(labels), np.sqrt(ss / np.maximum(n, 1)), None, n)

    out = []
    if friction is not None:
        resid = friction.measured - friction.before
        moving = np.isfinite(resid)
        joint = np.nonzero(moving)[1]
        out.append(summary("joint", joint, resid[moving], [f"j{j + 1}" for j in range(6)]))
        pair = np.broadcast_to(friction.pair[:, None], resid.shape)[moving]
        out.append(summary("uv/vu pair", pair, resid[moving], [f"{u}/{v}" for u, v in friction.pairs]))
    if sweeps is not None and len(sweeps.q2):
        idx, labels = _bins(sweeps.q2, 6, "rad", ".2f")
        out.append(summary("sweep q2", idx, sweeps.residual_before, labels))
        ids = np.unique(sweeps.sweep)
        out.append(summary("sweep", np.searchsorted(ids, sweeps.sweep), sweeps.residual_before,
                           [f"sweep {k + 1}" for k in range(len(ids))]))
    return tuple(out)
