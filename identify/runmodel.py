"""The torque model of run data, fitted as a whole, with its noise floor.

Run data show two friction-free or gravity-free reductions of the currents
(docs/physics.md): the **half-differences** of every forward/backward pair —
UV/VU runs and ``+``/``-`` joint sweeps alike, the same path both ways — hold
the friction (identify/friction.py), and the **sweep means** of joint 2 hold
the compensator and gravity (identify/compensator.py, identify/sweepfit.py).
:func:`fit_run_model` fits the effects of a model to both: per joint, the sum of
the model's friction columns (each effect's ``run_column``); on the sweeps, the
sum of the model's sweep terms (each effect's ``sweep_term``). It never looks
at an effect's name.

**Noise floor.** The repeatability ``sigma_j`` of one current reading comes
from the runs themselves: along a slow motion the current changes smoothly, so
the fourth difference ``i[k] - 4 i[k+1] + 6 i[k+2] - 4 i[k+3] + i[k+4]`` of
successive samples is noise (variance ``70 sigma^2``; a cubic trend cancels;
rms within 4 robust std, pooled over the runs). When the drive's filter
correlates successive samples, the differences of samples 3 apart are larger
than those of neighbours, and those are used. Through the half-difference
``xi (i_f - i_b)/2`` and the sweep mean ``xi (i_f + i_b)/2`` a reading's noise
becomes ``xi^2 sigma^2 (1 + w)/4`` (``w`` from the interpolation of the
backward run); the floor is the rms that this noise leaves after the fit,
``sqrt(sum var_i (1 - h_ii) / n)`` with the leverages ``h`` of each fit, and the
excess over it is tested with the whitened chi-square ``sum r_i^2 / var_i`` on
``n - p`` degrees of freedom — as for static data (diagnose/where.py).

**The arm's deflection.** The sweeps are placed at the deflected configuration
``q + offset + xi i / k``: with the static fit's stiffness when there is one,
else robot.toml's nominal joint stiffness, else the rigid model, whose bias is
stated (:class:`StiffnessUsed`): what a stiffness of
:data:`REFERENCE_STIFFNESS` on every joint would change, in proportion to the
compliance for any other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from elastocal.errors import UnidentifiableError
from elastocal.model.effects.base import Effect
from elastocal.model.robot import DEFAULT_PRIOR_PRISMATIC_STIFFNESS
from elastocal.identify.static import Parameter

#: a scaled friction design worse conditioned than this cannot separate a term from Coulomb
MAX_FRICTION_CONDITION = 1e4
#: the joint stiffness [N·m/rad] at which the rigid model's bias is stated (a heavy robot's
#: gear stiffness; the bias scales with the compliance 1/k)
REFERENCE_STIFFNESS = 1.0e6
#: lag-3 differences this much above lag-1 ones: the noise is correlated in time
CORRELATED_NOISE_RATIO = 1.25
#: the noise differences: fourth order, their variance per unit reading variance
DIFF_COEFFICIENTS = (1.0, -4.0, 6.0, -4.0, 1.0)
DIFF_VARIANCE = float(sum(c * c for c in DIFF_COEFFICIENTS))
#: differences beyond this many robust std from their median are not noise
TRIM_MAD = 4.0
#: the share of a normal variable's variance within +-TRIM_MAD std
TRIM_VARIANCE = 0.998929
#: fewer matched samples than this on a joint: its friction is not fitted
MIN_SAMPLES = 5


# ------------------------------------------------------------------ noise
def _robust_sigma(d2: np.ndarray) -> float:
    """sigma of one reading from fourth differences (variance 70 sigma^2): the rms of those
    within 4 robust standard deviations (MAD) of their median, so that a spike or a
    friction reversal does not count, at the efficiency of the rms for Gaussian noise."""
    d2 = d2[np.isfinite(d2)]
    if d2.size < 3:
        return float("nan")
    centre = float(np.median(d2))
    mad = float(np.median(np.abs(d2 - centre))) * 1.482602218505602
    kept = d2 if mad == 0.0 else d2[np.abs(d2 - centre) <= TRIM_MAD * mad]
    # a normal variable within +-4 sigma keeps 99.89 % of its variance
    return float(np.sqrt(np.mean(kept ** 2) / (DIFF_VARIANCE * (TRIM_VARIANCE if mad else 1.0))))


def _difference(i: np.ndarray, lag: int) -> np.ndarray:
    """Fourth differences of successive readings ``lag`` samples apart (a smooth signal's
    cubic trend cancels; white noise keeps variance 70 sigma^2)."""
    m = len(i) - 4 * lag
    return sum(c * i[k * lag:k * lag + m] for k, c in enumerate(DIFF_COEFFICIENTS))


def current_noise(table) -> np.ndarray:
    """Repeatability sigma [A] (N,) of one current reading per joint, from the fourth
    differences within each run (NaN for a joint without enough samples)."""
    n_joints = np.asarray(table.currents).shape[1]
    out = np.full(n_joints, np.nan)
    lag_diffs = {1: [], 3: []}
    for r in dict.fromkeys(table.run):
        i = table.currents[table.run == r]
        for lag in lag_diffs:
            if len(i) > 4 * lag + 2:
                lag_diffs[lag].append(_difference(i, lag))
    if not lag_diffs[1]:
        return out
    for j in range(n_joints):
        s1 = _robust_sigma(np.concatenate([d[:, j] for d in lag_diffs[1]]))
        s3 = _robust_sigma(np.concatenate([d[:, j] for d in lag_diffs[3]])) if lag_diffs[3] else float("nan")
        out[j] = s3 if np.isfinite(s3) and s3 > CORRELATED_NOISE_RATIO * s1 else s1
    return out


# ------------------------------------------------------------------ deflection
@dataclass(frozen=True)
class StiffnessUsed:
    """Where the joint stiffness that places the sweeps came from, and the rigid model's bias."""

    source: str                                  # "static fit", "robot.toml" or "rigid"
    values: tuple[float, ...] | None             # k1..kN [N·m/rad, N/m]; None for the rigid model
    #: rigid model: rms change of the sweep torques [N·m] with REFERENCE_STIFFNESS on every joint
    bias_torque_rms: float | None = None
    #: rigid model: (name, relative bias) of each fitted sweep parameter, the rigid value against
    #: the value with that stiffness, (rigid - deflected) / deflected
    bias_parameters: tuple[tuple[str, float], ...] = ()
    joint: int = 2                               # the swept joint (1-based) whose torque the bias is of
    #: whether the robot has prismatic joints (the bias then holds them at a track's prior N/m)
    prismatic: bool = False

    @property
    def _prismatic(self) -> str:
        return (f" (a prismatic one at {DEFAULT_PRIOR_PRISMATIC_STIFFNESS:.0e} N/m)" if self.prismatic else "")

    @property
    def note(self) -> str:
        if self.source != "rigid":
            return f"sweeps placed at the deflected configuration with the joint stiffness of the {self.source}"
        text = ("rigid model: robot.toml gives no joint stiffness, so the joint deflections xi i / k are "
                "neglected")
        if self.bias_torque_rms is not None:
            text += (f"; with every joint at {REFERENCE_STIFFNESS:.0e} N*m/rad{self._prismatic} they would "
                     "change the "
                     f"joint-{self.joint} sweep torque by {self.bias_torque_rms:.2g} N*m rms")
        if self.bias_parameters:
            text += (", and the rigid model's " + ", ".join(f"{n} would be off by {100 * v:+.2g} %"
                                                             for n, v in self.bias_parameters))
        return text + " (in proportion to 1/k for another stiffness)"

    def to_json(self) -> dict:
        out = {"source": self.source, "values": None if self.values is None else list(self.values),
               "unit": "N*m/rad", "note": self.note}
        if self.source == "rigid":
            out["bias"] = {"reference_stiffness": REFERENCE_STIFFNESS, "torque_rms": self.bias_torque_rms,
                           "relative": dict(self.bias_parameters)}
        return out


