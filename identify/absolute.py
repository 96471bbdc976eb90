"""The absolute fit: geometry, tracker registration and elasticity together.

Every static table holds the absolute marker positions in the tracker's frame
(docs/formats.md §2). The model of each state's mean reading (docs/architecture.md,
"Absolute and relative"; docs/physics.md, "Absolute positions") is

    p_tracker = R · FK(θ) · p_marker + t,   θ = q + offset + Δθ_kin + Δθ_elastic

with FK from Pinocchio on the robot rebuilt from the corrected DH table
(identify/kinematics.py), ``Δθ_elastic`` and the located compliance from the
static effects' bases per state (``Effect.absolute``: the joint springs carry the
absolute torques ``ξ i``, the link springs and a tilting base the moments of the
robot's weight and of the whole load, so the gravity sag is in the model; a drift
moves every reading) and ``R, t`` the registration (identify/registration.py). A loaded
state's reading is its reference's plus the deflection, so fitting the absolute
positions of all states fits the absolute positions and the deflections
together; the readings are weighted by their noise (the tracker's repeatability
per marker, the currents' propagated through ``c`` into each state's joint
angles), block by block (one block per state: its markers share its currents).

* Without ``tracker_frame`` or ``kinematic_errors`` in the model, the elastic
  parameters are those of the deflection fit and the registration is the
  closed-form rigid fit (Kabsch) of the model's predictions: the "absolute
  comparison" of every identification.
* With them, everything is refined by Gauss-Newton with halved steps from that
  start: the elastic parameters, the 6 DoF of the registration and the
  identifiable set of kinematic parameters, which a QR of the stacked, whitened
  regressor chooses (elastic parameters first, then the frame, the markers, the
  DH errors joint by joint); what it drops is reported as absorbed, with what
  absorbs it.

Standard deviations come from the covariance of the weighted fit; the
absolute noise floor is what the noise alone would leave, ``trace((I - H) Σ)``.

Why one module over 500 lines: the absolute model, its noise weighting and its
solver share one private setup (:class:`_Setup`) of one fit; the geometry and the
registration it uses are in identify/kinematics.py and identify/registration.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import Arg, InputError
from elastocal.identify import kinematics as kin
from elastocal.identify.blas import one_blas_thread
from elastocal.model.effects import BASE_EFFECT, absolute_effects, get_effect, having
from elastocal.identify.level import LevelBases, level_bases
from elastocal.identify.registration import Registration, kabsch, register
from elastocal.identify.toolpoints import ToolPoints, find_tool_points, fit_tool_points, needs_prefit, usable
from elastocal.model.kinds import KinematicForm, NoiseSource, TorqueSource, expect
from elastocal.model.robot import MARKER_PREFIX, Robot
from elastocal.identify.dataset import StaticDataset, build_dataset
from elastocal.identify.static import Parameter, StaticFit, identify_static
from elastocal.identify.staticmodel import Problem, absolute_bases, kinematics, state_torques, static_context
from elastocal.identify.absolute_only import absolute_only_start, is_absolute_only
from elastocal.formats.tables import StaticTable

#: effects only absolute positions show (docs/cli.md, effect table)
ABSOLUTE_EFFECTS = absolute_effects()
FRAME_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
#: std per axis of a prior tracker position (cell.toml's base_p_tracker: a tape measure) [m]
TRACKER_PRIOR_STD_M = 0.1
#: the fit leaves an unexplained residual above this x its floor at this p (diagnose's rule, stepwise.py)
UNEXPLAINED_RATIO = 1.3
UNEXPLAINED_P = 1e-3
#: the tracker noise assumed for weights when the table holds no repeated readings [m]
UNIT_NOISE_M = 1e-5


def has_absolute_positions(robot: Robot, ds: StaticDataset) -> bool:
    """Whether the dataset's x, y, z are absolute positions of this robot's markers
    (a rigid fit of the nominal model leaves less than registration.PLAUSIBLE_RMS_M)."""
    return ds.abs_xyz is not None and register(robot, ds) is not None


def split_model(model: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(static effects, absolute effects) of a model."""
    return (tuple(m for m in model if m not in ABSOLUTE_EFFECTS),
            tuple(m for m in model if m in ABSOLUTE_EFFECTS))


