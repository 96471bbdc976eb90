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
  number of deflection components); negative favours the effect.

Without repeated readings the noise level is unknown: the tests then assume
the structure of tracker noise (deflections of one marker share the reference
reading) at the level that makes the model's own residual what noise leaves,
which keeps the false-alarm rate near its nominal value but costs power; no
noise floor is reported.

The verdict (cli.md) is the best candidate when its p < 0.01 and its
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

Run data (:func:`diagnose_runs`): friction terms on the UV/VU half-differences,
compensator and gravity on the joint-2 sweep means, each a likelihood-ratio
test with the noise variance estimated per joint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
import scipy.sparse
import scipy.stats

from elastocal.errors import InputError, UnidentifiableError
from elastocal.identify.effects import ALL_EFFECTS, get_effect
from elastocal.identify.robot import Robot
from elastocal.identify.static import (
    Parameter,
    StaticDataset,
    StaticFit,
    build_dataset,
    identify_static,
)
from elastocal.identify.outliers import without_outliers
from elastocal.identify.plausibility import implausible_reason
from elastocal.identify.stepwise import (
    EXCESS_P,
    Step,
    Unexplained,
    stepwise,
    unexplained_of,
    verdict_of,
)
from elastocal.identify.tables import StaticTable

#: verdict rule of cli.md
VERDICT_P = 0.01
VERDICT_DELTA_BIC = -10.0
#: a feature the excess follows (rank correlation) is reported below this p
FEATURE_P = 5e-3
#: a pose holding more than this share of the excess is named
POSE_SHARE = 0.5


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
    #: (never a step, identify/plausibility.py); None when plausible
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


@dataclass(frozen=True)
class NotTestable:
    """An effect the model lacks that these data cannot show, and why."""

    effect: str
    reason: str


@dataclass(frozen=True)
class GroupSummary:
    """Residual rms per group of deflections (by pose, marker, load, ...)."""

    by: str
    labels: tuple[str, ...]
    rms: np.ndarray          # (G,) residual rms of the group's components [m]
    floor: np.ndarray | None  # (G,) rms that noise alone leaves there [m]
    n: np.ndarray            # (G,) components

    def to_json(self) -> dict:
        return {"by": self.by, "labels": list(self.labels), "rms": self.rms.tolist(),
                "floor": None if self.floor is None else self.floor.tolist(), "n": self.n.tolist(),
                "unit": "m"}


@dataclass(frozen=True, eq=False)
class Where:
    """Where a static fit fails: per-deflection features and group summaries."""

    pose: np.ndarray           # (D,) pose index
    pose_ids: tuple[str, ...]
    marker: np.ndarray         # (D,) marker index
    markers: tuple[str, ...]
    load: np.ndarray           # (D,) load-state id (str)
    q: np.ndarray              # (D, 6) commanded joint angles of the deflection's pose [rad]
    load_size: np.ndarray      # (D,) |F| [N] (or |dGamma| [N·m] without the wrench)
    load_unit: str
    t: np.ndarray              # (D,) time of the loaded readings [s], NaN if unknown
    measured: np.ndarray       # (D, 3) [m]
    predicted: np.ndarray      # (D, 3) [m]
    residual: np.ndarray       # (D, 3) [m]
    noise_var: np.ndarray | None  # (D,) variance noise alone leaves in |residual|^2 [m^2]
    groups: tuple[GroupSummary, ...]

    def group(self, by: str) -> GroupSummary:
        for g in self.groups:
            if g.by == by:
                return g
        raise KeyError(by)

    def to_json(self) -> dict:
        return {g.by: g.to_json() for g in self.groups}


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """What ``elastocal diagnose`` finds (cli.md, ``diagnose --json``)."""

    model: tuple[str, ...]
    torque: str
    form: str
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
    #: effects added in order (identify/stepwise.py); final is the model with all of them
    steps: tuple[Step, ...] = ()
    #: what stays above the floor that no candidate explains (None when nothing does)
    unexplained_detail: Unexplained | None = None
    #: readings far off their repeats (identify/outliers.py), left out of the noise floor
    outliers: tuple = ()

    @property
    def noise_floor(self) -> float | None:
        return self.fit.noise_floor if self.noise_known else None

    @property
    def verdict_candidate(self) -> Candidate | None:
        return self.steps[0].candidate if self.verdict is not None else None

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
            "unexplained": None if self.unexplained_detail is None else {
                **self.unexplained_detail.to_json(), "sentences": list(self.unexplained)},
            "outliers": [o.to_json() for o in self.outliers],
            "where": self.where.to_json(),
        }


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