def stiffness_used(robot, stiffness: Sequence[float] | None) -> StiffnessUsed:
    """The static fit's stiffness when given, else robot.toml's nominal one, else rigid (bias not yet stated)."""
    if stiffness is not None:
        return StiffnessUsed("static fit", tuple(float(k) for k in stiffness))
    nominal = robot.nominal_stiffness
    if nominal is not None:
        return StiffnessUsed("robot.toml", tuple(float(k) for k in nominal))
    return StiffnessUsed("rigid", None)


# ------------------------------------------------------------------ data
@dataclass(frozen=True, eq=False)
class RunData:
    """The reductions of a run table the run model is fitted to, with their noise."""

    robot: object
    source: str
    friction: object | None          # identify.friction.FrictionSamples (forward/backward pairs)
    friction_var: np.ndarray | None  # (n, N) noise variance of each half-difference [N·m^2]
    sweeps: object | None            # identify.compensator.SweepMeans
    sweep_y: np.ndarray | None       # (n,) what the sweep terms explain (identify/sweepfit.py) [N·m]
    sweep_var: np.ndarray | None     # (n,) noise variance of each sweep mean [N·m^2]
    sweep_terms: dict = field(default_factory=dict)     # effect -> SweepTerm
    sweep_refused: dict = field(default_factory=dict)   # effect -> why not
    current_noise: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))   # (N,) [A]
    stiffness: StiffnessUsed = StiffnessUsed("rigid", None)