@dataclass(frozen=True, eq=False)
class AbsoluteFit:
    """Result of an absolute fit (see the module docstring)."""

    model: tuple[str, ...]
    static: StaticFit                       # the deflection fit the absolute fit starts from
    parameters: tuple[Parameter, ...]       # reported: elastic, then tracker_frame and kinematic_errors ones
    unidentifiable: tuple[str, ...]
    absorbed_by: Mapping[str, tuple[tuple[str, float], ...]]
    identifiable: kin.IdentifiableSet | None
    registration: Registration
    kinematic_names: tuple[str, ...]
    kinematic_values: np.ndarray            # every kinematic parameter (0 where absorbed)
    elastic_beta: np.ndarray                # the static model's parameters (static.beta_names)
    measured: np.ndarray = field(repr=False)    # (S, M, 3) tracker frame
    predicted: np.ndarray = field(repr=False)   # (S, M, 3)
    rms: float = 0.0
    max: float = 0.0
    n: int = 0
    noise_floor: float | None = None
    deflection_residuals: np.ndarray = field(default=None, repr=False)   # (D, 3) tracker frame
    deflection_rms: float = 0.0
    deflection_max: float = 0.0
    rss_whitened: float = 0.0
    n_params: int = 0
    iterations: int = 0
    tracker_prior: np.ndarray | None = None
    #: the tool-point pre-fit the full model started from (None: robot.toml's markers)
    tool_prefit: ToolPoints | None = None
    #: (S, M, 3, p) Jacobian of the predicted positions (tracker frame) in the fitted parameters
    #: at the solution, their names and values: what each parameter explains, reading by reading
    design: np.ndarray | None = field(default=None, repr=False)
    design_names: tuple[str, ...] = ()
    design_values: np.ndarray | None = field(default=None, repr=False)
    #: (S, 3M, 3M) noise covariance of each state's mean readings (tracker frame) [m²]
    state_cov: np.ndarray | None = field(default=None, repr=False)

    @property
    def residuals(self) -> np.ndarray:
        return self.measured - self.predicted

    @property
    def dataset(self) -> StaticDataset:
        """The deflection fit's dataset (deflections in base axes)."""
        return self.static.dataset

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def unexplained_ratio(self) -> float | None:
        """rms over the floor when the fit (with absolute effects) leaves significantly more than
        noise (above UNEXPLAINED_RATIO x the floor, chi-square p below UNEXPLAINED_P), else None."""
        if self.noise_floor is None or not self.noise_floor > 0 or not any(m in ABSOLUTE_EFFECTS for m in self.model):
            return None
        # scipy.special alone (not scipy.stats): a command that never asks this imports no scipy
        from scipy.special import chdtrc

        p = float(chdtrc(max(self.n - self.n_params, 1), self.rss_whitened))
        ratio = self.rms / self.noise_floor
        return ratio if ratio > UNEXPLAINED_RATIO and p < UNEXPLAINED_P else None

    @property
    def undetermined(self) -> dict[str, str]:
        """Joint stiffnesses these data do not determine, name -> why (StaticFit.undetermined)."""
        return self.static.undetermined

    def sensitivities(self) -> tuple:
        """The parameters this fit moves by more than 2 std from the deflection-only fit while it
        leaves an unexplained residual (identify/evidence.py ``sensitive_parameters``)."""
        from elastocal.identify.evidence import sensitive_parameters

        ratio = self.unexplained_ratio
        if ratio is None:
            return ()
        defl = {p.name: (p.value, p.std) for p in self.static.parameters}
        return sensitive_parameters(defl, {p.name: (p.value, p.std) for p in self.parameters if p.name in defl},
                                    ratio)

    def calibrated_robot(self, robot: Robot) -> Robot:
        """The robot with the identified kinematic corrections (the nominal one without them)."""
        if not np.any(self.kinematic_values):
            return robot
        return kin.corrected_robot(robot, self.kinematic_names, self.kinematic_values)

    def per_pose(self) -> list[dict]:
        """Absolute error per pose (unloaded reference): rms and max over its markers [m]."""
        ds = self.static.dataset
        out = []
        refs = np.flatnonzero(ds.state_ref == np.arange(ds.n_states))
        for s in refs:
            e = np.linalg.norm(self.residuals[s], axis=1)
            out.append({"pose": ds.pose_ids[ds.state_pose[s]], "rms": float(np.sqrt(np.mean(e ** 2))),
                        "max": float(e.max())})
        return out

    def json_fields(self) -> dict:
        """What the absolute fit adds to ``identify --json`` (docs/cli.md)."""
        reg = self.registration
        out = {"absolute_residual": {"rms": self.rms, "max": self.max, "n": self.n, "unit": "m"},
               "absolute_noise_floor": self.noise_floor,
               "registration": {"rotation": reg.rotation.tolist(), "translation": reg.translation.tolist(),
                                "base_p_tracker": reg.base_p_tracker.tolist()}}
        if self.tracker_prior is not None:
            out["registration"]["prior"] = {
                "base_p_tracker": [float(v) for v in self.tracker_prior], "std": TRACKER_PRIOR_STD_M,
                "offset": float(np.linalg.norm(reg.base_p_tracker - np.asarray(self.tracker_prior))), "unit": "m"}
        if self.tool_prefit is not None:        # optional: where the pre-fit found the markers (flange frame)
            out["tool_prefit"] = {"rms": self.tool_prefit.rms, "unit": "m", "flange_p_markers": {
                m: [float(v) for v in p] for m, p in zip(self.tool_prefit.markers, self.tool_prefit.flange_p_markers)}}
        if self.absorbed_by:
            out["absorbed_by"] = {name: kin.absorbed_words(name, combo) for name, combo in self.absorbed_by.items()}
        return out

    def to_json(self) -> dict:
        """The ``identify --json`` object (docs/cli.md), deflection residual included."""
        out = self.static.to_json()
        out["model"] = list(self.model)
        from elastocal.identify.evidence import mark_sensitive, mark_stiffness, mark_twins

        marks = self.sensitivities()
        out["parameters"] = mark_sensitive(mark_twins(mark_stiffness(
            {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in self.parameters}),
            self.static.undetermined), marks)
        if marks:
            out["sensitive"] = [m.to_json() for m in marks]
        if is_absolute_only(self.static.dataset):    # no deflections: the absolute positions are the data
            out["residual"] = {"rms": self.rms, "max": self.max, "n": self.n, "unit": "m"}
            out["noise_floor"] = self.noise_floor
        elif any(m in ABSOLUTE_EFFECTS for m in self.model):
            out["residual"] = {"rms": self.deflection_rms, "max": self.deflection_max,
                               "n": int(self.deflection_residuals.size), "unit": "m"}
        if self.unidentifiable:
            out["unidentifiable"] = list(self.unidentifiable)
        out.update(self.json_fields())
        return out


# ===================================================================== model
@dataclass(frozen=True, eq=False)
class _Setup:
    robot: Robot
    ds: StaticDataset          # deflections in base axes (the static fit's)
    bases: tuple[np.ndarray, np.ndarray, np.ndarray]    # per state: theta, links, add (S, M, 3, p)
    frames: tuple[str, ...]
    kin_names: tuple[str, ...]
    rot0: np.ndarray
    t0: np.ndarray
    whiten: tuple[np.ndarray, ...]      # per state: inverse Cholesky factor of its (3M, 3M) covariance
    chol: tuple[np.ndarray, ...]
    y: np.ndarray                       # (S, M, 3) measured, tracker frame
    kin_columns: kin.Columns | None = None
    level: LevelBases | None = None     # the base's tilt from level: its joint-angle columns

    @property
    def level_names(self) -> tuple[str, ...]:
        return self.level.names if self.level is not None else ()


