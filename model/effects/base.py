"""What an effect is: parameters, where it shows, how it enters the static and run models.

Every static effect enters the model linearly through three bases evaluated on
a :class:`StaticContext` (one row per load state ``s`` and per deflection ``d``):

* ``theta``  (S, N, p): change of the N joint variables of state s per parameter;
* ``links``  (S, L, p): rotation of the link model's L passive springs (link_compliance);
* ``add``    (D, 3, p): a term added to deflection d directly (tracker drift).

The absolute model (identify/absolute.py) needs each state's own positions, not
only their differences: :meth:`Effect.absolute` gives the same three bases per
state (``add`` per state and marker, (S, M, 3, p)). By default they are the
static ones (the angle and link bases of a state, the additive term of a
deflection on its loaded state); an effect whose static basis holds only the
change from the reference (the link springs carry the change of the load's
moment, the drift the time between two readings) declares ``absolute_basis``
with what the absolute readings carry (the moment of gravity and of the whole
load, the time since the first reading).

Parameters that exist once per joint (``k1..kN``, ``fc1..fcN``) are sized for the
robot: an effect module builds its :class:`Effect` with a ``make(robot)`` factory
(:func:`joint_names`, :func:`joint_units`: a prismatic joint's units are N and m
where a revolute joint's are N·m and rad), declares it as ``sized``, and its
module-level ``EFFECT`` is the one of a six-axis revolute arm (the table of
docs/cli.md); ``get_effect(name, robot)`` gives the robot's own.

An effect the given data cannot show returns the reason from ``static_refusal``;
the fit then refuses it with that reason instead of reporting a number the data
do not hold. A basis column that is exactly zero marks a parameter these data
cannot see (e.g. the backlash of a joint whose torque never reverses): the fit
reports it as unidentifiable.

The fit (identify/static.py) turns angles into positions with Pinocchio: in the
first-order form through the Jacobians at the commanded pose, in the exact
form through forward kinematics at the deflected configuration.

Run data are declared the same way: ``run_part`` says which part of a run table
shows the effect, and a friction effect gives its column of the per-joint friction
regression (``run_column``) and the runs that separate it (``run_needs``). The
friction fit and the run diagnosis take the effects as strategies (the friction
regression is the sum of the columns of the effects in the model), so a new
friction law is one new effect module. A "sweep" effect gives its part of the
joint-2 sweep torque (``sweep_term``: a :class:`SweepTerm` built on a
:class:`SweepContext`, or the reason these sweeps cannot hold it): the sweep fits
(identify/sweepfit.py) sum the terms of the effects in the model, nonlinear ones
(the compensator's geometry) and linear ones (gravity's regressor) alike.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

import numpy as np

from elastocal.model.kinds import KinematicForm, TorqueSource, expect


@dataclass(frozen=True, eq=False)
class StaticContext:
    """Arrays an effect may use to build its static basis."""

    tau: np.ndarray             # (S, N) absolute gear torque of each state [N·m; N for a prismatic joint]
    delta_tau: np.ndarray       # (S, N) torque change from the pose's reference (0 for references)
    delta_link_moment: np.ndarray  # (S, L) change of the moments at the link springs [N·m]
    state_is_reference: np.ndarray  # (S,) bool
    deflection_dt: np.ndarray   # (D,) time between the loaded and the reference readings [s]; NaN if unknown
    n_deflections: int
    torque_source: TorqueSource
    form: KinematicForm = KinematicForm.EXACT
    #: current estimate of every model parameter (None in the first solve), for
    #: effects whose basis depends on it (Effect.iterative)
    estimate: np.ndarray | None = None
    estimate_names: tuple[str, ...] = ()
    #: (S, 6) change of the external wrench on the load point from the pose's
    #: reference, base axes (from the wrench columns, or J_f^{-T} dGamma with currents)
    delta_wrench: np.ndarray | None = None
    #: (S, N) std of each state's gear torque from current noise [N·m] (None without repeats)
    torque_noise: np.ndarray | None = None
    #: (S, 6) the external wrench on the load point of each state, base axes (with currents:
    #: the change from the reference recovered from them, the reference carrying none)
    wrench: np.ndarray | None = None
    #: the robot and the dataset, for effects whose basis needs the geometry
    #: (located compliance: frames and marker positions at each pose)
    robot: object = None
    dataset: object = None
    #: the computation's Pinocchio work buffers (``robot.create_data()``, model/robot.py), for
    #: effects whose basis needs kinematics; None: the effect makes its own
    data: object = None

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque_source, "torque_source")
        expect(KinematicForm, self.form, "form")

    def estimated(self, name: str) -> float | None:
        """Current estimate of parameter ``name`` (None before the first solve)."""
        if self.estimate is None or name not in self.estimate_names:
            return None
        return float(self.estimate[self.estimate_names.index(name)])


@dataclass(frozen=True, eq=False)
class SweepContext:
    """Sweep means (of joint 2 on a six-axis arm) an effect may use to build its :class:`SweepTerm`."""

    robot: object               # the Robot (model/robot.py)
    q2: np.ndarray              # (n,) the swept joint's coordinate of each mean (the compensator's) [rad]
    theta: np.ndarray           # (n, N) link-side configuration of each mean (deflected when known)
    joint: int = 1              # 0-based index of the swept joint (1: joint 2)


@dataclass(frozen=True, eq=False)
class SweepTerm:
    """An effect's part of the friction-free joint-2 sweep torque.

    The sweep model is ``y = -(sum of the terms' torques)``, ``y`` the measured
    mean torque less the external wrench's, plus the description's gravity
    (identify/sweepfit.py); each term takes ``torque(p)`` [N·m] off joint 2.
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    torque: Callable[[np.ndarray], np.ndarray]     # parameters -> (n,) [N·m]
    jacobian: Callable[[np.ndarray], np.ndarray]   # parameters -> (n, p)
    linear: bool = False
    #: (target y, (n, m) columns of the linear terms fitted with it) -> starting parameters
    start: Optional[Callable[[np.ndarray, np.ndarray], np.ndarray]] = None
    lower: np.ndarray | None = None                # bounds on the parameters (None: none)
    #: the description's values, the model's torque when the effect is not fitted (None: zero)
    nominal: np.ndarray | None = None
    #: why the sweep fit must always hold it (the description lacks what it would be
    #: taken as known from), or None
    required: str | None = None


@dataclass(frozen=True)
class StaticBasis:
    theta: np.ndarray | None = None
    links: np.ndarray | None = None
    add: np.ndarray | None = None


@dataclass(frozen=True)
class AbsoluteBasis:
    """The static bases per state (module docstring): ``theta`` (S, N, p), ``links``
    (S, L, p), ``add`` (S, M, 3, p) added to the base position of each state's markers."""

    theta: np.ndarray | None = None
    links: np.ndarray | None = None
    add: np.ndarray | None = None


class Compensation(enum.Enum):
    """How compensation (compensation/model.py) treats an effect a calibration holds."""

    #: the compensation model holds it (the joint springs, the compensator, gravity, the geometry)
    MODELLED = "modelled"
    #: it moves no tool point of a planned path: a measurement-side session effect, or friction
    #: (a torque during motion, not a deflection at rest)
    NO_PATH_DEFLECTION = "no path deflection"
    #: it deflects the robot, but compensation leaves it out (refused unless left out knowingly)
    UNMODELLED = "unmodelled"


# What generic code asks of an effect, by capability. :class:`Effect` implements all of them
# (a capability an effect lacks is None, False or empty there); each effect module fills in
# the capabilities it has. Generic code asks these, never which effect it is (tests/test_layers.py).


class EffectCore(Protocol):
    """Every effect: its name, parameters and units, and its words for users."""

    name: str
    parameters: tuple[str, ...]
    units: tuple[str, ...]
    seen_in: tuple[str, ...]
    explanation: str
    evidence: str
    static_model: str
    run_model: str
    describe: Optional[Callable[[tuple[str, ...], np.ndarray, np.ndarray], str]]
    plausibility: Optional[Callable[[tuple[str, ...], np.ndarray, np.ndarray], Optional[str]]]

    def for_robot(self, robot) -> "Effect": ...


class StaticCapability(Protocol):
    """How the effect enters the deflection fit (identify/static.py, identify/staticmodel.py)."""

    static_basis: Optional[Callable[[StaticContext], StaticBasis]]
    static_refusal: Optional[Callable[[StaticContext], Optional[str]]]
    iterative: bool
    torque_at_deflection: bool
    torque_sensitivity: Optional[Callable[[StaticContext, np.ndarray], np.ndarray]]
    selectable: bool
    report_names: tuple[str, ...] | None


class AbsoluteCapability(Protocol):
    """How the effect enters the absolute fit (identify/absolute.py) and what a calibration
    carries of it to another session (identify/accuracy.py, diagnose/check.py)."""

    absolute_basis: Optional[Callable[[StaticContext], AbsoluteBasis]]
    absolute_only: bool
    geometry: bool
    registration: bool
    session: bool
    self_weight: bool
    shown_by_times: bool
    absolute_only_refusal: Optional[Callable[[object, object], Optional[str]]]
    fitted_with: tuple[str, ...]
    absolute_shows_more: bool


class RunCapability(Protocol):
    """How run data show the effect (identify/friction.py, identify/sweepfit.py, diagnose/runs.py)."""

    run_part: Optional[str]
    run_column: Optional[Callable[[np.ndarray, np.ndarray], np.ndarray]]
    run_needs: str
    sweep_term: Optional[Callable[[SweepContext], "SweepTerm | str"]]


class CompensationCapability(Protocol):
    """How compensation treats the effect (compensation/model.py)."""

    compensation: Compensation


@dataclass(frozen=True, eq=False)
class Effect:
    """One physical effect: its parameters, the data that shows it, its words (the
    capabilities above: :class:`EffectCore`, :class:`StaticCapability`,
    :class:`AbsoluteCapability`, :class:`RunCapability`, :class:`CompensationCapability`)."""

    name: str
    parameters: tuple[str, ...]
    units: tuple[str, ...]
    seen_in: tuple[str, ...]          # "static", "runs"
    explanation: str                  # one sentence a user understands
    evidence: str                     # what the residual looks like when it is missing
    static_basis: Optional[Callable[[StaticContext], StaticBasis]] = None
    #: what the absolute readings of each state carry, when it is not the static basis
    #: placed on the loaded states (module docstring; :meth:`absolute`)
    absolute_basis: Optional[Callable[[StaticContext], AbsoluteBasis]] = None
    #: why the given static data cannot show the effect (None when it can)
    static_refusal: Optional[Callable[[StaticContext], Optional[str]]] = None
    #: model value -> reported value and its derivative (for the std)
    report: Optional[Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]] = None
    report_units: tuple[str, ...] | None = None
    #: (beta names, beta, covariance, this effect's slice) -> (reported values, stds), for
    #: reported values that need other parameters of the model (nonlinear_stiffness: T = c / phi)
    report_with_model: Optional[Callable] = None
    #: the model takes the force-based torques at the deflected configuration (not only the
    #: exact form does): a force-based fit recomputes them as it iterates (identify/staticmodel.py)
    torque_at_deflection: bool = False
    #: the static basis depends on the current estimate (StaticContext.estimate):
    #: the fit rebuilds it at every iteration
    iterative: bool = False
    #: (context, this effect's parameter values) -> (S, N) what the effect adds to
    #: d dtheta / d tau of each state (current noise propagates through it)
    torque_sensitivity: Optional[Callable[[StaticContext, np.ndarray], np.ndarray]] = None
    #: (parameter names, values, stds) of a fit -> the evidence in these data, in words
    describe: Optional[Callable[[tuple[str, ...], np.ndarray, np.ndarray], str]] = None
    #: (parameter names, values, stds) of a fit -> why the values are physically
    #: implausible (diagnose/plausibility.py), or None
    plausibility: Optional[Callable[[tuple[str, ...], np.ndarray, np.ndarray], Optional[str]]] = None
    #: a fit keeps only the parameters the data support (forward selection,
    #: identify/selection.py) unless the effect is already restricted
    selectable: bool = False
    #: the parameters of the effect it was restricted from (None: not restricted)
    selected_from: tuple[str, ...] | None = None
    #: a selectable effect's components count for identifiability in this order (lower
    #: first, per parameter; None: all alike): a component that the joint springs and the
    #: components before it already express is unidentifiable, not a second name for them
    priority: tuple[int, ...] | None = None
    #: names under which parameters are reported (default: ``parameters``)
    report_names: tuple[str, ...] | None = None
    #: how the effect enters the static model and the run (torque) model, in words
    static_model: str = ""
    run_model: str = ""
    #: which part of run data shows it: "uv/vu" (the friction half-differences of UV/VU
    #: pairs, :mod:`elastocal.identify.friction`), "sweep" (joint-2 sweep means,
    #: :mod:`elastocal.identify.compensator`), or None (run data cannot show it)
    run_part: Optional[str] = None
    #: only absolute positions show it (deflections cancel it): the absolute fit
    #: (identify/absolute.py) identifies it jointly with the registration
    absolute_only: bool = False
    #: "uv/vu" effects: (speed |dq| [rad/s], load torque [N·m]) of one joint's matched
    #: samples -> this effect's column of the friction regression (per unit parameter);
    #: the friction fits and the run diagnosis take their columns from here
    run_column: Optional[Callable[[np.ndarray, np.ndarray], np.ndarray]] = None
    #: the run data that separate it from the effects before it, in words (for the refusal)
    run_needs: str = ""
    #: "sweep" effects: the joint-2 sweep means -> this effect's SweepTerm, or the
    #: reason these sweeps (or the robot description) cannot hold it
    sweep_term: Optional[Callable[[SweepContext], "SweepTerm | str"]] = None
    #: its parameters correct the robot's kinematic description (DH errors, marker positions):
    #: the absolute fit identifies them with the registration, a calibration holding it describes
    #: a corrected robot (identify/kinematics.py)
    geometry: bool = False
    #: its parameters are the tracker's placement, the registration every absolute fit makes:
    #: reported as findings only when the model holds it
    registration: bool = False
    #: it belongs to the measuring session, not to the robot (a drift, the tracker's placement): a
    #: calibration's prediction for another session leaves it out, a check refits it
    session: bool = False
    #: a table without loads shows it, as the twist under the robot's own weight
    #: (identify/absolute_only.py)
    self_weight: bool = False
    #: a table without loads shows it through the times of its readings alone (a drift over the
    #: session): the absolute fit takes it beside the geometry and the registration
    shown_by_times: bool = False
    #: (robot, dataset) -> why an absolute-only table cannot test it (diagnose/absolute_only.py), or
    #: None when it can; None here: such tables never test it
    absolute_only_refusal: Optional[Callable[[object, object], Optional[str]]] = None
    #: the effects an absolute fit that tests it as a candidate fits with it (diagnose/absolute.py)
    fitted_with: tuple[str, ...] = ()
    #: absolute positions show it far more than deflections do (a drift over the hours of an
    #: experiment, the deflections seconds apart): a diagnosis tests it on them too (diagnose/static.py)
    absolute_shows_more: bool = False
    #: how compensation treats it (:class:`Compensation`)
    compensation: Compensation = Compensation.UNMODELLED
    #: robot -> this effect sized for that robot's joints (module docstring); None: the
    #: parameters do not depend on the robot
    sized: Optional[Callable[[object], "Effect"]] = None
    #: joint compliances c (N,) [rad/(N·m)] -> (p,) the smallest size of each parameter worth
    #: finding: the size a discriminating experiment must show (design/discriminate.py); None:
    #: the effect is no target of one (it can still be a rival)
    design_size: Optional[Callable[[np.ndarray], np.ndarray]] = None

    def for_robot(self, robot) -> "Effect":
        """The effect with the parameters of ``robot``'s joints (itself when they do not depend on it)."""
        if robot is None or self.sized is None or self.selected_from is not None:
            return self
        return self.sized(robot)

    @property
    def run_prefix(self) -> str:
        """Per-joint parameter prefix (``fc`` of fc1..fc6) of a "uv/vu" effect."""
        return self.parameters[0].rstrip("0123456789")

    @property
    def reported_names(self) -> tuple[str, ...]:
        return self.report_names if self.report_names is not None else self.parameters

    def restricted(self, keep) -> "Effect":
        """The effect with only the parameters ``keep`` (the others held at zero)."""
        full = self.selected_from if self.selected_from is not None else self.parameters
        base = self if self.selected_from is None else self._unrestricted
        idx = [full.index(n) for n in keep]
        names = tuple(full[i] for i in idx)
        inner = base.static_basis
        inner_absolute = base.absolute_basis
        sens = base.torque_sensitivity

        def basis(ctx: StaticContext) -> StaticBasis:
            b = inner(ctx) if inner is not None else StaticBasis()
            return StaticBasis(theta=None if b.theta is None else b.theta[..., idx],
                               links=None if b.links is None else b.links[..., idx],
                               add=None if b.add is None else b.add[..., idx])

        def absolute(ctx: StaticContext) -> AbsoluteBasis:
            b = inner_absolute(ctx)
            return AbsoluteBasis(theta=None if b.theta is None else b.theta[..., idx],
                                 links=None if b.links is None else b.links[..., idx],
                                 add=None if b.add is None else b.add[..., idx])

        def sensitivity(ctx: StaticContext, values: np.ndarray) -> np.ndarray:
            v = np.zeros(len(full))
            v[idx] = values
            return sens(ctx, v)

        from dataclasses import replace

        out = replace(base, parameters=names, units=tuple(base.units[i] for i in idx), static_basis=basis,
                      absolute_basis=None if inner_absolute is None else absolute,
                      torque_sensitivity=None if sens is None else sensitivity, selected_from=full,
                      priority=None if base.priority is None else tuple(base.priority[i] for i in idx),
                      report_names=None if base.report_names is None else tuple(base.report_names[i] for i in idx))
        object.__setattr__(out, "_unrestricted", base)
        return out

    def absolute(self, ctx: StaticContext) -> AbsoluteBasis:
        """The bases per state of the absolute model, full-sized (module docstring)."""
        ds = ctx.dataset
        p = len(self.parameters)
        n_states, n_markers = len(ctx.tau), len(ds.markers)
        b = self.absolute_basis(ctx) if self.absolute_basis is not None else None
        if b is None:
            s = self.static_basis(ctx) if self.static_basis is not None else StaticBasis()
            add = None
            if s.add is not None:
                add = np.zeros((n_states, n_markers, 3, p))
                add[ds.defl_state, ds.defl_marker] = s.add
            b = AbsoluteBasis(theta=s.theta, links=s.links, add=add)
        n_joints, n_springs = ctx.tau.shape[1], ctx.delta_link_moment.shape[1]
        return AbsoluteBasis(theta=np.zeros((n_states, n_joints, p)) if b.theta is None else b.theta,
                             links=np.zeros((n_states, n_springs, p)) if b.links is None else b.links,
                             add=np.zeros((n_states, n_markers, 3, p)) if b.add is None else b.add)

    def reported(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.report is None:
            return values, np.ones_like(values)
        return self.report(values)


#: the joints of the effects' default table (docs/cli.md): a six-axis revolute arm
DEFAULT_N_JOINTS = 6


def joint_names(prefix: str, robot=None) -> tuple[str, ...]:
    """``prefix1 .. prefixN`` for the robot's N joints (six without a robot)."""
    n = DEFAULT_N_JOINTS if robot is None else robot.n_joints
    return tuple(f"{prefix}{j}" for j in range(1, n + 1))


def joint_units(revolute: str, prismatic: str, robot=None) -> tuple[str, ...]:
    """Per joint, the unit of a revolute joint's parameter or of a prismatic joint's."""
    if robot is None:
        return (revolute,) * DEFAULT_N_JOINTS
    return tuple(prismatic if k.value == "prismatic" else revolute for k in robot.joint_kinds)


def diagonal_basis(values: np.ndarray) -> np.ndarray:
    """(S, n) -> (S, n, n) with values on the diagonal."""
    s, n = values.shape
    out = np.zeros((s, n, n))
    idx = np.arange(n)
    out[:, idx, idx] = values
    return out


def strongest(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> int:
    """Index of the parameter the data show most clearly (largest |value/std|)."""
    z = np.abs(values) / np.where(stds > 0, stds, np.inf)
    return int(np.argmax(z))


#: a value this many std on the wrong side of zero is a wrong sign, not noise
WRONG_SIGN_STD = 3.0


def wrong_sign(names, values, stds, words: str) -> str | None:
    """Reason when some parameter that must be positive is significantly negative."""
    bad = [(n, v, s) for n, v, s in zip(names, values, stds) if v < -WRONG_SIGN_STD * max(s, 0.0)]
    if not bad:
        return None
    n, v, s = min(bad, key=lambda x: x[1] / x[2] if x[2] > 0 else -np.inf)
    return f"{words} of the wrong sign ({n} = {v:.3g}, {abs(v) / s:.0f} std below zero)" if s > 0 else \
        f"{words} of the wrong sign ({n} = {v:.3g})"
