"""Does the current calibration still hold? (docs/check.md)

A check is a short experiment (a few static poses under one load, one UV/VU
pair) compared with what the current calibration predicts for it.

Deflections. The check data are fitted with the calibration's static model
(:func:`~elastocal.identify.static.identify_static`); the deflections the
calibration predicts follow from that fit by one Gauss-Newton step from the
check's own parameters to the calibrated ones (exact for the first-order
form, and to ~1e-4 of the change for the exact form). The unexplained part
``r = measured - predicted`` is weighed with its covariance under the
hypothesis that nothing changed::

    Sigma = noise (tracker and current repeatability of the check data,
                   propagated through the model: StaticFit.noise_blocks)
          + A diag(var(calibrated parameters)) A^T
          + s_m^2 I      (s_m^2 = calibration rms^2 - noise floor^2, when > 0:
                          what the calibrated model already left unexplained)

and ``chi2 = r^T Sigma^-1 r`` is compared with the chi-square distribution of
``3 D - (nuisance parameters)`` degrees of freedom. Session effects (tracker
thermal drift) are nuisance: fitted on the check data, never compared.

Friction. The UV/VU half-differences of the check run (Y48) are compared
joint by joint with ``fc + fv |dq| + fl |tau|`` of the calibration: the mean
difference over the path, its standard error from batch means (robust to
correlation along the path) plus the calibrated parameters' uncertainty, a
two-sided Student test. Friction varies with temperature, so a joint fails
only when the difference is significant *and* larger than ``tolerance`` of
the predicted friction.

The verdict is "recalibrate" when a test fails at its share of ``alpha``
(Bonferroni over the tests and, for friction, over the joints), "holds"
otherwise. Pure: tables and calibration in, a frozen :class:`CheckResult` out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
import numpy as np
from scipy import stats

from elastocal.diagnose.check_positions import PositionCheck, check_positions
from elastocal.errors import InputError
from elastocal.formats.calibration import Calibration
from elastocal.model.effects import get_effect, having
from elastocal.model.robot import Robot
from elastocal.formats.tables import RunTable, StaticTable
from elastocal.model.kinds import KinematicForm

#: contiguous batches the friction samples of a joint are averaged in
FRICTION_BATCHES = 10
VERDICTS = ("holds", "recalibrate")


# ==================================================================== results
@dataclass(frozen=True)
class ParameterChange:
    """A calibrated parameter against its value on the check data."""

    name: str
    unit: str
    calibrated: float
    check: float
    check_std: float            # std of the check's own estimate
    std: float                  # combined std of the difference
    z: float                    # (check - calibrated) / std

    @property
    def relative(self) -> float:
        return self.check / self.calibrated - 1.0 if self.calibrated else math.nan


@dataclass(frozen=True, eq=False)
class DeflectionCheck:
    measured: np.ndarray         # (D, 3) [m]
    predicted: np.ndarray        # (D, 3) by the calibration [m]
    chi2: float
    dof: int
    p_value: float
    alpha: float                 # this test's share of the overall alpha
    noise_floor_m: float
    model_allowance_m: float
    changes: tuple[ParameterChange, ...]   # largest |z| first
    untested: tuple[str, ...]    # calibrated parameters these data do not determine
    nuisance: tuple[str, ...]    # fitted on the check data, not compared

    @property
    def passed(self) -> bool:
        return self.p_value >= self.alpha

    @property
    def rms_measured_m(self) -> float:
        return float(np.sqrt(np.mean(self.measured ** 2)))

    @property
    def rms_unexplained_m(self) -> float:
        return float(np.sqrt(np.mean((self.measured - self.predicted) ** 2)))

    def reason(self) -> str:
        head = (f"{self.rms_unexplained_m * 1e6:.1f} µm rms unexplained, noise floor "
                f"{self.noise_floor_m * 1e6:.1f} µm (chi2 {self.chi2:.1f} on {self.dof} dof, "
                f"p = {self.p_value:.2g})")
        if self.passed:
            return f"deflections agree with the calibration: {head}"
        text = f"deflections differ from what the calibration predicts: {head}"
        big = [c for c in self.changes if abs(c.z) > 3.0]
        if big:
            c = big[0]
            text += (f"; the check data put {c.name} at {c.check:.4g} {c.unit}, {c.relative * 100:+.1f} % "
                     f"from the calibrated {c.calibrated:.4g} (z = {c.z:.1f})")
        return text

    def to_json(self) -> dict:
        return {"passed": self.passed, "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value,
                "alpha": self.alpha, "n": int(self.measured.size),
                "rms_measured": self.rms_measured_m, "rms_unexplained": self.rms_unexplained_m,
                "noise_floor": self.noise_floor_m, "model_allowance": self.model_allowance_m, "unit": "m",
                "parameters": {c.name: {"calibrated": c.calibrated, "check": c.check, "check_std": c.check_std,
                                        "std": c.std, "z": c.z,
                                        "relative": c.relative, "unit": c.unit} for c in self.changes},
                "untested": list(self.untested), "nuisance": list(self.nuisance)}


@dataclass(frozen=True)
class FrictionJoint:
    joint: int
    measured_nm: float           # mean friction over the check path
    predicted_nm: float          # mean of the calibration's friction over the same samples
    std_nm: float                # std of the difference
    p_value: float
    n: int
    unit: str = "N*m"            # the friction's unit: N on a prismatic joint

    @property
    def relative(self) -> float:
        return (self.measured_nm - self.predicted_nm) / self.predicted_nm if self.predicted_nm else math.inf


@dataclass(frozen=True, eq=False)
class FrictionCheck:
    joints: tuple[FrictionJoint, ...]
    alpha: float                 # this test's share of the overall alpha (split over the joints)
    tolerance: float
    missing_terms: tuple[str, ...]   # calibration parameters absent, counted as zero

    def failing(self) -> tuple[FrictionJoint, ...]:
        level = self.alpha / max(len(self.joints), 1)
        return tuple(j for j in self.joints if j.p_value < level and abs(j.relative) > self.tolerance)

    @property
    def passed(self) -> bool:
        return not self.failing()

    def reason(self) -> str:
        bad = self.failing()
        if bad:
            return "; ".join(f"friction of joint {j.joint} is {j.relative * 100:+.0f} % off the calibration "
                             f"({j.measured_nm:.1f} {j.unit.replace('*', '·')} measured, {j.predicted_nm:.1f} "
                             f"predicted, p = {j.p_value:.2g})"
                             for j in bad)
        if not self.joints:
            return "friction not checked: no joint moved in the check run"
        worst = max(self.joints, key=lambda j: abs(j.relative))
        joints = ", ".join(str(j.joint) for j in self.joints)
        return (f"friction agrees with the calibration on joints {joints} (largest change "
                f"{worst.relative * 100:+.1f} % at joint {worst.joint}, tolerance {self.tolerance * 100:.0f} %)")

    def to_json(self) -> dict:
        return {"passed": self.passed, "alpha": self.alpha, "tolerance": self.tolerance,
                "joints": {str(j.joint): {"measured": j.measured_nm, "predicted": j.predicted_nm, "std": j.std_nm,
                                          "relative": j.relative, "p_value": j.p_value, "n": j.n, "unit": j.unit}
                           for j in self.joints},
                "missing_terms": list(self.missing_terms), "unit": "N*m"}


@dataclass(frozen=True, eq=False)
class CheckResult:
    verdict: str                          # "holds" or "recalibrate"
    reasons: tuple[str, ...]
    alpha: float
    deflection: DeflectionCheck | None
    friction: FrictionCheck | None
    #: absolute accuracy (identify/accuracy.py), when the calibration holds kinematic_errors
    absolute: object | None = None
    #: unloaded positions against the calibration's own data (diagnose/check_positions.py)
    positions: PositionCheck | None = None

    def to_json(self) -> dict:
        return {"verdict": self.verdict, "reasons": list(self.reasons), "alpha": self.alpha,
                "deflection": None if self.deflection is None else self.deflection.to_json(),
                "friction": None if self.friction is None else self.friction.to_json(),
                **({} if self.absolute is None else {"absolute": self.absolute.to_json()}),
                **({} if self.positions is None else {"positions": self.positions.to_json()})}


# ================================================================ deflections
def _reported_name(beta_name: str) -> str:
    """Name of a model parameter in the calibration (c_j -> k_j)."""
    return f"k{beta_name[1:]}" if beta_name[:1] == "c" and beta_name[1:].isdigit() else beta_name


def _param(cal: Calibration, name: str) -> tuple[float, float] | None:
    p = cal.find(name)
    return None if p is None else (p.value, p.std_or_zero)


def _model_allowance(calibration: Calibration, noise_var: float, n_params: int) -> float:
    """What the calibrated model already left unexplained, per component [m]:
    ``rms^2`` minus what noise alone leaves. The calibration's own noise floor
    when it records one, else the check's noise per component reduced by the
    calibration's degrees of freedom (``1 - p/n``)."""
    res = calibration.residual
    rms = res.rms
    if rms is None or not math.isfinite(rms):
        return 0.0
    floor = res.noise_floor
    if floor is not None and math.isfinite(floor):
        expected = floor ** 2
    else:
        n = res.n
        frac = 1.0 - n_params / n if n is not None and n > n_params else 1.0
        expected = noise_var * frac
    return math.sqrt(max(rms ** 2 - expected, 0.0))