def _sweep_part(robot, table, stiffness: Sequence[float] | None, sweep_effects: Sequence[Effect]):
    from elastocal.identify.compensator import known_torque, sweep_means
    from elastocal.identify.sweepfit import sweep_terms

    sweeps = np.isin(table.direction, ("+", "-"))
    if not np.any(sweeps):
        return None, None, {}, {}
    sub = table.subset(sweeps)
    means = sweep_means(robot, sub.q, sub.currents, sub.direction, sub.load, sub.wrench, run=sub.run,
                        stiffness=stiffness, source=table.source)
    terms, refused = sweep_terms(robot, means.q2, means.theta, sweep_effects, means.joint)
    return means, known_torque(robot, means), terms, refused


def prepare_run_data(robot, table, *, stiffness: Sequence[float] | None = None,
                     sweep_effects: Sequence[Effect] = ()) -> RunData:
    """Half-differences of every forward/backward pair, sweep means of joint 2 (at the deflected
    configuration of :func:`stiffness_used`), the sweep effects' terms, and the noise of each."""
    from elastocal.identify.friction import table_friction_samples

    used = stiffness_used(robot, stiffness)
    sigma = current_noise(table)
    xi = robot.torque_constants
    samples = table_friction_samples(table, xi)
    f_var = None
    if samples is not None:
        w = samples.weight if samples.weight is not None else np.ones(len(samples.pair))
        f_var = (xi * sigma)[None, :] ** 2 * (1.0 + w)[:, None] / 4.0
    means, y, terms, refused = _sweep_part(robot, table, used.values, sweep_effects)
    s_var = None
    if means is not None:
        w = means.weight if means.weight is not None else np.ones(len(y))
        s_var = (xi[means.joint] * sigma[means.joint]) ** 2 * (1.0 + w) / 4.0
        used = replace(used, joint=means.joint + 1, prismatic=bool(np.any(robot.prismatic)))
    return RunData(robot=robot, source=table.source, friction=samples, friction_var=f_var, sweeps=means,
                   sweep_y=y, sweep_var=s_var, sweep_terms=terms, sweep_refused=refused, current_noise=sigma,
                   stiffness=used)


def with_rigid_bias(data: RunData, table, sweep_effects: Sequence[Effect], fitted: Sequence[str]) -> RunData:
    """``data`` whose rigid-model note states the bias: the sweep fit of ``fitted`` again with
    REFERENCE_STIFFNESS on every joint."""
    if data.stiffness.source != "rigid" or data.sweeps is None:
        return data
    # a prismatic joint's reference is in N/m: a track's prior stiffness (model/robot.py)
    ref_k = np.where(data.robot.prismatic, DEFAULT_PRIOR_PRISMATIC_STIFFNESS, REFERENCE_STIFFNESS)
    ref = prepare_run_data(data.robot, table, stiffness=ref_k, sweep_effects=sweep_effects)
    torque_rms = float(np.sqrt(np.mean((ref.sweep_y - data.sweep_y) ** 2)))
    rel: tuple[tuple[str, float], ...] = ()
    wanted = [e for e, t in data.sweep_terms.items() if (e in fitted or t.required) and e in ref.sweep_terms]
    if any(not data.sweep_terms[e].linear for e in wanted):
        from elastocal.identify.sweepfit import fit_sweeps

        try:
            rigid = fit_sweeps(data.sweep_y, [(e, data.sweep_terms[e]) for e in wanted])
            soft = fit_sweeps(ref.sweep_y, [(e, ref.sweep_terms[e]) for e in wanted])
        except UnidentifiableError:
            rigid = soft = None
        if rigid is not None:   # the physical parameters (nonlinear terms), not gravity's combinations
            rel = tuple((p.name, (p.value - s.value) / s.value)
                        for e in wanted if not data.sweep_terms[e].linear
                        for p, s in zip(rigid.parameters(e), soft.parameters(e)) if p.value != 0.0)
    return replace(data, stiffness=replace(data.stiffness, bias_torque_rms=torque_rms, bias_parameters=rel))