def _unpack(st: _Setup, x: np.ndarray, n_el: int):
    beta = x[:n_el]
    dr = x[n_el:n_el + 3]
    t = x[n_el + 3:n_el + 6]
    kv = x[n_el + 6:n_el + 6 + len(st.kin_names)]
    return beta, dr, t, kv


def _lev(st: _Setup, x: np.ndarray, n_el: int) -> np.ndarray:
    """The base's tilt and its nuisance products (after the kinematic parameters)."""
    return x[n_el + 6 + len(st.kin_names):]


def _model(st: _Setup, beta: np.ndarray, dr: np.ndarray, dt: np.ndarray, kv: np.ndarray, *, jacobian: bool,
           lev: np.ndarray | None = None, chain_frame: bool = False):
    """Predicted tracker positions (S, M, 3) and their Jacobian (S, M, 3, n_el + 6 + n_kin + n_level).

    The registration is ``p_tracker = R0 (exp(dr) p + dt) + t0``: ``dr`` and
    ``dt`` are a rotation about and a translation along the base axes (so that
    "dq1 is absorbed by the rotation about z" reads as it is). With ``chain_frame`` the frame's
    rotation columns turn the chain's positions without the additive deflections: the geometry's
    columns do not turn those either (a turn of the whole chain times a deflection is second order,
    left out of the model), so a joint-1 error that turns the whole chain (the zero of a revolute
    joint 1, the theta of a track's carriage about its axis) is then exactly the frame's."""
    ds = st.ds
    robot = kin.corrected_robot(st.robot, st.kin_names, kv) if st.kin_names and np.any(kv) else st.robot
    b_theta, b_links, b_add = st.bases
    n_el, n_k = len(beta), len(st.kin_names)
    b_lev = st.level.theta if st.level is not None else np.zeros((ds.n_states, robot.n_joints, 0))
    n_lev = b_lev.shape[2]
    turn = pin.exp3(dr)
    dtheta = b_theta @ beta + (b_lev @ lev if n_lev else 0.0)
    dlink = b_links @ beta
    markers = list(ds.markers)
    nm = len(markers)
    pos = np.empty((ds.n_states, nm, 3))
    jac = np.zeros((ds.n_states, nm, 3, n_el + 6 + n_k + n_lev)) if jacobian else None
    data = robot.create_data()          # this evaluation's (the corrected robot is a new model)
    batch = jacobian and n_k and not np.any(dlink)
    if batch:       # the geometry's Jacobian of every state at once (no bent links)
        theta_all = ds.q[ds.state_pose] + robot.offsets + dtheta
        pos[:], jac[..., n_el + 6:n_el + 6 + n_k] = kin.position_jacobian_batch(robot, theta_all, markers, st.kin_names,
                                                                  st.kin_columns, data)
    for s in range(ds.n_states):
        if batch and not n_el and not n_lev:
            break
        theta = robot.theta(ds.q[ds.state_pose[s]]) + dtheta[s]
        if not jacobian:
            pos[s] = robot.positions(robot.theta_links(theta, dlink[s]), markers, links=True, data=data)
            continue
        p, j10 = kinematics(robot, robot.theta_links(theta, dlink[s]), st.frames, data)
        pos[s] = p
        j_el = (j10[:, :, robot.actuated_in_link_model] @ b_theta[s]
                + j10[:, :, robot.springs_in_link_model] @ b_links[s])
        jac[s, :, :, :n_el] = j_el
        if n_lev:
            jac[s, :, :, n_el + 6 + n_k:] = j10[:, :, robot.actuated_in_link_model] @ b_lev[s]
        if n_k and not batch:
            _, jk = kin.position_jacobian(robot, theta, markers, st.kin_names, st.kin_columns,
                                          dlink[s] if np.any(dlink[s]) else None, data=data)
            jac[s, :, :, n_el + 6:n_el + 6 + n_k] = jk
    chain = pos @ turn.T if chain_frame else None
    pos += b_add @ beta
    if jacobian:
        jac[..., :n_el] += b_add
    turned = pos @ turn.T
    out = (turned + dt) @ st.rot0.T + st.t0
    if jacobian:
        jac[..., :n_el] = np.einsum("ij,smjk->smik", turn, jac[..., :n_el])
        jac[..., n_el + 6:] = np.einsum("ij,smjk->smik", turn, jac[..., n_el + 6:])
        jl = pin.Jexp3(-dr)                       # left Jacobian of exp at dr
        arm = turned if chain is None else chain
        skew = np.zeros((ds.n_states, nm, 3, 3))
        skew[..., 0, 1], skew[..., 0, 2] = -arm[..., 2], arm[..., 1]
        skew[..., 1, 0], skew[..., 1, 2] = arm[..., 2], -arm[..., 0]
        skew[..., 2, 0], skew[..., 2, 1] = -arm[..., 1], arm[..., 0]
        jac[..., n_el:n_el + 3] = -skew @ jl
        jac[..., n_el + 3:n_el + 6] = np.eye(3)
        jac = np.einsum("ij,smjk->smik", st.rot0, jac)
    return out, jac