def check_static(robot: Robot, calibration: Calibration, table: StaticTable, *, alpha: float = 1e-3,
                 form: KinematicForm = KinematicForm.EXACT) -> DeflectionCheck:
    """Compare the check's deflections with the calibration's prediction (module docstring)."""
    from elastocal.identify.static import identify_static

    missing = [f"k{j}" for j in range(1, robot.n_joints + 1) if not calibration.has(f"k{j}")]
    if len(missing) == robot.n_joints:
        raise InputError(f"the calibration holds no joint stiffness (k1..k{robot.n_joints}); a static check needs one",
                         source=calibration.source, argument="calibration")
    from elastocal.identify.absolute import ABSOLUTE_EFFECTS

    model = tuple(name for name in calibration.model
                  if "static" in get_effect(name).seen_in and name not in ABSOLUTE_EFFECTS)
    fit = identify_static(robot, table, model=model or ("joint_stiffness",), torque=calibration.torque, form=form)
    if fit.noise_blocks is None:
        raise InputError("the check data hold no repeated readings: the check needs repeats >= 2 per marker and "
                         "load state to know the noise", source=table.source)
    session = {p for name in having("session", fit.model) for p in get_effect(name).parameters}
    identifiable = [i for i, b in enumerate(fit.beta_names) if _reported_name(b) not in fit.unidentifiable]
    a = fit.design
    if a is None or a.shape[1] != len(identifiable):
        raise RuntimeError("static fit without a design matrix for its identifiable parameters")
    delta = np.zeros(len(identifiable))
    var_cal = np.zeros(len(identifiable))
    tested = np.zeros(len(identifiable), dtype=bool)
    nuisance: list[str] = []
    changes: list[ParameterChange] = []
    for col, i in enumerate(identifiable):
        beta_name = fit.beta_names[i]
        name = _reported_name(beta_name)
        cal = None if beta_name in session else _param(calibration, name)
        if cal is None:
            nuisance.append(name)
            continue
        value, std = cal
        if name != beta_name:               # stiffness k -> compliance c
            if value == 0.0:
                raise InputError(f"calibrated {name} is zero", source=calibration.source, argument="calibration",
                                 column=f"parameters.{name}")
            beta_cal, var = 1.0 / value, (std / value ** 2) ** 2
        else:
            beta_cal, var = value, std ** 2
        delta[col] = beta_cal - fit.beta[i]
        var_cal[col] = var
        tested[col] = True
        p = fit.parameter(name)
        comb = math.hypot(p.std, std)
        changes.append(ParameterChange(name=name, unit=p.unit, calibrated=value, check=p.value, check_std=p.std,
                                       std=comb,
                                       z=(p.value - value) / comb if comb > 0 else math.inf))
    measured = fit.dataset.dP
    predicted = fit.predicted + (a @ delta).reshape(-1, 3)
    r = (measured - predicted).reshape(-1)
    n = r.size
    cov = np.zeros((n, n))
    for rows, block in fit.noise_blocks:
        cov[np.ix_(rows, rows)] += block
    a_t = a[:, tested]
    cov += (a_t * var_cal[tested]) @ a_t.T
    floor = float(fit.noise_floor or 0.0)
    allowance = _model_allowance(calibration, float(np.mean(np.diag(cov))), len(fit.beta_names))
    cov += allowance ** 2 * np.eye(n)
    try:
        chi2 = float(r @ np.linalg.solve(cov, r))
    except np.linalg.LinAlgError:
        raise InputError("the calibration's uncertainties leave no test of the deflections (the covariance of "
                         "the prediction is singular): check the std of its parameters",
                         source=calibration.source, argument="calibration", column="parameters") from None
    dof = n - len(nuisance)
    if dof < 1:
        raise InputError(f"{n} deflection components cannot test the calibration once {len(nuisance)} session "
                         "parameters are fitted; add poses to the check", source=table.source)
    untested = tuple(m for m in missing) + tuple(u for u in fit.unidentifiable if calibration.has(u))
    changes.sort(key=lambda c: -abs(c.z))
    return DeflectionCheck(measured=measured, predicted=predicted, chi2=chi2, dof=dof,
                           p_value=float(stats.chi2.sf(chi2, dof)), alpha=alpha, noise_floor_m=floor,
                           model_allowance_m=allowance, changes=tuple(changes), untested=untested,
                           nuisance=tuple(nuisance))