# =================================================================== noise algebra
@dataclass(frozen=True, eq=False)
class _Noise:
    """Noise covariance of a fit's residual space: (I - H) Sigma."""

    cov: scipy.sparse.csr_matrix  # (n, n) Sigma
    basis: np.ndarray             # (n, p) orthonormal basis of the design's columns
    resid_var: np.ndarray         # (n,) diag((I - H) Sigma)
    mean: float                   # tr((I - H) Sigma)
    var: float                    # var of the rss under noise: 2 tr(((I - H) Sigma)^2)


def _noise(fit: StaticFit) -> _Noise:
    """The noise algebra of a fit that has a noise model (repeated readings)."""
    if fit.noise_blocks is None:
        raise ValueError("the fit has no noise model (no repeated readings)")
    n = fit.n
    a = fit.design
    if a.shape[1]:
        u, s, _ = np.linalg.svd(a, full_matrices=False)
        basis = u[:, s > s[0] * 1e-12]
    else:
        basis = np.zeros((n, 0))
    rows = np.concatenate([r for r, _ in fit.noise_blocks])
    blocks = [c for _, c in fit.noise_blocks]
    stacked = scipy.sparse.block_diag(blocks, format="csr")
    order = np.empty(n, dtype=int)          # place the blocks at their rows
    order[rows] = np.arange(len(rows))
    cov = stacked[order][:, order]
    diag = cov.diagonal()
    sb = cov @ basis                        # Sigma Q
    bsb = basis.T @ sb                      # Q' Sigma Q
    resid_var = diag - np.einsum("ij,ij->i", basis, sb)
    mean = float(diag.sum() - np.trace(bsb))
    tr_s2 = float(sum((c * c).sum() for c in blocks))
    s2b = cov @ sb                          # Sigma^2 Q
    var = 2.0 * (tr_s2 - 2.0 * float(np.einsum("ij,ij->", basis, s2b)) + float((bsb * bsb).sum()))
    return _Noise(cov, basis, resid_var, mean, max(var, 1e-300))


def excess_p_value(fit: StaticFit) -> float | None:
    """P-value of the residual sum of squares under noise alone (scaled
    chi-square matched to its mean and variance); None without repeats."""
    if fit.noise_blocks is None:
        return None
    nz = _noise(fit)
    g = nz.var / (2.0 * nz.mean)
    h = 2.0 * nz.mean**2 / nz.var
    return float(scipy.stats.chi2.sf(fit.rss / g, h))


# =================================================================== where
def _load_sizes(robot: Robot, ds: StaticDataset) -> tuple[np.ndarray, str]:
    sl, sr = ds.defl_state, ds.defl_ref
    if ds.has_wrench:
        return np.linalg.norm(ds.state_wrench[sl, :3] - ds.state_wrench[sr, :3], axis=1), "N"
    d_tau = (ds.state_currents[sl] - ds.state_currents[sr]) * robot.torque_constants
    return np.linalg.norm(d_tau, axis=1), "N*m"