def _noise(robot: Robot, ds: StaticDataset, torque: TorqueSource, compliance: np.ndarray, rot: np.ndarray,
           frames: Sequence[str]) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...], bool]:
    """Per-state Cholesky factors of the covariance of the mean readings (tracker
    frame), and whether the noise level is known: from the repeats, else the readings' own
    uncertainty columns, else the tracker's law (``ds.noise_source``)."""
    columns = ds.stated_variance is not None
    known = ds.sigma_tracker is not None or columns
    sig_t = ds.sigma_tracker if ds.sigma_tracker is not None else UNIT_NOISE_M
    nm = len(ds.markers)
    # each reading's own covariance (the columns', or the law's at its range and beam)
    own = ds.reading_cov if known else None
    sig_i = ds.sigma_current if (known and torque is TorqueSource.CURRENT and ds.sigma_current is not None) else None
    covs = np.zeros((ds.n_states, 3 * nm, 3 * nm))
    jac_pose: dict[int, np.ndarray] = {}
    data = robot.create_data()
    for s in range(ds.n_states):
        cov = np.zeros((3 * nm, 3 * nm))
        for m in range(nm):
            cov[3 * m:3 * m + 3, 3 * m:3 * m + 3] += (sig_t ** 2 / ds.abs_n[s, m] * np.eye(3) if own is None
                                                      else own[s, m])
        if sig_i is not None:
            pi = int(ds.state_pose[s])
            if pi not in jac_pose:
                _, j10 = kinematics(robot, robot.theta_links(robot.theta(ds.q[pi])), frames, data)
                jac_pose[pi] = np.einsum("ij,mjk->mik", rot, j10[:, :, robot.actuated_in_link_model]).reshape(
                    3 * nm, robot.n_joints)
            g = jac_pose[pi] * (compliance * robot.torque_constants)
            cov += (g * (sig_i ** 2 / ds.state_n_currents[s])) @ g.T
        covs[s] = cov
    chols = np.linalg.cholesky(covs)          # one batched call: small LAPACK calls are slow on a busy machine
    whitens = np.linalg.inv(chols)
    return tuple(chols), tuple(whitens), known


def _whitened(st: _Setup, r: np.ndarray, jac: np.ndarray | None):
    """Whitened residual (n,) and Jacobian (n, p) from (S, M, 3) and (S, M, 3, p)."""
    ns, nm = r.shape[0], r.shape[1]
    w = np.asarray(st.whiten)
    rw = np.einsum("sij,sj->si", w, r.reshape(ns, 3 * nm)).reshape(-1)
    if jac is None:
        return rw, None
    jw = np.einsum("sij,sjp->sip", w, jac.reshape(ns, 3 * nm, -1)).reshape(ns * 3 * nm, -1)
    return rw, jw


@dataclass(frozen=True, eq=False)
class _Sag:
    """Where a table without loads has the robot's own weight act: the (S, N) link-side angles
    it sags to and the geometry it sags on (the first pass's corrected robot)."""

    theta: np.ndarray
    robot: Robot
    beta: np.ndarray             # the first pass's elastic parameters
    identified: np.ndarray       # which of them the table determines


@dataclass(frozen=True, eq=False)
class _Start:
    """Where the absolute fit starts: the robot (with the tool-point pre-fit's markers), the
    deflection fit (or an absolute-only table's rigid start), the model's bases per state and
    the kinematic parameters the model fits."""

    robot: Robot                  # robot.toml's, or with the pre-fit's markers
    tools: ToolPoints | None      # the tool-point pre-fit (None: robot.toml's markers)
    registration: Registration    # the nominal model's (or the pre-fit's) rigid registration
    kin_names: tuple[str, ...]
    fit: StaticFit
    effects: tuple
    pr: Problem
    bases: tuple[np.ndarray, np.ndarray, np.ndarray]
    el_mask: np.ndarray           # the elastic parameters the deflection fit identified
    level: LevelBases | None = None   # the base's tilt beside self-weight springs (second pass)


@dataclass(frozen=True, eq=False)
class _Solved:
    """The free parameters (elastic, frame, kinematic) and their values at the solution."""

    x_full: np.ndarray
    free: np.ndarray              # (n_el + 6 + n_kin,) bool
    ident: kin.IdentifiableSet | None
    iterations: int

    @property
    def idx(self) -> np.ndarray:
        return np.flatnonzero(self.free)


@dataclass(frozen=True, eq=False)
class _AbsoluteUncertainty:
    """The solution's prediction, covariance of the free parameters and the noise floor."""

    pred: np.ndarray              # (S, M, 3) tracker frame
    jac: np.ndarray               # (S, M, 3, n_el + 6 + n_kin)
    cov_free: np.ndarray
    floor: float | None
    rss_whitened: float
    n_params: int


@one_blas_thread
def identify_absolute(robot: Robot, data: StaticTable | StaticDataset, *,
                      model: Sequence[str] = ("joint_stiffness",), torque: TorqueSource = TorqueSource.CURRENT,
                      form: KinematicForm = KinematicForm.EXACT, max_iter: int = 30,
                      tracker_prior: Sequence[float] | None = None,
                      excess_var: float | None = None, _sag: _Sag | None = None) -> AbsoluteFit:
    """Compare the model with the absolute positions (and fit the absolute
    effects of ``model`` jointly with the rest); see the module docstring.

    ``tracker_prior``: where the tracker stands in base coordinates [m] as the
    cell knows it (cell.toml's ``[tracker] base_p_tracker``): a prior of
    :data:`TRACKER_PRIOR_STD_M` per axis on the registration when it is fitted,
    and reported against the registration found.

    Readings that state their own uncertainty (``u95`` or ``sx, sy, sz``) and are not
    repeated are weighted by it plus what the model leaves unexplained: each coordinate
    by ``1 / (sigma_i^2 + s^2)``, ``s^2`` the excess variance that makes the weighted
    residual its degrees of freedom (0 on a complete model; far above the readings' own
    noise, the weights even out and a few very precise readings do not pull the fit);
    ``excess_var`` fixes ``s^2`` [m²]. The noise floor is then what the stated noise
    alone would leave.

    On a table without loads the twist under the robot's own weight is exact: the weight's
    torques are taken at the configuration it sags to, on the geometry the fit found (the
    robot sags on its as-built links, not on the drawing's), by refitting once from the
    first fit's sag and geometry (``_sag``, internal)."""
    expect(TorqueSource, torque, "torque")
    expect(KinematicForm, form, "form")
    ds0 = data if isinstance(data, StaticDataset) else build_dataset(data)
    stated = ds0.noise_source is NoiseSource.UNCERTAINTY_COLUMNS and is_absolute_only(ds0)
    if stated and excess_var is None:      # a first fit with even weights, then s^2 from its residual
        kwargs = dict(model=model, torque=torque, form=form, max_iter=max_iter, tracker_prior=tracker_prior,
                      _sag=_sag)
        first = identify_absolute(robot, ds0, excess_var=float(np.max(ds0.stated_variance)) * 1e6, **kwargs)
        s2 = excess_variance(first.residuals, ds0.stated_variance, first.n_params)
        return identify_absolute(robot, ds0, excess_var=s2, **kwargs)
    only = is_absolute_only(ds0)      # no loads: geometry, registration, the twist under self-weight
    names = tuple(dict.fromkeys(model if only else [BASE_EFFECT, *model]))
    static_model, absolute = split_model(names)
    start = _start(robot, ds0, static_model, absolute, torque=torque, form=form,
                   sag=_sag if only else None, only=only)
    st, known = _setup(start, ds0, excess_var if stated else None)
    solved = _solve(st, start, absolute, max_iter=max_iter, tracker_prior=tracker_prior)
    fit, n_el = start.fit, len(start.fit.beta_names)
    unc = _uncertainty(st, solved, n_el, ds0, known, excess_var if stated else None)
    beta, dr, dt, kv = _unpack(st, solved.x_full, n_el)
    if only and fit.beta_names and _sag is None and np.any(beta):
        # the weight's torques at the configuration it sags to, on the geometry found (the first
        # pass took them at the commanded configuration of the drawing's geometry)
        built = kin.corrected_robot(start.robot, st.kin_names, kv) if st.kin_names else start.robot
        theta = start.pr.ds.q[start.pr.ds.state_pose] + built.offsets + start.bases[0] @ beta
        return identify_absolute(start.robot, ds0, model=model, torque=torque, form=form, max_iter=max_iter,
                                 tracker_prior=tracker_prior, excess_var=excess_var,
                                 _sag=_Sag(theta, built, beta.copy(), start.el_mask))
    return _absolute_fit(st, start, solved, unc, ds0, names=names, absolute=absolute, nominal_robot=robot,
                         tracker_prior=tracker_prior)