# =================================================================== friction
def _batch_se(x: np.ndarray, batches: int) -> float:
    means = np.array([b.mean() for b in np.array_split(x, batches) if b.size])
    return float(np.std(means, ddof=1) / math.sqrt(len(means)))


def check_friction(robot: Robot, calibration: Calibration, runs: RunTable, *, alpha: float = 1e-3,
                   tolerance: float = 0.2) -> FrictionCheck | None:
    """Compare the friction of the check's UV/VU runs with the calibration's;
    None when the calibration holds no friction."""
    from elastocal.identify.friction import friction_samples

    if not any(p.name.startswith("fc") and p.name[2:].isdigit() for p in calibration.parameters):
        return None
    if not 0.0 <= tolerance:
        raise InputError(f"must be >= 0, got {tolerance}", argument="friction_tolerance")
    uvvu = np.isin(runs.direction, ("UV", "VU"))
    if not np.any(uvvu):
        raise InputError("the check runs hold no UV/VU pair", source=runs.source, column="direction")
    sub = runs.subset(uvvu)
    samples = friction_samples(sub.q, sub.dq, sub.currents, sub.run, sub.direction, sub.load,
                               robot.torque_constants, t=sub.t, source=runs.source)
    joints: list[FrictionJoint] = []
    missing: list[str] = []
    for j in range(robot.n_joints):
        fc = _param(calibration, f"fc{j + 1}")
        if fc is None:
            continue
        ok = np.isfinite(samples.friction[:, j])
        if ok.sum() < 2 * FRICTION_BATCHES:
            continue
        f = samples.friction[ok, j]
        speed = samples.speed[ok, j]
        tau = np.abs(samples.load_torque[ok, j])
        pred = np.full(f.shape, fc[0])
        var_pred = fc[1] ** 2
        for prefix, x in (("fv", speed), ("fl", tau)):
            p = _param(calibration, f"{prefix}{j + 1}")
            if p is None:
                missing.append(f"{prefix}{j + 1}")
                continue
            pred = pred + p[0] * x
            var_pred += (p[1] * float(np.mean(x))) ** 2
        d = f - pred
        se = _batch_se(d, FRICTION_BATCHES)
        std = math.sqrt(se ** 2 + var_pred)
        z = float(np.mean(d)) / std if std > 0 else math.inf
        p_value = float(2.0 * stats.t.sf(abs(z), FRICTION_BATCHES - 1))
        joints.append(FrictionJoint(joint=j + 1, measured_nm=float(np.mean(f)), predicted_nm=float(np.mean(pred)),
                                    std_nm=std, p_value=p_value, n=int(ok.sum()),
                                    unit="N" if robot.prismatic[j] else "N*m"))
    return FrictionCheck(joints=tuple(joints), alpha=alpha, tolerance=tolerance, missing_terms=tuple(missing))