def _bins(values: np.ndarray, n_bins: int, unit: str, fmt: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """Equal-width bins over the range of ``values``: (bin index per value, labels)."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if hi - lo <= 0.0:
        return np.zeros(len(values), dtype=int), (f"{lo:{fmt}} {unit}",)
    edges = np.linspace(lo, hi, n_bins + 1)
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n_bins - 1)
    labels = tuple(f"{edges[k]:{fmt}}..{edges[k + 1]:{fmt}} {unit}" for k in range(n_bins))
    used = np.unique(idx)
    remap = {old: new for new, old in enumerate(used)}
    return np.array([remap[i] for i in idx]), tuple(labels[i] for i in used)


def where_it_fails(robot: Robot, fit: StaticFit, *, n_bins: int = 6, noise: bool = True) -> Where:
    """Residual summaries of a static fit by pose, marker, load state, joint
    angle (each of q1..q6), load size and time; with ``noise`` (and repeated
    readings), what noise alone leaves in each group."""
    ds = fit.dataset
    pose = ds.state_pose[ds.defl_state]
    q = ds.q[pose]
    load_size, load_unit = _load_sizes(robot, ds)
    resid = fit.residuals
    sq = (resid**2).sum(axis=1)
    noise_var = None
    if noise and fit.noise_blocks is not None:
        noise_var = _noise(fit).resid_var.reshape(-1, 3).sum(axis=1)

    def summary(by: str, index: np.ndarray, labels: Sequence[str]) -> GroupSummary:
        g = len(labels)
        n = np.bincount(index, minlength=g) * 3
        ss = np.bincount(index, weights=sq, minlength=g)
        rms = np.sqrt(ss / np.maximum(n, 1))
        floor = None
        if noise_var is not None:
            floor = np.sqrt(np.bincount(index, weights=noise_var, minlength=g) / np.maximum(n, 1))
        return GroupSummary(by, tuple(labels), rms, floor, n)

    groups = [
        summary("pose", pose, ds.pose_ids),
        summary("marker", ds.defl_marker, ds.markers),
    ]
    loads = tuple(dict.fromkeys(ds.state_load[ds.defl_state]))
    groups.append(summary("load", np.array([loads.index(x) for x in ds.state_load[ds.defl_state]]), loads))
    for j in range(6):
        idx, labels = _bins(q[:, j], n_bins, "rad", ".2f")
        groups.append(summary(f"q{j + 1}", idx, labels))
    idx, labels = _bins(load_size, n_bins, load_unit, ".0f")
    groups.append(summary("load_size", idx, labels))
    if np.all(np.isfinite(ds.defl_t)):
        idx, labels = _bins(ds.defl_t, n_bins, "s", ".0f")
        groups.append(summary("time", idx, labels))
    return Where(pose=pose, pose_ids=ds.pose_ids, marker=ds.defl_marker, markers=ds.markers,
                 load=ds.state_load[ds.defl_state], q=q, load_size=load_size, load_unit=load_unit,
                 t=ds.defl_t, measured=ds.dP, predicted=fit.predicted, residual=resid,
                 noise_var=noise_var, groups=tuple(groups))


def unexplained_structure(where: Where) -> tuple[str, ...]:
    """What the excess of the residual over the noise follows: sentences.

    Uses the excess ratio of each deflection (|r|^2 over what noise leaves
    there) and rank correlations: with each joint angle over poses, with the
    load size and the time over load states; the share of the excess at the
    worst pose and marker."""
    if where.noise_var is None:
        return ()
    ratio = (where.residual**2).sum(axis=1) / where.noise_var
    excess = np.maximum(ratio - 1.0, 0.0) * where.noise_var
    total = float(excess.sum())
    if total <= 0.0:
        return ()
    found: list[tuple[float, str]] = []
    n_pose = len(where.pose_ids)
    pose_ratio = np.array([ratio[where.pose == p].mean() for p in range(n_pose)])
    if n_pose >= 5:
        for j in range(6):
            qj = np.array([where.q[where.pose == p][0, j] for p in range(n_pose)])
            if np.ptp(qj) == 0.0:
                continue
            rho, p = scipy.stats.spearmanr(qj, pose_ratio)
            if np.isfinite(p) and p < FEATURE_P:
                word = "grows" if rho > 0 else "falls"
                found.append((p, f"residual {word} with q{j + 1} (rank correlation {rho:+.2f} over "
                                 f"{n_pose} poses)"))
    states = sorted({(int(a), str(b)) for a, b in zip(where.pose, where.load)})
    if len(states) >= 5:
        st_ratio, st_load, st_t = [], [], []
        for pose, load in states:
            m = (where.pose == pose) & (where.load == load)
            st_ratio.append(ratio[m].mean())
            st_load.append(where.load_size[m][0])
            st_t.append(where.t[m].mean())
        st_ratio = np.array(st_ratio)
        for name, values in (("the load", np.array(st_load)), ("time", np.array(st_t))):
            if not np.all(np.isfinite(values)) or np.ptp(values) == 0.0:
                continue
            rho, p = scipy.stats.spearmanr(values, st_ratio)
            if np.isfinite(p) and p < FEATURE_P:
                word = "grows" if rho > 0 else "falls"
                found.append((p, f"residual {word} with {name} (rank correlation {rho:+.2f} over "
                                 f"{len(states)} load states)"))
    if len(where.markers) > 1:
        groups = [ratio[where.marker == m] for m in range(len(where.markers))]
        if all(len(g) > 1 for g in groups):
            _, p = scipy.stats.kruskal(*groups)
            if np.isfinite(p) and p < FEATURE_P:
                worst = int(np.argmax([g.mean() for g in groups]))
                m = where.marker == worst
                ratio_rms = math.sqrt(float((where.residual[m] ** 2).sum() / where.noise_var[m].sum()))
                found.append((p, f"residual is largest at marker {where.markers[worst]} "
                                 f"({ratio_rms:.1f}x the noise rms there)"))
    pose_excess = np.array([excess[where.pose == p].sum() for p in range(n_pose)])
    worst = int(np.argmax(pose_excess))
    if n_pose > 2 and pose_excess[worst] > POSE_SHARE * total:
        found.append((0.0, f"{100 * pose_excess[worst] / total:.0f} % of the excess is at pose "
                           f"{where.pose_ids[worst]}: check that pose's readings"))
    found.sort(key=lambda x: x[0])
    return tuple(text for _, text in found)


# =================================================================== tests
def _wald(aug: StaticFit, names: Sequence[str]) -> tuple[float, int, float, float]:
    """Statistic, dof, p-value and delta BIC of the added parameters ``names``
    (the augmented fit's sandwich covariance with the noise model, scaled by
    its dispersion)."""
    idx = [aug.beta_names.index(nm) for nm in names if nm not in aug.unidentifiable]
    q = len(idx)
    gamma = aug.beta[idx]
    cov = aug.beta_cov[np.ix_(idx, idx)]
    scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    cs = cov / np.outer(scale, scale)
    gs = gamma / scale
    stat = float(gs @ np.linalg.lstsq(cs, gs, rcond=None)[0])
    return stat, q, float(scipy.stats.chi2.sf(stat, q)), -stat + q * math.log(aug.n)


def _assumed_noise(robot: Robot, ds: StaticDataset, model, torque: str, form: str) -> StaticDataset:
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
    d_perp = d - nz.basis @ (nz.basis.T @ d)
    dd = float(d_perp @ d_perp)
    r = base.residuals.reshape(-1)
    if dd <= 0.0:
        return 0.0, 1.0, 0.0
    lam = float(d_perp @ r) / dd
    var = float(d_perp @ (nz.cov @ d_perp)) / dd**2 * _dispersion(aug)
    stat = lam**2 / var
    p = float(scipy.stats.chi2.sf(stat, 1))
    dbic = -(2.0 * lam - 1.0) / var
    return stat, p, dbic


def _dispersion(fit: StaticFit) -> float:
    if fit.expected_rss is None or fit.expected_rss <= 0:
        return 1.0
    return max(1.0, fit.rss / fit.expected_rss)


def _evidence(effect, params: Sequence[Parameter], fallback: str) -> str:
    detail = getattr(effect, "describe", None)
    if detail is None or not params:
        return fallback
    return detail(tuple(p.name for p in params), np.array([p.value for p in params]),
                  np.array([p.std for p in params])) or fallback


# =================================================================== diagnose
def test_candidates(robot: Robot, ds: StaticDataset, base: StaticFit, pool: Sequence[str], *, torque: str,
                    form: str, noise_known: bool) -> tuple[list[Candidate], list[NotTestable]]:
    """Fit ``base``'s model plus each effect of ``pool`` it lacks and test it
    against ``base``: candidates best first, and the effects these data cannot show."""
    model_names = base.model
    candidates: list[Candidate] = []
    skipped: list[NotTestable] = []
    for name in pool:
        if name in model_names:
            continue
        eff = get_effect(name)
        try:
            aug = identify_static(robot, ds, model=(*model_names, name), torque=torque, form=form)
        except InputError as exc:
            if exc.source != "--model":
                raise
            reason = exc.detail.split(": ", 1)[1] if exc.detail.startswith(name + ":") else exc.detail
            skipped.append(NotTestable(name, reason))
            continue
        except UnidentifiableError as exc:
            skipped.append(NotTestable(name, str(exc)))
            continue
        added = [p for p in eff.parameters]
        unident = tuple(nm for nm in added if nm in aug.unidentifiable)
        if added and len(unident) == len(added):
            skipped.append(NotTestable(name, "these data cannot separate its parameters from the model's "
                                             f"(rank {aug.n_params} of {len(aug.beta_names)} parameters, "
                                             f"condition number {aug.condition_number:.3g})"))
            continue
        if added:
            stat, dof, p, dbic = _wald(aug, added)
        else:
            stat, p, dbic = _embedding(base, aug)
            dof = 1
        params = tuple(pp for pp in aug.parameters if pp.name in added)
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


def diagnose_static(robot: Robot, data: StaticTable | StaticDataset, *,
                    model: Sequence[str] = ("joint_stiffness",), torque: str = "current",
                    form: str = "exact", effects: Sequence[str] | None = None,
                    exclude_outliers: bool = False) -> Diagnosis:
    """Fit ``model``, test each effect it lacks, and diagnose stepwise (cli.md).

    ``candidates`` are the effects tested against the model as given, best
    first; the best significant, plausible one is added and the rest tested
    again until none is (identify/stepwise.py). The verdict is the first step
    when the final model sits at the noise floor, else None with what stays
    unexplained. ``effects``: the candidate effects to try (default: every
    effect of the table). Effects these data cannot show are listed in
    ``not_testable`` with the reason. Readings far off their repeats are listed
    in ``outliers`` and left out of the noise floor; ``exclude_outliers`` (a
    table only) refits without them.
    """
    excluded: tuple = ()
    if exclude_outliers and isinstance(data, StaticTable):
        data, excluded = without_outliers(data)
    ds = data if isinstance(data, StaticDataset) else build_dataset(data)
    noise_known = ds.sigma_tracker is not None
    if not noise_known:
        ds = _assumed_noise(robot, ds, model, torque, form)
    base = identify_static(robot, ds, model=model, torque=torque, form=form)
    pool = ALL_EFFECTS if effects is None else tuple(effects)
    skipped_first: list[NotTestable] = []

    def test(fit: StaticFit, added: Sequence[str]) -> list[Candidate]:
        cands, skipped = test_candidates(robot, ds, fit, pool, torque=torque, form=form, noise_known=noise_known)
        if not added:
            skipped_first.extend(skipped)
        return cands

    candidates, steps, final, _ = stepwise(base, test)
    excess = excess_p_value(final) if noise_known else None
    floor = final.noise_floor if noise_known else None
    verdict = verdict_of(steps, final.rms, floor, excess) if noise_known else (steps[0].effect if steps else None)
    where = where_it_fails(robot, base, noise=noise_known)
    where_final = where_it_fails(robot, final, noise=noise_known) if final is not base else where
    unexplained: tuple[str, ...] = ()
    detail = None
    if excess is not None and excess < EXCESS_P:
        unexplained = unexplained_structure(where_final)
        detail = unexplained_of(base.rms, steps, final.rms, floor, excess, unexplained)
        if detail is not None:
            if not unexplained:
                unexplained = (f"residual stays {detail.ratio:.2f}x the noise floor with no pattern in pose, "
                               "marker, joint angle, load or time",)
            kept = [o for o in ds.outliers if not o.excluded]
            if kept:
                unexplained = (f"{len(kept)} reading(s) far off their repeats (lines "
                               f"{', '.join(str(o.line) for o in kept)}) are in the fit: diagnose again with "
                               "--exclude-outliers", *unexplained)
            detail = replace(detail, follows=unexplained)
    return Diagnosis(model=base.model, torque=torque, form=form, fit=base, candidates=tuple(candidates),
                     not_testable=tuple(skipped_first), verdict=verdict, final=final, excess_p_value=excess,
                     unexplained=unexplained, where=where, where_final=where_final, noise_known=noise_known,
                     steps=steps, unexplained_detail=detail, outliers=(*excluded, *ds.outliers))


# =================================================================== run data
#: friction effects and the column of the friction regression each adds
FRICTION_EFFECTS = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
RUN_EFFECTS = (*FRICTION_EFFECTS, "compensator", "gravity")
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


def _friction_columns(speed: np.ndarray, load: np.ndarray) -> dict[str, np.ndarray]:
    return {"coulomb_friction": np.ones_like(speed), "viscous_friction": speed,
            "load_dependent_friction": np.abs(load)}


_FRICTION_PREFIX = {"coulomb_friction": "fc", "viscous_friction": "fv", "load_dependent_friction": "fl"}
_FRICTION_UNIT = {"coulomb_friction": "N*m", "viscous_friction": "N*m*s/rad", "load_dependent_friction": "1"}
_FRICTION_NEEDS = {"viscous_friction": "runs at two or more speeds",
                   "load_dependent_friction": "runs under two or more loads",
                   "coulomb_friction": "UV/VU runs"}


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


def _diagnose_friction(samples, model: tuple[str, ...]):
    """Candidates among the friction effects from matched UV/VU samples."""
    have = [e for e in FRICTION_EFFECTS if e in model]
    cols_all = _friction_columns(samples.speed, samples.load_torque)
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
    for eff_name in FRICTION_EFFECTS:
        if eff_name in have:
            continue
        eff = get_effect(eff_name)
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
            check = terms if "coulomb_friction" in terms else ["coulomb_friction", *terms]
            xc = np.column_stack([cols_all[e][ok, j] for e in check])
            name = f"{_FRICTION_PREFIX[eff_name]}{j + 1}"
            if n[j] <= len(check) + 1 or _scaled_condition(xc) > MAX_FRICTION_CONDITION:
                unident.append(name)
                continue
            beta, cov, rss1[j] = _lstsq(x, y)
            after[ok, j] = x @ beta
            params.append(Parameter(name, float(beta[-1]), float(np.sqrt(max(cov[-1, -1], 0.0))),
                                    _FRICTION_UNIT[eff_name]))
            tested.append(j)
        if not tested:
            skipped.append(NotTestable(eff_name, f"these runs cannot separate it from Coulomb friction; "
                                                 f"it needs {_FRICTION_NEEDS[eff_name]}"))
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


def _diagnose_sweeps(robot: Robot, table, model: tuple[str, ...], stiffness: np.ndarray):
    """Candidates compensator and gravity from joint-2 sweep means."""
    from elastocal.identify.compensator import identify_compensator, sweep_means

    sub = table.subset(np.isin(table.direction, ("+", "-")))
    means = sweep_means(robot, sub.q, sub.currents, sub.direction, sub.load, sub.wrench, stiffness=stiffness,
                        source=table.source)
    spec = robot.compensator
    theta = means.theta
    ext = np.array([(robot.jacobians(th, ["load_point"])[0].T @ w)[1] if np.any(w) else 0.0
                    for th, w in zip(theta, means.wrench)])
    g2 = np.array([robot.gravity_torque(th)[1] for th in theta])
    y = means.torque - ext + g2                       # = -M(q2) - (gravity error)
    candidates: list[tuple[RunCandidate, np.ndarray]] = []
    skipped: list[NotTestable] = []
    nominal = spec.nominal_parameters() if spec is not None else None
    comp_fit = None
    if spec is not None and "compensator" in model:
        comp_fit = identify_compensator(robot, means, gravity="model")
        m_model = spec.torque(means.q2, comp_fit.values)
    elif spec is not None and nominal is not None:
        m_model = spec.torque(means.q2, nominal)
    else:
        m_model = np.zeros_like(y)
    r0 = y + m_model
    n = np.array([len(r0)])
    rss0 = float(r0 @ r0)
    if spec is None:
        skipped.append(NotTestable("compensator", "the robot description has no [compensator]"))
    elif "compensator" not in model:
        try:
            fit = identify_compensator(robot, means, gravity="model")
        except (InputError, UnidentifiableError) as exc:
            skipped.append(NotTestable("compensator", str(exc)))
        else:
            r1 = fit.residuals
            stat, p, dbic = _lr(np.array([rss0]), np.array([float(r1 @ r1)]), n, 2)
            params = tuple(Parameter(nm, float(v), float(s), u)
                           for nm, v, s, u in zip(fit.names, fit.values, fit.std, fit.units))
            base = "the robot description's nominal values" if nominal is not None else "no compensator"
            eff = get_effect("compensator")
            evidence = (f"{eff.evidence}: {', '.join(f'{p_.name} = {p_.value:.4g} {p_.unit}' for p_ in params)} "
                        f"instead of {base}")
            candidates.append((RunCandidate("compensator", "sweep", eff.explanation, evidence,
                                            float(np.sqrt(rss0 / n[0])), fit.rms, dbic, p, stat, 2, params, ()),
                               r1))
    if "gravity" not in model:
        if not robot.has_masses:
            skipped.append(NotTestable("gravity", "the robot description gives no link masses to correct"))
        else:
            reg = _gravity_regressor2(robot, theta)
            scale = np.linalg.norm(reg, axis=0)
            used = scale > 0
            _, s, vt = np.linalg.svd(reg[:, used], full_matrices=False)
            rank = int(np.sum(s > GRAVITY_RANK_TOL * s[0])) if s.size and s[0] > 0 else 0
            if rank == 0 or len(r0) <= rank + 1:
                skipped.append(NotTestable("gravity", "the sweeps excite no gravity parameter"))
            else:
                phi = reg[:, used] @ vt[:rank].T
                beta, cov, rss1 = _lstsq(phi, r0)
                r1 = r0 - phi @ beta
                stat, p, dbic = _lr(np.array([rss0]), np.array([rss1]), n, rank)
                eff = get_effect("gravity")
                params = tuple(Parameter(f"g{k + 1}", float(b), float(np.sqrt(max(cov[k, k], 0.0))), "N*m")
                               for k, b in enumerate(beta))
                candidates.append((RunCandidate("gravity", "sweep", eff.explanation,
                                                f"{eff.evidence} ({rank} mass-moment combinations the sweeps excite)",
                                                float(np.sqrt(rss0 / n[0])), float(np.sqrt(rss1 / n[0])), dbic, p,
                                                stat, rank, params, ()), r1))
    return candidates, skipped, means, r0


def diagnose_runs(robot: Robot, table, *, model: Sequence[str] = ("joint_stiffness",),
                  stiffness: Sequence[float] | None = None) -> RunDiagnosis:
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
    """
    from elastocal.identify.friction import friction_samples

    model = tuple(dict.fromkeys(["joint_stiffness", *model]))
    for name in model:
        get_effect(name)
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
        found, skip, before, rss0, n = _diagnose_friction(samples, model)
        candidates += found
        skipped += skip
        friction_out = (samples, before)
        pieces_rss += float(rss0.sum())
        pieces_n += int(n.sum())
        resid = samples.friction - before
        if np.any(np.isfinite(resid)):
            pieces_max = max(pieces_max, float(np.nanmax(np.abs(resid))))
    else:
        for name in FRICTION_EFFECTS:
            if name not in model:
                skipped.append(NotTestable(name, "the runs hold no UV/VU pairs (the same path forward and backward)"))
    sweep_out = None
    has_sweeps = bool(np.any(np.isin(table.direction, ("+", "-"))))
    if has_sweeps and stiffness is None:
        for name in ("compensator", "gravity"):
            if name not in model:
                skipped.append(NotTestable(name, "the sweep torques need the joint stiffness to place the arm at "
                                                 "its deflected configuration: give the static table too"))
    elif has_sweeps:
        found, skip, means, r0 = _diagnose_sweeps(robot, table, model, np.asarray(stiffness, dtype=float))
        candidates += found
        skipped += skip
        sweep_out = (means, r0)
        pieces_rss += float(r0 @ r0)
        pieces_n += len(r0)
        pieces_max = max(pieces_max, float(np.max(np.abs(r0))) if len(r0) else 0.0)
    else:
        for name in ("compensator", "gravity"):
            if name not in model:
                skipped.append(NotTestable(name, "the runs hold no joint-2 sweep (direction + and -)"))
    for name in ALL_EFFECTS:
        if name in model or name in RUN_EFFECTS:
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
        if verdict in FRICTION_EFFECTS:
            after = candidates[0][1]
        friction_view = FrictionView(samples.friction, samples.speed, samples.load_torque, samples.pair,
                                     samples.pairs, before, after)
    if sweep_out is not None:
        means, r0 = sweep_out
        after = candidates[0][1] if verdict in ("compensator", "gravity") else None
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
