"""A calibration against data it was not fitted on (docs/cli.md, ``elastocal validate``).

Two models predict the same static table:

* ``nominal``: robot.toml's rigid model (the drawing's DH table, no
  elasticity): absolute positions ``FK(q + offset)``, deflections zero;
* ``calibrated``: the calibration's full model: the robot rebuilt with its
  kinematic errors (identify/kinematics.py), the joint springs ``c = 1/k`` on
  the absolute torques (currents ``ξ i``, or the model's gravity plus the wrench
  with a force-based calibration), and every other static effect it holds
  (the elastic part exactly as the absolute fit has it, identify/absolute.py).

Both are registered to the tracker afresh on the validation data (closed-form
rigid fit: the tracker may have moved), or the calibrated one keeps the
calibration's registration (``keep_frame``, which needs ``tracker_frame`` in
the calibration). Errors are over the x, y, z components (each counts once, as
in docs/cli.md's residuals): rms, mean of their magnitudes, max, 95th percentile.
Session effects (thermal drift) are not carried from one day to another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from elastocal.errors import Arg, InputError
from elastocal.identify import kinematics as kin
from elastocal.identify.blas import one_blas_thread
from elastocal.formats.calibration import Calibration
from elastocal.model.effects import BASE_EFFECT, get_effect, having
from elastocal.identify.registration import Registration, kabsch, nominal_positions
from elastocal.model.kinds import NoiseSource
from elastocal.model.robot import MARKER_PREFIX, Robot
from elastocal.identify.dataset import StaticDataset, build_dataset
from elastocal.identify.level import TILT_NAMES, tilt_twist
from elastocal.identify.staticmodel import Problem, absolute_bases, absolute_positions, state_torques, static_context
from elastocal.formats.tables import StaticTable
from elastocal.model.kinds import KinematicForm, TorqueSource



@dataclass(frozen=True)
class ErrorStats:
    rms: float
    mean: float
    max: float
    p95: float
    n: int

    @classmethod
    def of(cls, residual: np.ndarray) -> "ErrorStats":
        a = np.abs(np.asarray(residual, dtype=float).reshape(-1))
        return cls(rms=float(np.sqrt(np.mean(a ** 2))), mean=float(a.mean()), max=float(a.max()),
                   p95=float(np.percentile(a, 95)), n=int(a.size))

    def to_json(self) -> dict:
        return {"rms": self.rms, "mean": self.mean, "max": self.max, "p95": self.p95, "n": self.n, "unit": "m"}


@dataclass(frozen=True, eq=False)
class Validation:
    calibration: str
    poses: int
    absolute_nominal: ErrorStats
    absolute_calibrated: ErrorStats
    deflection_nominal: ErrorStats | None          # None: the data hold no deflections (no loads)
    deflection_calibrated: ErrorStats | None
    keep_frame: bool
    registration: Registration           # the calibrated model's
    #: rms that the noise of these data alone would leave in the absolute comparison
    #: (tracker and current repeatability; None without repeated readings) [m]
    noise_floor: float | None
    absolute_residual: np.ndarray        # (S, M, 3) calibrated, tracker frame
    nominal_residual: np.ndarray         # (S, M, 3)
    pose_ids: tuple[str, ...]
    reference_states: np.ndarray
    markers: tuple[str, ...] = ()
    #: the joints the calibration's stiffness keeps rigid (not held, not determined: identify's marks)
    rigid: tuple[str, ...] = ()

    def by_marker(self) -> dict:
        """The absolute errors per marker, both models (docs/cli.md ``by_marker``)."""
        return {m: {"nominal": ErrorStats.of(self.nominal_residual[:, k]).to_json(),
                    "calibrated": ErrorStats.of(self.absolute_residual[:, k]).to_json()}
                for k, m in enumerate(self.markers)}

    def note(self) -> str | None:
        """What the reader must know of the calibrated model, or None."""
        if not self.rigid:
            return None
        return (f"{', '.join(self.rigid)} not determined by the calibration: "
                f"{'these joints are' if len(self.rigid) > 1 else 'this joint is'} rigid in the calibrated model")

    def per_pose(self) -> list[dict]:
        """Absolute error per pose (unloaded reference), nominal and calibrated [m]."""
        out = []
        for s in self.reference_states:
            en = np.linalg.norm(self.nominal_residual[s], axis=1)
            ec = np.linalg.norm(self.absolute_residual[s], axis=1)
            out.append({"pose": self.pose_ids[len(out)], "nominal_max": float(en.max()),
                        "calibrated_max": float(ec.max())})
        return out

    def to_json(self) -> dict:
        return {"calibration": self.calibration, "poses": self.poses, "keep_frame": self.keep_frame,
                "absolute": {"nominal": self.absolute_nominal.to_json(),
                             "calibrated": self.absolute_calibrated.to_json(), "noise_floor": self.noise_floor},
                "deflection": None if self.deflection_nominal is None else {
                    "nominal": self.deflection_nominal.to_json(), "calibrated": self.deflection_calibrated.to_json()},
                "by_marker": self.by_marker(),
                "registration": {"rotation": self.registration.rotation.tolist(),
                                 "translation": self.registration.translation.tolist(),
                                 "base_p_tracker": self.registration.base_p_tracker.tolist()},
                **({"note": self.note()} if self.note() else {})}


def _value(cal: Calibration, name: str) -> float | None:
    p = cal.find(name)
    return None if p is None else p.value


def calibrated_robot(robot: Robot, calibration: Calibration) -> Robot:
    """The robot with the calibration's kinematic errors (robot itself without them)."""
    if not having("geometry", calibration.model):
        return robot
    names = kin.parameter_names(robot, robot.marker_names)
    values = [_value(calibration, n) or 0.0 for n in names]
    return kin.corrected_robot(robot, names, values)