def _start(robot: Robot, ds0: StaticDataset, static_model: tuple[str, ...], absolute: tuple[str, ...], *,
           torque: TorqueSource, form: KinematicForm, sag: _Sag | None, only: bool) -> _Start:
    """The registration (after the tool-point pre-fit when robot.toml's markers leave the
    readings unexplained), the deflection fit and the model's absolute bases at its solution."""
    reg = register(robot, ds0) if ds0.abs_xyz is not None else None
    geometry = bool(having("geometry", absolute))       # the model corrects the robot's geometry and markers
    tools = _tool_prefit(robot, ds0, reg, fits_markers=geometry)
    if tools is not None:              # the full model starts from the markers the pre-fit found
        robot, reg = tools.robot(robot), tools.registration
    if reg is None:
        raise InputError("this table holds no absolute positions of the robot's markers (a rigid fit of the "
                         "model leaves more than 5 cm, or too few points to fix a rotation); "
                         f"{' and '.join(absolute) or 'an absolute comparison'} needs them", source=ds0.source)
    kin_names = kin.parameter_names(robot, ds0.markers) if geometry else ()
    work = robot.create_data()        # the static fit's and the absolute bases' buffers
    if only:
        fit = absolute_only_start(robot, ds0, static_model)
        torque, form = fit.torque, fit.form
    else:
        fit = identify_static(robot, ds0, model=static_model, torque=torque, form=form, work=work)
    ds = fit.dataset
    effects = fit.effects or tuple(get_effect(n, robot) for n in static_model)   # as fitted (selected components)
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    pr = Problem(robot, ds, effects, torque, form, frames, work)
    level = None
    if fit.beta_names:
        sagged = replace(pr, robot=sag.robot, data=None) if sag is not None else None
        tau = state_torques(pr, None) if sag is None else state_torques(sagged, sag.theta)
        iterative = any(e.iterative for e in effects)
        bases = absolute_bases(pr, static_context(pr, tau, fit.beta if iterative else None))
        if sag is not None and absolute:     # the weight's direction beside the springs the first pass found
            units = tuple(u for e in effects for u in e.units)
            level = level_bases(sagged, sag.theta, sag.beta, sag.identified, fit.beta_names, units)
    else:                             # a rigid model: no elastic parameters
        bases = (np.zeros((ds.n_states, robot.n_joints, 0)),
                 np.zeros((ds.n_states, len(robot.springs_in_link_model), 0)),
                 np.zeros((ds.n_states, len(ds.markers), 3, 0)))
    return _Start(robot=robot, tools=tools, registration=reg, kin_names=kin_names, fit=fit, effects=effects, pr=pr,
                  bases=bases, el_mask=_elastic_mask(fit, effects), level=level)


def _setup(start: _Start, ds0: StaticDataset, excess_var: float | None) -> tuple[_Setup, bool]:
    """The deflection fit's elasticity registered in closed form, and the readings' weights:
    the noise of the mean readings, or (``excess_var`` given) the readings' own stated
    variance plus the excess, per coordinate. Also whether the noise level is known."""
    robot, fit, pr = start.robot, start.fit, start.pr
    ds, frames, y = pr.ds, pr.frames, ds0.abs_xyz
    st0 = _Setup(robot, ds, start.bases, frames, (), np.eye(3), np.zeros(3), (), (), y)
    base_p, _ = _model(st0, fit.beta, np.zeros(3), np.zeros(3), np.zeros(0), jacobian=False)
    rigid = kabsch(base_p.reshape(-1, 3), y.reshape(-1, 3), ds0.abs_n.reshape(-1)) or start.registration
    chols, whitens, known = _noise(robot, ds, pr.torque, fit.beta[:robot.n_joints], rigid.rotation, frames)
    if excess_var is not None:
        total = (ds0.stated_variance + excess_var).reshape(ds.n_states, -1)
        chols = tuple(np.apply_along_axis(np.diag, 1, np.sqrt(total)))
        whitens = tuple(np.apply_along_axis(np.diag, 1, 1.0 / np.sqrt(total)))
        known = True
    st = _Setup(robot, ds, start.bases, frames, start.kin_names, rigid.rotation, rigid.translation, whitens, chols,
                y, kin.columns(start.kin_names, ds.markers), start.level)
    return st, known