# ------------------------------------------------------------------ the fit
@dataclass(frozen=True, eq=False)
class RunModelFit:
    """The run model's effects fitted to the half-differences and the sweep means."""

    model: tuple[str, ...]
    parameters: tuple[Parameter, ...]
    unidentifiable: tuple[str, ...]
    friction_pred: np.ndarray | None     # (n, N) the model's friction (NaN where the joint is still)
    friction_rss: np.ndarray             # (N,) [N·m^2, N^2 on a prismatic joint]
    friction_n: np.ndarray               # (N,)
    friction_floor_ss: np.ndarray        # (N,) sum of var (1 - h)
    friction_chi2: np.ndarray            # (N,) sum of r^2 / var
    friction_p: np.ndarray               # (N,) parameters fitted per joint
    #: which friction effect's column each joint holds: effect -> (N,) bool
    friction_columns: dict
    sweep: object | None                 # identify.sweepfit.SweepFit
    sweep_floor_ss: float = 0.0
    sweep_chi2: float = 0.0
    friction_residual: np.ndarray | None = None   # (n, N) measured - model

    @property
    def sweep_rss(self) -> float:
        return float(self.sweep.residuals @ self.sweep.residuals) if self.sweep is not None else 0.0

    @property
    def sweep_n(self) -> int:
        return int(len(self.sweep.residuals)) if self.sweep is not None else 0

    @property
    def n(self) -> int:
        return int(self.friction_n.sum()) + self.sweep_n

    @property
    def n_parameters(self) -> int:
        return int(self.friction_p.sum()) + (self.sweep.n_parameters if self.sweep is not None else 0)

    @property
    def rms(self) -> float:
        n = self.n
        return math.sqrt((float(self.friction_rss.sum()) + self.sweep_rss) / n) if n else float("nan")

    @property
    def max(self) -> float:
        parts = [0.0]
        if self.friction_pred is not None and self.friction_residual is not None:
            r = self.friction_residual[np.isfinite(self.friction_residual)]
            parts.append(float(np.max(np.abs(r))) if r.size else 0.0)
        if self.sweep is not None and self.sweep_n:
            parts.append(float(np.max(np.abs(self.sweep.residuals))))
        return max(parts)

    @property
    def noise_floor(self) -> float | None:
        n = self.n
        ss = float(self.friction_floor_ss.sum()) + self.sweep_floor_ss
        return math.sqrt(ss / n) if n and np.isfinite(ss) and ss > 0 else None

    @property
    def excess_p(self) -> float | None:
        """p-value of the whitened residual against the noise alone (small: above the floor)."""
        if self.noise_floor is None:
            return None
        dof = self.n - self.n_parameters
        stat = float(self.friction_chi2.sum()) + self.sweep_chi2
        import scipy.stats  # imported where used: scipy.stats costs the commands that never test a quarter second

        return float(scipy.stats.chi2.sf(stat, dof)) if dof > 0 else None

    def group_rss(self) -> np.ndarray:
        """(N + 1,) rss of the N joints' half-differences and of the sweep means."""
        return np.append(self.friction_rss, self.sweep_rss)

    def group_n(self) -> np.ndarray:
        return np.append(self.friction_n, self.sweep_n)

    def to_json(self) -> dict:
        return {"model": list(self.model),
                "residual": {"rms": self.rms, "max": self.max, "n": self.n, "unit": "N*m"},
                "noise_floor": self.noise_floor, "excess_p_value": self.excess_p}


def _scaled_condition(x: np.ndarray) -> float:
    scale = np.linalg.norm(x, axis=0)
    if np.any(scale == 0):
        return float("inf")
    return float(np.linalg.cond(x / scale))