def calibration_frame(calibration: Calibration) -> Registration:
    """The calibration's registration (``tracker_frame`` parameters rx..tz)."""
    values = [_value(calibration, n) for n in ("rx", "ry", "rz", "tx", "ty", "tz")]
    if any(v is None for v in values):
        raise InputError((Arg("keep_frame"), " needs a calibration with tracker_frame (rx..tz); identify with ",
                          Arg("model", "...,tracker_frame")), argument="calibration")
    return Registration(rotation=pin.exp3(np.array(values[:3])), translation=np.array(values[3:]), rms=float("nan"))


def calibration_compliance(robot: Robot, calibration: Calibration) -> tuple[np.ndarray, tuple[str, ...]]:
    """Compliance ``c = 1/k`` per joint as the calibration holds it, and the joints it keeps rigid
    (``c = 0``): those whose stiffness it does not hold, holds marked ``"determined": false`` or
    holds not positive (identify writes them so: what identify writes, validate reads)."""
    c = np.zeros(robot.n_joints)
    rigid = []
    for j in range(1, robot.n_joints + 1):
        p = calibration.find(f"k{j}")
        if p is None or not p.is_result or not p.value > 0 or not np.isfinite(p.value):
            rigid.append(f"k{j}")
        else:
            c[j - 1] = 1.0 / p.value
    return c, tuple(rigid)


def predicted_base_positions(robot: Robot, calibration: Calibration, ds: StaticDataset) -> np.ndarray:
    """Base positions (S, M, 3) of every state's markers under the calibration's full model."""
    return _predicted(robot, calibration, ds)[0]


def _predicted(robot: Robot, calibration: Calibration, ds: StaticDataset) -> tuple[np.ndarray, tuple[str, ...]]:
    """:func:`predicted_base_positions` and the joints kept rigid (:func:`calibration_compliance`)."""
    from elastocal.identify.absolute_only import is_absolute_only, self_weight_dataset

    # the effects only absolute positions show, and those of the measuring session, are not carried to other data
    model = tuple(m for m in calibration.model if not (get_effect(m).absolute_only or get_effect(m).session))
    model = tuple(dict.fromkeys(m for m in model if "static" in get_effect(m).seen_in))
    effects = tuple(get_effect(n, robot) for n in model)
    beta = []
    rigid: tuple[str, ...] = ()
    for eff in effects:
        if eff.name == BASE_EFFECT:
            compliance, rigid = calibration_compliance(robot, calibration)
            beta += list(compliance)
        else:
            beta += [_value(calibration, n) or 0.0 for n in eff.parameters]
    beta = np.array(beta)
    rob = calibrated_robot(robot, calibration)
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    values = {p.name: p.value for p in calibration.parameters}
    tilted = any(n in values for n in TILT_NAMES)
    if not np.any(beta) and not tilted:     # a rigid model: the corrected geometry alone
        return absolute_positions(rob, ds, frames, np.zeros(0), _no_bases(rob, ds)), rigid
    torque = calibration.torque
    if is_absolute_only(ds) and not ds.has_wrench:   # no loads: the robot's own weight only
        ds, torque = self_weight_dataset(ds), TorqueSource.FORCE
    if torque is TorqueSource.CURRENT and not ds.has_currents:
        raise InputError("a current-based calibration with joint stiffness needs the currents i1..iN in every "
                         "row", source=ds.source)
    pr = Problem(rob, ds, effects, torque, KinematicForm.EXACT, frames)
    tau = state_torques(pr, None)
    iterative = any(e.iterative for e in effects)
    bases = absolute_bases(pr, static_context(pr, tau, beta if iterative else None))
    # the weight's direction the fit found (a base out of level; the currents already hold it)
    twist = tilt_twist(pr, beta, tuple(p for e in effects for p in e.parameters), values) \
        if tilted and torque is TorqueSource.FORCE else None
    if twist is not None:                   # one more column, its coefficient 1
        bases = (np.concatenate([bases[0], twist[:, :, None]], axis=2),
                 np.concatenate([bases[1], np.zeros((*bases[1].shape[:2], 1))], axis=2),
                 np.concatenate([bases[2], np.zeros((*bases[2].shape[:3], 1))], axis=3))
        beta = np.append(beta, 1.0)
    return absolute_positions(rob, ds, frames, beta, bases, pr.data), rigid