# ==================================================================== verdict
def check_calibration(robot: Robot, calibration: Calibration, *, static: StaticTable | None = None,
                      runs: RunTable | None = None, alpha: float = 1e-3, friction_tolerance: float = 0.2,
                      form: KinematicForm = KinematicForm.EXACT, baseline: StaticTable | None = None) -> CheckResult:
    """The verdict on ``calibration`` from a check's static table and/or runs. ``baseline``: the
    calibration's own static data; a check's unloaded readings are compared with its unloaded
    readings at the same poses (diagnose/check_positions.py), which is all an unattended check
    (no load hung) can test of the static model."""
    if not 0.0 < alpha < 1.0:
        raise InputError(f"must be between 0 and 1, got {alpha}", argument="alpha")
    if static is None and runs is None:
        raise InputError("the check holds neither static poses nor runs", argument="static")
    has_friction = runs is not None and any(p.name.startswith("fc") and p.name[2:].isdigit()
                                            for p in calibration.parameters)
    loaded = static is not None and not static.absolute_only
    compare_positions = static is not None and baseline is not None
    n_tests = int(loaded) + int(has_friction) + int(compare_positions)
    share = alpha / max(n_tests, 1)
    reasons: list[tuple[bool, str]] = []      # (failed, text)
    deflection = check_static(robot, calibration, static, alpha=share, form=form) if loaded else None
    if deflection is not None:
        reasons.append((not deflection.passed, deflection.reason()))
    elif static is not None:
        reasons.append((False, "deflections not checked: the check read its poses unloaded only"))
    positions = check_positions(static, baseline, alpha=share) if compare_positions else None
    if positions is not None:
        reasons.append((not positions.passed, positions.reason()))
    from elastocal.identify.accuracy import absolute_check

    absolute = absolute_check(robot, calibration, static) if static is not None else None
    if absolute is not None:             # the validate comparison (identify/accuracy.py)
        reasons.append((not absolute.passed, absolute.reason()))
    friction = None
    if runs is not None:
        friction = check_friction(robot, calibration, runs, alpha=share, tolerance=friction_tolerance)
        reasons.append((False, "friction not checked: the calibration holds no friction parameters")
                       if friction is None else (not friction.passed, friction.reason()))
    else:
        reasons.append((False, "friction not checked: the check has no UV/VU runs"))
    failed = any(f for f, _ in reasons)
    ordered = [text for f, text in reasons if f] + [text for f, text in reasons if not f]
    return CheckResult(verdict="recalibrate" if failed else "holds", reasons=tuple(ordered), alpha=alpha,
                       deflection=deflection, friction=friction, absolute=absolute, positions=positions)