def _fit_friction(data: RunData, effects: Sequence[Effect], constant: Effect | None):
    """Per joint, least squares of the half-differences on the columns of ``effects``
    that these samples separate (from each other and from ``constant``)."""
    s = data.friction
    n_all, n_joints = s.friction.shape
    pred = np.full((n_all, n_joints), np.nan)
    rss, floor, chi2 = np.zeros(n_joints), np.zeros(n_joints), np.zeros(n_joints)
    n, p = np.zeros(n_joints, dtype=int), np.zeros(n_joints, dtype=int)
    cols_in = {e.name: np.zeros(n_joints, dtype=bool) for e in effects}
    params: list[Parameter] = []
    unident: list[str] = []
    std_all = {}
    for j in range(n_joints):
        ok = np.isfinite(s.friction[:, j])
        n[j] = int(ok.sum())
        if n[j] == 0:
            continue
        y = s.friction[ok, j]
        var = data.friction_var[ok, j] if data.friction_var is not None else np.full(n[j], np.nan)
        cols: list[np.ndarray] = []
        kept: list[Effect] = []
        for e in effects:
            col = e.run_column(s.speed[ok, j], s.load_torque[ok, j])
            check = [*cols, col]
            # by name: the same effect sized for another robot is another object
            if constant is not None and constant.name not in {k.name for k in (*kept, e)}:
                check = [constant.run_column(s.speed[ok, j], s.load_torque[ok, j]), *check]
            if n[j] <= max(MIN_SAMPLES - 1, len(check) + 1) or _scaled_condition(np.column_stack(check)) > \
                    MAX_FRICTION_CONDITION:
                unident.append(f"{e.run_prefix}{j + 1}")
                continue
            cols.append(col)
            kept.append(e)
        if cols:
            x = np.column_stack(cols)
            beta, *_ = np.linalg.lstsq(x, y, rcond=None)
            fitted = x @ beta
            q, _ = np.linalg.qr(x / np.linalg.norm(x, axis=0))
            h = np.einsum("ij,ij->i", q, q)
            res = y - fitted
            dof = max(n[j] - len(cols), 1)
            cov = float(res @ res) / dof * np.linalg.pinv(x.T @ x)
            for k, e in enumerate(kept):
                cols_in[e.name][j] = True
                std_all[(e.name, j)] = (float(beta[k]), float(math.sqrt(max(cov[k, k], 0.0))))
        else:
            fitted, h, res = np.zeros(n[j]), np.zeros(n[j]), y
        pred[ok, j] = fitted
        rss[j] = float(res @ res)
        floor[j] = float(np.sum(var * (1.0 - h)))
        chi2[j] = float(np.sum(res ** 2 / var))
        p[j] = len(cols)
    for e in effects:
        for j in range(n_joints):
            if (e.name, j) in std_all:
                v, sd = std_all[(e.name, j)]
                params.append(Parameter(f"{e.run_prefix}{j + 1}", v, sd, e.units[j]))
    return pred, rss, n, floor, chi2, p, cols_in, tuple(params), tuple(unident)


def fit_run_model(data: RunData, effects: Sequence[Effect], *, constant: Effect | None = None) -> RunModelFit:
    """Fit the run-data ``effects`` (friction columns, sweep terms) to ``data``.

    ``constant``: the friction effect every other one must be told apart from (the
    Coulomb-like one; default: the first friction effect of the table). Sweep terms
    that the description makes required are fitted whether or not they are named.
    Raises UnidentifiableError when the model's sweep terms cannot be separated.
    """
    from elastocal.identify.sweepfit import fit_sweeps

    effects = tuple(effects)
    friction_effects = [e for e in effects if e.run_part == "uv/vu" and e.run_column is not None]
    if constant is None:
        from elastocal.model.effects import get_effect, run_effects

        constant = get_effect(run_effects("uv/vu")[0], data.robot)
    model = tuple(e.name for e in effects)
    params: list[Parameter] = []
    unident: list[str] = []
    if data.friction is not None:
        pred, rss, n, floor, chi2, p, cols_in, f_params, f_unident = _fit_friction(data, friction_effects, constant)
        params += f_params
        unident += f_unident
        resid = data.friction.friction - pred
    else:
        pred = resid = None
        nj = data.robot.n_joints
        rss, floor, chi2, n, p = np.zeros(nj), np.zeros(nj), np.zeros(nj), np.zeros(nj, int), np.zeros(nj, int)
        cols_in = {e.name: np.zeros(nj, dtype=bool) for e in friction_effects}
    sweep = None
    s_floor = s_chi2 = 0.0
    if data.sweeps is not None:
        names = {e.name for e in effects}
        fitted = [(name, term) for name, term in data.sweep_terms.items() if name in names or term.required]
        fixed = [term for name, term in data.sweep_terms.items() if not (name in names or term.required)]
        sweep = fit_sweeps(data.sweep_y, fitted, fixed)
        params += sweep.parameters()
        var = data.sweep_var
        s_floor = float(np.sum(var * (1.0 - sweep.leverage)))
        s_chi2 = float(np.sum(sweep.residuals ** 2 / var))
        model = tuple(dict.fromkeys((*model, *sweep.effects)))
    return RunModelFit(model=model, parameters=tuple(params), unidentifiable=tuple(unident), friction_pred=pred,
                       friction_rss=rss, friction_n=n, friction_floor_ss=floor, friction_chi2=chi2, friction_p=p,
                       friction_columns=cols_in, sweep=sweep, sweep_floor_ss=s_floor, sweep_chi2=s_chi2,
                       friction_residual=resid)