def _no_bases(robot: Robot, ds: StaticDataset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.zeros((ds.n_states, robot.n_joints, 0)), np.zeros((ds.n_states, len(robot.springs_in_link_model), 0)),
            np.zeros((ds.n_states, len(ds.markers), 3, 0)))


def _noise_floor(robot: Robot, calibration: Calibration, ds: StaticDataset, rotation: np.ndarray) -> float | None:
    """sqrt(trace(Σ)/n) of the mean readings (identify/absolute.py's noise model)."""
    from elastocal.identify.absolute import _noise

    if ds.noise_source is NoiseSource.NONE:
        return None
    compliance = calibration_compliance(robot, calibration)[0]
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    chols, _, _ = _noise(calibrated_robot(robot, calibration), ds, calibration.torque, compliance, rotation, frames)
    return float(np.sqrt(sum(np.sum(c ** 2) for c in chols) / ds.abs_xyz.size))


@one_blas_thread
def validate(robot: Robot, calibration: Calibration, data: StaticTable | StaticDataset, *,
             keep_frame: bool = False, calibration_name: str = "") -> Validation:
    """Nominal and calibrated model against the data (module docstring)."""
    if calibration.robot != robot.name:
        raise InputError(f"the calibration is of robot {calibration.robot!r}, the description of {robot.name!r}",
                         argument="calibration")
    ds = data if isinstance(data, StaticDataset) else build_dataset(data)
    weights = ds.abs_n.reshape(-1)
    y = ds.abs_xyz
    nominal = nominal_positions(robot, ds)
    reg_nominal = kabsch(nominal.reshape(-1, 3), y.reshape(-1, 3), weights)
    if reg_nominal is None or not reg_nominal.rms < 0.05:
        raise InputError("the table's x, y, z are not absolute positions of this robot's markers (a rigid fit "
                         "leaves more than 5 cm or cannot fix a rotation)", source=ds.source)
    predicted, rigid = _predicted(robot, calibration, ds)
    if keep_frame:
        reg = calibration_frame(calibration)
    else:
        reg = kabsch(predicted.reshape(-1, 3), y.reshape(-1, 3), weights)
    nominal_res = y - reg_nominal.apply(nominal)
    calibrated_res = y - reg.apply(predicted)
    floor = _noise_floor(robot, calibration, ds, reg.rotation)
    d_meas = ds.dP                 # the rigid model predicts no deflection
    d_cal = calibrated_res[ds.defl_state, ds.defl_marker] - calibrated_res[ds.defl_ref, ds.defl_marker]
    refs = np.flatnonzero(ds.state_ref == np.arange(ds.n_states))
    return Validation(
        calibration=calibration_name, poses=len(ds.pose_ids),
        absolute_nominal=ErrorStats.of(nominal_res), absolute_calibrated=ErrorStats.of(calibrated_res),
        deflection_nominal=ErrorStats.of(d_meas) if d_meas.size else None,
        deflection_calibrated=ErrorStats.of(d_cal) if d_cal.size else None,
        keep_frame=keep_frame, registration=reg, noise_floor=floor, absolute_residual=calibrated_res,
        nominal_residual=nominal_res, pose_ids=ds.pose_ids, reference_states=refs, markers=ds.markers,
        rigid=rigid if BASE_EFFECT in calibration.model else ())


#: a check's absolute accuracy holds while the calibrated rms stays within this many noise floors
#: (beyond it the calibrated model explains less than the tracker measures)
CHECK_FLOOR_RATIO = 2.0


@dataclass(frozen=True, eq=False)
class AbsoluteCheck:
    """The absolute comparison of ``elastocal validate`` inside a calibration check."""

    validation: Validation

    @property
    def passed(self) -> bool:
        return self.validation.absolute_calibrated.rms <= CHECK_FLOOR_RATIO * self.validation.noise_floor

    def reason(self) -> str:
        v = self.validation
        ratio = v.absolute_calibrated.rms / v.noise_floor
        words = "holds" if self.passed else f"lost (over {CHECK_FLOOR_RATIO:g}x the noise floor)"
        return (f"absolute accuracy {words}: {v.absolute_calibrated.rms * 1e6:.1f} µm rms calibrated, "
                f"{ratio:.2f}x the noise floor {v.noise_floor * 1e6:.1f} µm (nominal "
                f"{v.absolute_nominal.rms * 1e6:.0f} µm)")

    def to_json(self) -> dict:
        return {**self.validation.to_json(), "passed": self.passed, "limit_ratio": CHECK_FLOOR_RATIO}


def absolute_check(robot: Robot, calibration: Calibration, table: StaticTable) -> AbsoluteCheck | None:
    """The check's absolute comparison, when the calibration holds the geometry
    (kinematic_errors) and the check's table holds repeated absolute readings; else None."""
    from elastocal.identify.absolute import has_absolute_positions

    if not having("geometry", calibration.model):
        return None
    ds = build_dataset(table)
    if ds.sigma_tracker is None or not has_absolute_positions(robot, ds):
        return None
    return AbsoluteCheck(validate(robot, calibration, ds))