def _solve(st: _Setup, start: _Start, absolute: tuple[str, ...], *, max_iter: int,
           tracker_prior: Sequence[float] | None) -> _Solved:
    """Without absolute effects, the registration alone is free (the closed-form start is the
    answer). With them, the elastic parameters the deflections identified, the frame and the
    identifiable kinematic parameters (a QR of the whitened regressor: elastic first, then the
    frame, the markers, the DH errors) refined by Gauss-Newton."""
    fit, kin_names, el_mask = start.fit, start.kin_names, start.el_mask
    n_el = len(fit.beta_names)
    lev_names = st.level_names
    x_full = np.concatenate([fit.beta, np.zeros(6), np.zeros(len(kin_names) + len(lev_names))])
    if not absolute:
        return _Solved(x_full, np.concatenate([np.zeros(n_el, dtype=bool), np.ones(6, dtype=bool)]), None, 0)
    all_names = (*fit.beta_names, *FRAME_NAMES, *kin_names, *lev_names)
    free = np.concatenate([el_mask, np.ones(6, dtype=bool), np.zeros(len(kin_names) + len(lev_names), dtype=bool)])
    ident = None
    if kin_names or lev_names:
        # which parameters the data determine, decided on the model's own order: the frame turns the chain
        # as the geometry's columns do (_model, chain_frame)
        pred, jac = _model(st, *_unpack(st, x_full, n_el), jacobian=True, lev=_lev(st, x_full, n_el),
                           chain_frame=True)
        _, jw = _whitened(st, st.y - pred, jac)
        candidate = np.concatenate([el_mask, np.ones(6 + len(kin_names) + len(lev_names), dtype=bool)])
        cand_names = [n for n, k in zip(all_names, candidate) if k]
        markers_first = [n for n in kin_names if n.startswith(("dx_", "dy_", "dz_"))]
        # the geometry before the tilt: a tilt column is the weight's, which the geometry cannot carry
        priority = [n for n, k in zip(fit.beta_names, el_mask) if k] + list(FRAME_NAMES) + markers_first
        ident = kin.identifiable_set(jw[:, candidate], cand_names, priority)
        kept = dict(zip(cand_names, ident.keep))
        free = np.array([kept.get(n, False) for n in all_names])
    idx = np.flatnonzero(free)
    prior = None if tracker_prior is None else np.asarray(tracker_prior, dtype=float)

    def evaluate(xf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xx = x_full.copy()
        xx[idx] = xf
        p, j = _model(st, *_unpack(st, xx, n_el), jacobian=True, lev=_lev(st, xx, n_el))
        rw, jw_ = _whitened(st, st.y - p, j)
        jac_ = -jw_[:, idx]
        if prior is not None:       # three rows: the tracker's position against the cell's
            r_p, j_p = _prior_rows(st, xx, n_el, prior)
            rw = np.concatenate([rw, r_p])
            jac_ = np.vstack([jac_, j_p[:, idx]])
        return rw, jac_

    x_free, iterations = _gauss_newton(evaluate, x_full[idx], max_iter=max_iter)
    x_full = x_full.copy()
    x_full[idx] = x_free
    return _Solved(x_full, free, ident, iterations)


def _uncertainty(st: _Setup, solved: _Solved, n_el: int, ds0: StaticDataset, known: bool,
                 excess_var: float | None) -> _AbsoluteUncertainty:
    """Covariance of the free parameters and what noise alone would leave:
    ``trace(Σ) - trace(A (A^T Σ^-1 A)^-1 A^T)``, A the unwhitened Jacobian; with stated noise
    (``excess_var`` given) that of the stated noise alone, the fit weighted with the excess in."""
    pred, jac = _model(st, *_unpack(st, solved.x_full, n_el), jacobian=True, lev=_lev(st, solved.x_full, n_el))
    rw, jw = _whitened(st, st.y - pred, jac)
    idx = solved.idx
    a_w = jw[:, idx]
    p = len(idx)
    n = rw.size
    m_inv = np.linalg.pinv(a_w.T @ a_w)
    rss_w = float(rw @ rw)
    inflation = max(1.0, rss_w / max(n - p, 1)) if known else rss_w / max(n - p, 1)
    nm = len(st.ds.markers)
    a_raw = np.einsum("sij,sjp->sip", np.asarray(st.chol), jw[:, idx].reshape(st.ds.n_states, 3 * nm, -1))
    a_raw = a_raw.reshape(-1, len(idx))
    trace_sigma = float(np.sum(np.asarray(st.chol) ** 2))
    expected = trace_sigma - float(np.trace(m_inv @ (a_raw.T @ a_raw)))
    if excess_var is not None:
        v_read = ds0.stated_variance.reshape(-1)
        w = 1.0 / (v_read + excess_var)
        awv = a_raw.T * (w * v_read)                       # A^T W Sigma
        cross = float(np.trace(m_inv @ (awv @ a_raw)))      # tr(H Sigma)
        quad = float(np.trace(m_inv @ ((awv * w) @ a_raw) @ m_inv @ (a_raw.T @ a_raw)))   # tr(H Sigma H^T)
        expected = float(np.sum(v_read)) - 2.0 * cross + quad
    if not known:
        expected *= rss_w / max(n - p, 1)
    floor = float(np.sqrt(max(expected, 0.0) / n)) if known else None
    return _AbsoluteUncertainty(pred, jac, m_inv * inflation, floor, rss_w, p)


def _frame_parameters(st: _Setup, solved: _Solved, unc: _AbsoluteUncertainty, n_el: int) -> list[Parameter]:
    """The registration as reported: rotation vector of R and t (p_tracker = R p_base + t); their
    covariance from the base-axes perturbations through d log3 and R0."""
    _, dr, dt, _ = _unpack(st, solved.x_full, n_el)
    rot = st.rot0 @ pin.exp3(dr)
    t = st.rot0 @ dt + st.t0
    rvec = pin.log3(rot)
    pos_free = {c: k for k, c in enumerate(solved.idx)}
    cols = [pos_free[n_el + k] for k in range(6)]
    cov6 = unc.cov_free[np.ix_(cols, cols)]
    jmap = np.zeros((6, 6))
    jmap[:3, :3], jmap[3:, 3:] = pin.Jlog3(rot), st.rot0
    std6 = np.sqrt(np.clip(np.diag(jmap @ cov6 @ jmap.T), 0.0, None))
    return [Parameter(name, float(rvec[k]) if k < 3 else float(t[k - 3]), float(std6[k]), "rad" if k < 3 else "m")
            for k, name in enumerate(FRAME_NAMES)]


def _absolute_fit(st: _Setup, start: _Start, solved: _Solved, unc: _AbsoluteUncertainty, ds0: StaticDataset, *,
                  names: tuple[str, ...], absolute: tuple[str, ...], nominal_robot: Robot,
                  tracker_prior: Sequence[float] | None) -> AbsoluteFit:
    fit, kin_names, free, idx = start.fit, start.kin_names, solved.free, solved.idx
    n_el = len(fit.beta_names)
    beta, dr, dt, kv = _unpack(st, solved.x_full, n_el)
    pred, y = unc.pred, st.y
    ds = st.ds
    r_flat = (y - pred).reshape(-1)
    registration = Registration(rotation=st.rot0 @ pin.exp3(dr), translation=st.rot0 @ dt + st.t0,
                                rms=float(np.sqrt(np.mean(r_flat ** 2))))
    # deflections predicted by the same model, in the tracker frame
    d_pred = pred[ds.defl_state, ds.defl_marker] - pred[ds.defl_ref, ds.defl_marker]
    # measured deflections in the tracker frame (a dataset already turned to base axes is turned back)
    d_meas = ds0.dP if ds0.tracker_rotation is None else ds0.dP @ ds0.tracker_rotation.T
    d_res = d_meas - d_pred
    all_names = (*fit.beta_names, *FRAME_NAMES, *kin_names, *st.level_names)
    std_full = np.zeros(len(all_names))
    std_full[idx] = np.sqrt(np.clip(np.diag(unc.cov_free), 0.0, None))
    if not absolute:
        std_full[:n_el] = np.sqrt(np.clip(np.diag(fit.beta_cov), 0.0, None))
    params, unident = _report(fit, start.effects, beta, std_full[:n_el], start.el_mask)
    if having("registration", absolute):     # the tracker's placement is a finding of this model
        params += _frame_parameters(st, solved, unc, n_el)
    kv_total = np.where(free[n_el + 6:n_el + 6 + len(kin_names)], kv, 0.0) if kin_names else np.zeros(0)
    if start.tools is not None:        # marker corrections from robot.toml's positions: the pre-fit's and the fit's
        kv, kv_total = _with_prefit(start.tools, nominal_robot, kin_names, kv, kv_total)
    absorbed: dict[str, tuple[tuple[str, float], ...]] = {}
    if kin_names:
        for k, name in enumerate(kin_names):
            col = n_el + 6 + k
            if free[col]:
                params.append(Parameter(name, float(kv[k]), float(std_full[col]), kin.unit_of(name, start.robot)))
            else:
                unident.append(name)
    if solved.ident is not None:      # the geometry's words (the tilt is the weight's, never absorbed in words)
        absorbed = {n: c for n, c in solved.ident.absorbed_by.items() if n not in st.level_names}
    lev = _lev(st, solved.x_full, n_el)
    for k, name in enumerate(st.level_names):
        col = n_el + 6 + len(kin_names) + k
        if free[col]:             # the base's tilt from level and the products the calibration carries
            params.append(Parameter(name, float(lev[k]), float(std_full[col]), st.level.units[k]))
    return AbsoluteFit(
        model=names, static=fit, parameters=tuple(params), unidentifiable=tuple(unident), absorbed_by=absorbed,
        identifiable=solved.ident, registration=registration, kinematic_names=kin_names,
        kinematic_values=kv_total,
        elastic_beta=beta.copy(), measured=y, predicted=pred, rms=float(np.sqrt(np.mean(r_flat ** 2))),
        max=float(np.max(np.abs(r_flat))), n=int(r_flat.size), noise_floor=unc.floor, deflection_residuals=d_res,
        deflection_rms=float(np.sqrt(np.mean(d_res ** 2))) if d_res.size else 0.0,
        deflection_max=float(np.max(np.abs(d_res))) if d_res.size else 0.0,
        rss_whitened=unc.rss_whitened, n_params=unc.n_params, iterations=solved.iterations,
        tracker_prior=None if tracker_prior is None else np.asarray(tracker_prior, dtype=float),
        tool_prefit=start.tools,
        design=unc.jac[..., idx], design_names=tuple(all_names[i] for i in idx),
        design_values=solved.x_full[idx].copy(),
        state_cov=np.einsum("sij,skj->sik", np.asarray(st.chol), np.asarray(st.chol)))


def _tool_prefit(robot: Robot, ds: StaticDataset, nominal: Registration | None, *,
                 fits_markers: bool) -> ToolPoints | None:
    """The tool-point pre-fit (identify/toolpoints.py) when robot.toml's markers leave the
    readings unexplained (or explained only roughly): its placement to start the full model
    from, None to start from robot.toml's; refused naming the marker no placement explains."""
    if ds.abs_xyz is None or not needs_prefit(nominal):
        return None
    if nominal is None:
        tools = find_tool_points(robot, ds)
    else:
        tools = fit_tool_points(robot, ds)
        if tools is None or not usable(robot, tools, nominal):
            return None
    if not usable(robot, tools, nominal):
        return None
    if not fits_markers:
        if nominal is not None:
            return None
        far = ", ".join(f"{m} {np.linalg.norm(v) * 100:.3g} cm" for m, v in tools.moved(robot).items()
                        if np.linalg.norm(v) > 0.05)
        raise InputError(("the markers are far from robot.toml's [tool.markers] (a tool-point pre-fit moves ", far,
                          "); add kinematic_errors to ", Arg("model"), " to fit them, or correct robot.toml"),
                         source=ds.source)
    return tools


def _with_prefit(tools: ToolPoints, robot: Robot, kin_names: Sequence[str], kv: np.ndarray,
                 kv_total: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The marker corrections ``dx_/dy_/dz_`` counted from robot.toml's markers: the pre-fit's
    move plus the full fit's correction of it."""
    moved = tools.moved(robot)
    kv, kv_total = kv.copy(), kv_total.copy()
    for k, name in enumerate(kin_names):
        if name.startswith(("dx_", "dy_", "dz_")) and name[3:] in moved:
            kv[k] += moved[name[3:]]["xyz".index(name[1])]
            kv_total[k] += moved[name[3:]]["xyz".index(name[1])]
    return kv, kv_total


def excess_variance(residual: np.ndarray, variance: np.ndarray, n_params: int) -> float:
    """The variance ``s^2`` [m²] that, added to each coordinate's stated variance, makes the
    weighted residual sum its degrees of freedom: ``sum r^2 / (v + s^2) = n - p`` (0 when the
    stated noise already explains the residual)."""
    r2, v = np.asarray(residual).reshape(-1) ** 2, np.asarray(variance).reshape(-1)
    dof = max(r2.size - n_params, 1)

    def excess(s2: float) -> float:
        return float(np.sum(r2 / (v + s2))) - dof

    if excess(0.0) <= 0.0:
        return 0.0
    # excess falls monotonically from above 0 at s2 = 0 to below it at hi: bisection to the last bits
    # (scipy.optimize's import alone costs a command more than this whole fit)
    lo, hi = 0.0, float(np.max(r2)) * r2.size + float(np.max(v))
    while True:
        mid = 0.5 * (lo + hi)
        if not lo < mid < hi:
            return hi
        if excess(mid) > 0.0:
            lo = mid
        else:
            hi = mid


def _tracker_position(st: _Setup, x: np.ndarray, n_el: int) -> np.ndarray:
    """Where the registration puts the tracker, base coordinates: ``-R^T t``."""
    _, dr, dt, _ = _unpack(st, x, n_el)
    rot = st.rot0 @ pin.exp3(dr)
    return -rot.T @ (st.rot0 @ dt + st.t0)


def _prior_rows(st: _Setup, x: np.ndarray, n_el: int, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residual (3,) of the tracker position against its prior and its
    Jacobian (3, len(x)) (central differences in the frame's six: a closed form)."""
    here = _tracker_position(st, x, n_el)
    jac = np.zeros((3, len(x)))
    for k in range(n_el, n_el + 6):
        step = np.zeros(len(x))
        step[k] = 1e-7
        jac[:, k] = (_tracker_position(st, x + step, n_el) - _tracker_position(st, x - step, n_el)) / 2e-7
    return (prior - here) / TRACKER_PRIOR_STD_M, -jac / TRACKER_PRIOR_STD_M


def _gauss_newton(evaluate, x0: np.ndarray, *, max_iter: int, rel_tol: float = 1e-10) -> tuple[np.ndarray, int]:
    """Minimise ``|r(x)|^2`` by Gauss-Newton steps (LAPACK's least-squares solve of the
    column-scaled Jacobian, so that near-dependent columns cost nothing), a step
    halved until the cost falls (Levenberg-Marquardt's safeguard); ``evaluate(x)``
    returns ``(r, dr/dx)``. Converged when a step lowers the cost by less than
    ``rel_tol`` of itself: far below one standard deviation of any parameter."""
    x = np.array(x0, dtype=float)
    r, jac = evaluate(x)
    cost = float(r @ r)
    for iteration in range(1, max_iter + 1):
        scale = np.linalg.norm(jac, axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        step = np.linalg.lstsq(jac / scale, -r, rcond=np.finfo(float).eps)[0] / scale    # LAPACK's gelsd
        for _ in range(8):
            r_new, jac_new = evaluate(x + step)
            cost_new = float(r_new @ r_new)
            if cost_new <= cost:
                break
            step = step / 2.0
        else:
            return x, iteration
        x, r, jac = x + step, r_new, jac_new
        done = cost - cost_new <= rel_tol * cost
        cost = cost_new
        if done:
            return x, iteration
    return x, max_iter


def _reported_names(eff) -> tuple[str, ...]:
    """The names the static fit reports an effect's parameters under; a value reported through the
    rest of the model (``report_with_model``) is reported here as its own parameter."""
    return eff.parameters if eff.report_with_model is not None else eff.reported_names


def _elastic_mask(fit: StaticFit, effects) -> np.ndarray:
    """Which static-model parameters the deflection fit identified."""
    mask = []
    for eff in effects:
        outs = _reported_names(eff)
        mask += [o not in fit.unidentifiable for o in outs]
    return np.array(mask, dtype=bool)


def _report(fit: StaticFit, effects, beta: np.ndarray, std: np.ndarray,
            mask: np.ndarray) -> tuple[list[Parameter], list[str]]:
    params: list[Parameter] = []
    unident: list[str] = []
    offset = 0
    for eff in effects:
        k = len(eff.parameters)
        sl = slice(offset, offset + k)
        offset += k
        if k == 0:
            continue
        values, deriv = eff.reported(np.where(mask[sl], beta[sl], 1.0))
        units = eff.report_units or eff.units
        outs = _reported_names(eff)
        for i in range(k):
            if not mask[sl][i]:
                unident.append(outs[i])
                continue
            params.append(Parameter(outs[i], float(values[i]), float(abs(deriv[i]) * std[sl][i]), units[i]))
    return params, unident
