"""Static identification from before/after-load deflections (Y35, Y39-42, K37).

Pure functions: a robot and a table (or dataset) in, a frozen :class:`StaticFit`
out. The model is a set of effects (identify/effects), each entering linearly
through angle, link-spring and additive bases. Two forms:

* ``first-order``: ``dP = J_m(q) (dtheta_load - dtheta_ref)`` as in the papers,
  one linear least-squares solve;
* ``exact`` (secant): ``dP = p(theta_load) - p(theta_ref)`` with the kinematics
  evaluated at the deflected configurations, solved by Gauss-Newton from the
  first-order solution.

Torques come from motor currents (``xi i``, absolute, so the deflected
configurations are known) or from the wrench columns (``J_f^T W - g - M``).

The noise floor is the residual rms that measurement noise alone leaves: the
tracker's and the currents' repeatability, estimated from repeated readings and
propagated through the fitted model and the hat matrix.

Why one module over 500 lines: the dataset, the problem and its two forms (first
order, exact secant Gauss-Newton) share private state of one solve; the effects'
physics is not here but in identify/effects, one module each.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Sequence

import numpy as np
import pinocchio as pin
import scipy.linalg

from elastocal.errors import Arg, EffectRefused, InputError, UnidentifiableError
from elastocal.identify.blas import one_blas_thread
from elastocal.model.effects import get_effect
from elastocal.model.effects.base import Effect, StaticBasis, StaticContext
from elastocal.model.robot import (
    LOAD_FRAME,
    MARKER_PREFIX,
    Robot,
    RobotData,
)
from elastocal.identify.evidence import check_loads_changed, mark_stiffness
from elastocal.identify.grouping import combine, first_seen, group_count, group_sum, sums_per_group
from elastocal.identify.registration import in_base_axes, refine_registration
from elastocal.formats.tables import StaticTable
from elastocal.model.tracker_noise import TrackerNoise

TORQUE_SOURCES = ("current", "force")
FORMS = ("exact", "first-order")
#: a pivoted-QR diagonal below this fraction of the largest marks a parameter
#: the data cannot separate from the others
RANK_TOL = 1e-7
#: a regressor column this small next to the largest is zero
ZERO_COLUMN = 1e-10


# =================================================================== dataset
@dataclass(frozen=True, eq=False)
class StaticDataset:
    """A static table reduced to load states and deflections.

    States ``s`` are (pose, load) pairs; deflections ``d`` are (loaded state,
    marker) pairs, measured against the reference state of the same pose.
    """

    source: str
    pose_ids: tuple[str, ...]
    q: np.ndarray                 # (P, N)
    markers: tuple[str, ...]
    state_pose: np.ndarray        # (S,) index into pose_ids
    state_load: np.ndarray        # (S,) str
    state_ref: np.ndarray         # (S,) index of the pose's reference state
    state_currents: np.ndarray    # (S, N) mean currents [A], NaN when absent
    state_n_currents: np.ndarray  # (S,) distinct drive readings averaged (docs/formats.md §2)
    state_wrench: np.ndarray      # (S, 6) [N, N·m], NaN when unknown; 0 for references without one
    defl_state: np.ndarray        # (D,)
    defl_ref: np.ndarray          # (D,)
    defl_marker: np.ndarray       # (D,) index into markers
    dP: np.ndarray                # (D, 3) measured deflection [m]
    defl_n: np.ndarray            # (D,) readings averaged in the loaded state
    defl_n_ref: np.ndarray        # (D,) readings averaged in the reference
    defl_dt: np.ndarray           # (D,) mean time loaded minus mean time reference [s], NaN if unknown
    defl_t: np.ndarray            # (D,) mean time of the loaded readings [s], NaN if unknown
    sigma_tracker: float | None   # repeatability per coordinate [m]
    sigma_current: np.ndarray | None  # (N,) repeatability per joint [A]
    #: tracker readings far off their repeats (identify/outliers.py): left out of
    #: sigma_tracker; in the means unless the table was refitted without them
    outliers: tuple = ()
    #: (D,) variance per coordinate of each deflection from the readings' U95 (the optional
    #: ``u95`` column, docs/import.md; sigma = U95 / 1.96), None without it: the fit's weights
    defl_u95_var: np.ndarray | None = None
    #: (D,) the part of it from the reference state's readings (shared by the deflections of a marker)
    defl_u95_var_ref: np.ndarray | None = None
    abs_xyz: np.ndarray | None = None  # (S, M, 3) mean absolute position per state and marker, tracker frame [m]
    abs_n: np.ndarray | None = None    # (S, M) readings averaged
    abs_t: np.ndarray | None = None    # (S, M) mean time of those readings [s], NaN if unknown
    #: (S, M, 3) variance per coordinate of those mean readings from the readings' own stated
    #: uncertainty (``u95`` or ``sx, sy, sz``), None without it [m²]
    abs_var: np.ndarray | None = None
    #: rotation tracker <- base that dP was turned back by (identify/registration.py); None: dP as measured
    tracker_rotation: np.ndarray | None = None
    #: the tracker's noise law in force (model/tracker_noise.py): estimated from the repeats where
    #: they are enough, else the cell's; None without either
    tracker_noise: TrackerNoise | None = None
    #: (S, M, 3, 3) covariance of each state's mean reading of each marker under that law,
    #: tracker frame [m²]; None without a law
    abs_cov: np.ndarray | None = None

    @property
    def n_states(self) -> int:
        return len(self.state_pose)

    @property
    def n_deflections(self) -> int:
        return len(self.defl_state)

    @property
    def has_currents(self) -> bool:
        return bool(np.all(np.isfinite(self.state_currents)))

    @property
    def has_wrench(self) -> bool:
        return bool(np.all(np.isfinite(self.state_wrench)))


def distinct_readings(currents: np.ndarray) -> np.ndarray:
    """The distinct drive readings among a load state's rows (docs/formats.md §2):
    rows that carry identical currents share one reading (the currents of one
    repeat read once for all its markers), which counts once in the mean and
    in the noise estimate. Order of first appearance is kept."""
    if len(currents) < 2 or not np.all(np.isfinite(currents)):
        return currents
    _, first = np.unique(currents, axis=0, return_index=True)
    return currents[np.sort(first)]


def _in_order(values: np.ndarray, start: np.ndarray | float) -> np.ndarray:
    """``start`` plus the ``values`` (along axis 0) added one after the other, in order: the sum
    a loop over the groups makes, to the last bit (the fits downstream are that sensitive)."""
    return np.add.accumulate(np.concatenate([np.asarray(start, dtype=float)[None], values]), axis=0)[-1]


def build_dataset(table: StaticTable, *, tracker_noise: TrackerNoise | None = None) -> StaticDataset:
    """Average repeated readings and form the deflections of a validated table.

    The tracker's repeatability leaves out the readings far off their repeats
    (identify/outliers.py); they are listed in ``outliers``. The tracker's noise
    law (identify/trackernoise.py) is estimated from the repeats where they are
    enough, else ``tracker_noise`` (cell.toml ``[tracker] noise``) is taken; it gives
    every mean reading its covariance (``abs_cov``) and, without repeats, the noise level.

    States are numbered pose by pose in order of first appearance, the reference (load 0)
    first, then the pose's loads in order of first appearance; deflections run over the
    loaded states and every marker of the table. One grouped pass over the rows
    (identify/grouping.py): no Python loop per row, state or marker."""
    from elastocal.identify.outliers import find_outliers, outlier_mask, tracker_noise_of

    noise = tracker_noise_of(table, tracker_noise if tracker_noise is not None else table.tracker_noise)
    outliers = find_outliers(table, noise=noise)
    bad = outlier_mask(len(table), outliers)
    pose_code, pose_first = first_seen(table.pose)
    marker_code, marker_first = first_seen(table.marker)
    pose_ids = tuple(table.pose[pose_first])
    markers = tuple(table.marker[marker_first])
    q = table.q[pose_first]
    n_markers = len(markers)
    missing = sorted(set(range(len(pose_ids))) - set(pose_code[table.load == "0"].tolist()))
    if missing:
        p = pose_ids[missing[0]]
        raise InputError(f"pose {p} has no unloaded reference (load 0)", source=table.source,
                         row=int(table.line[pose_first[missing[0]]]), column="load")

    # states: (pose, load) pairs, the reference first within a pose, then in order of first appearance
    pair_code, pair_first = first_seen(combine(pose_code, first_seen(table.load)[0]))
    order = np.lexsort((pair_first, table.load[pair_first] != "0", pose_code[pair_first]))
    state_of_pair = np.empty(len(order), dtype=np.intp)
    state_of_pair[order] = np.arange(len(order))
    state = state_of_pair[pair_code]                       # (n,) state of each row
    first_row = pair_first[order]                          # (S,) first row of each state
    n_states = len(first_row)
    state_pose = pose_code[first_row]
    state_load = np.array(list(table.load[first_row]), dtype=str)
    state_ref = np.searchsorted(state_pose, state_pose)    # states are sorted by pose, reference first

    # currents: the distinct drive readings of each state (distinct_readings), averaged
    currents = table.currents
    row_finite = np.all(np.isfinite(currents), axis=1)
    state_finite = group_count(state[~row_finite], n_states) == 0
    keep = np.ones(len(table), dtype=bool)
    dedupe = np.flatnonzero(state_finite[state])
    if dedupe.size:
        _, first = np.unique(np.column_stack([state[dedupe].astype(float), currents[dedupe]]), axis=0,
                             return_index=True)
        keep[dedupe] = False
        keep[dedupe[first]] = True
    ncur = group_count(state[keep], n_states)
    with np.errstate(invalid="ignore", divide="ignore"):
        cur = group_sum(state[keep], currents[keep], n_states) / ncur[:, None]
    noisy = state_finite & (ncur > 1)
    rows_i = keep & noisy[state]
    per_state = group_sum(state[rows_i], (currents[rows_i] - cur[state[rows_i]]) ** 2, n_states)[noisy]
    dev_sq_i = _in_order(per_state, np.zeros(table.n_joints))
    dof_i = int(np.sum(ncur[noisy] - 1))

    wrench = table.wrench[first_row].copy()
    blank_ref = (state_load == "0") & ~np.all(np.isfinite(wrench), axis=1)
    wrench[blank_ref] = 0.0

    # (state, marker) cells: mean position, readings, mean time; repeatability from the good readings
    cell = state * n_markers + marker_code
    n_cells = n_states * n_markers
    count = group_count(cell, n_cells)
    good = ~bad
    n_good = group_count(cell[good], n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        xyz_mean = group_sum(cell, table.xyz, n_cells) / count[:, None]
        t_mean = group_sum(cell, table.t, n_cells) / count
        good_mean = group_sum(cell[good], table.xyz[good], n_cells) / n_good[:, None]
    rows_p = np.flatnonzero(good & (n_good[cell] > 1))
    rows_p = rows_p[np.argsort(cell[rows_p], kind="stable")]
    dev_sq_p = float(_in_order(sums_per_group((table.xyz[rows_p] - good_mean[cell[rows_p]]) ** 2,
                                               n_good[n_good > 1]), 0.0))
    dof_p = int(np.sum(3 * (n_good[n_good > 1] - 1)))
    u95 = table.optional("u95")
    if u95 is not None and not (np.all(np.isfinite(u95)) and np.all(u95 > 0)):
        u95 = None                  # weights only when every reading has its uncertainty
    if u95 is not None:             # variance of the mean of the state's readings
        with np.errstate(invalid="ignore", divide="ignore"):
            var_of = group_sum(cell, (u95 / 1.96) ** 2, n_cells) / count.astype(float) ** 2
    abs_var = _reading_variances(table, cell, count, n_cells)

    # deflections: every loaded state against its pose's reference, marker by marker
    loaded = np.flatnonzero(state_ref != np.arange(n_states))
    d_state = np.repeat(loaded, n_markers)
    d_marker = np.tile(np.arange(n_markers), len(loaded))
    d_ref = state_ref[d_state]
    c1, c0 = d_state * n_markers + d_marker, d_ref * n_markers + d_marker
    sigma_tracker = float(np.sqrt(dev_sq_p / dof_p)) if dof_p else None
    sigma_current = np.sqrt(dev_sq_i / dof_i) if dof_i else None
    abs_cov = None
    if noise is not None:          # each mean reading's covariance under the law
        finite = np.all(np.isfinite(xyz_mean), axis=1)
        abs_cov = np.full((n_cells, 3, 3), np.nan)
        abs_cov[finite] = noise.covariance(xyz_mean[finite]) / count[finite][:, None, None]
        abs_cov = abs_cov.reshape(n_states, n_markers, 3, 3)
        if sigma_tracker is None:  # no repeats: the law sets the level
            sigma_tracker = noise.rms_sigma(xyz_mean[finite])
    return StaticDataset(
        source=table.source, pose_ids=pose_ids, q=q, markers=markers,
        state_pose=state_pose, state_load=state_load, state_ref=state_ref, state_currents=cur,
        state_n_currents=ncur, state_wrench=wrench, defl_state=d_state, defl_ref=d_ref,
        defl_marker=d_marker, dP=(xyz_mean[c1] - xyz_mean[c0]).reshape(-1, 3),
        defl_n=count[c1], defl_n_ref=count[c0], defl_dt=t_mean[c1] - t_mean[c0],
        defl_t=t_mean[c1], sigma_tracker=sigma_tracker, sigma_current=sigma_current,
        defl_u95_var=var_of[c1] + var_of[c0] if u95 is not None else None,
        defl_u95_var_ref=var_of[c0] if u95 is not None else None,
        outliers=outliers,
        abs_xyz=xyz_mean.reshape(n_states, n_markers, 3), abs_n=count.reshape(n_states, n_markers),
        abs_t=t_mean.reshape(n_states, n_markers).astype(float),
        tracker_noise=noise, abs_cov=abs_cov,
        abs_var=None if abs_var is None else abs_var.reshape(n_states, n_markers, 3),
    )


def _reading_variances(table: StaticTable, cell: np.ndarray, count: np.ndarray, n_cells: int) -> np.ndarray | None:
    """(cells, 3) variance per coordinate of each cell's mean reading from the readings' own
    uncertainties (``u95``: sigma = U95 / 1.96 on each coordinate; ``sx, sy, sz``: per axis), or
    None unless every reading states a positive one (docs/formats.md §2)."""
    u95 = table.optional("u95")
    if u95 is not None:
        sigma = np.repeat((u95 / 1.96)[:, None], 3, axis=1)
    elif table.optional("sx") is not None:
        sigma = np.column_stack([table.optional(c) for c in ("sx", "sy", "sz")])
    else:
        return None
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        return group_sum(cell, sigma ** 2, n_cells) / count.astype(float)[:, None] ** 2


# =================================================================== results
@dataclass(frozen=True)
class Parameter:
    name: str
    value: float
    std: float
    unit: str


@dataclass(frozen=True, eq=False)
class StaticFit:
    """Result of a static identification."""

    model: tuple[str, ...]
    torque: str
    form: str
    parameters: tuple[Parameter, ...]      # reported parameters (k, not c), identifiable ones
    unidentifiable: tuple[str, ...]        # parameters the data cannot separate
    beta_names: tuple[str, ...]            # model parameters (c1.., cl2x.., vx.., b1..)
    beta: np.ndarray                       # their values (0 for unidentifiable ones)
    beta_cov: np.ndarray                   # their covariance
    predicted: np.ndarray                  # (D, 3)
    residuals: np.ndarray                  # (D, 3) measured - predicted
    rms: float
    max: float
    n: int
    rss: float
    n_params: int
    noise_floor: float | None
    expected_rss: float | None             # trace((I - H) Sigma): what noise alone leaves
    condition_number: float
    iterations: int
    dataset: StaticDataset = field(repr=False)
    #: (3D, n_params) Jacobian of the predicted deflections in the identifiable
    #: parameters at the solution (rows x, y, z of each deflection)
    design: np.ndarray | None = field(default=None, repr=False)
    #: per-pose (row indices, covariance) of the deflection noise; None without repeats
    noise_blocks: tuple[tuple[np.ndarray, np.ndarray], ...] | None = field(default=None, repr=False)
    #: what the model's absolute marker positions are computed from, on demand (absolute_base)
    absolute_model: tuple | None = field(default=None, repr=False)
    #: beta names of the design's columns
    design_names: tuple[str, ...] = ()
    #: what the data support of each selectable effect (identify/selection.py)
    selections: tuple = ()
    #: the effects fitted (selectable ones restricted to the kept parameters)
    effects: tuple = field(default=(), repr=False)
    #: per-pose (row indices, lower Cholesky factor of the noise covariance) of a
    #: GLS fit (:class:`Whitening`: iterates as those pairs); None for an unweighted one
    whitening: "Whitening | None" = field(default=None, repr=False)
    #: residual sum of squares in the whitened metric (chi-square with n - p
    #: degrees of freedom under noise alone); None for an unweighted fit
    rss_whitened: float | None = None

    @property
    def absolute_base(self) -> np.ndarray | None:
        """(S, M, 3) the model's absolute marker positions of every state, base frame."""
        if self.absolute_model is None:
            return None
        pr, beta, ctx = self.absolute_model
        return _absolute_base(pr, beta, ctx)

    @property
    def dispersion(self) -> float:
        """How much more than noise the fit leaves (>= 1)."""
        if self.rss_whitened is not None:
            return max(1.0, self.rss_whitened / max(self.n - self.n_params, 1))
        if self.expected_rss is None or self.expected_rss <= 0:
            return 1.0
        return max(1.0, self.rss / self.expected_rss)

    def whiten(self, v: np.ndarray) -> np.ndarray:
        """``L^-1 v`` (rows of the deflection components) for a GLS fit."""
        return _whiten(self.whitening, v)

    def unwhiten(self, v: np.ndarray) -> np.ndarray:
        """``L v`` for a GLS fit."""
        return _unwhiten(self.whitening, v)

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def values(self, names: Sequence[str]) -> np.ndarray:
        return np.array([self.parameter(n).value for n in names])

    def stds(self, names: Sequence[str]) -> np.ndarray:
        return np.array([self.parameter(n).std for n in names])

    def to_json(self) -> dict:
        """The ``identify --json`` object of docs/cli.md."""
        out = {
            "model": list(self.model),
            "torque": self.torque,
            "form": self.form,
            "parameters": mark_stiffness({p.name: {"value": p.value, "std": p.std, "unit": p.unit}
                                          for p in self.parameters}),
            "residual": {"rms": self.rms, "max": self.max, "n": self.n, "unit": "m"},
            "noise_floor": self.noise_floor,
        }
        if self.unidentifiable:
            out["unidentifiable"] = list(self.unidentifiable)
            out["rank"] = self.n_params
        for sel in self.selections:
            out.setdefault("selected", {})[sel.effect] = list(sel.kept)
            if sel.controls:     # fitted so that the joint springs stay honest, not findings
                out.setdefault("controls", {})[sel.effect] = list(sel.controls)
        out["condition_number"] = self.condition_number
        return out


# =================================================================== model
@dataclass(frozen=True, eq=False)
class _Problem:
    robot: Robot
    ds: StaticDataset
    effects: tuple[Effect, ...]
    torque: str
    form: str
    complementary: bool
    frames: tuple[str, ...]
    #: this problem's Pinocchio work buffers (made by the robot, used by every kinematics call
    #: of the solve: creating a Data costs more than the kinematics it serves)
    data: RobotData | None = None

    def __post_init__(self) -> None:
        if self.data is None:
            object.__setattr__(self, "data", self.robot.create_data())
        elif not self.data.belongs_to(self.robot):
            raise ValueError("the work buffers were made by another robot")

    @cached_property
    def nominal_theta(self) -> np.ndarray:
        """(S, N) link-side angles of every state's commanded pose (``robot.theta``)."""
        return self.ds.q[self.ds.state_pose] + self.robot.offsets

    @cached_property
    def nominal_kinematics(self) -> tuple[np.ndarray, np.ndarray]:
        """Marker positions (P, M, 3) and position Jacobians (P, M, 3, nv) of every pose
        at its commanded configuration: computed once per problem, read by the
        first-order form, the noise covariance and its rank."""
        theta = _link_configurations(self.robot, self.ds.q + self.robot.offsets)
        return _kinematics_batch(self.robot, theta, self.frames, self.data)

    @cached_property
    def load_jacobians(self) -> np.ndarray:
        """(P, 6, nv) Jacobian of the load point of every pose at its commanded
        configuration (LOCAL_WORLD_ALIGNED, as ``Robot.jacobians``)."""
        model, data = self.robot.link_model, self.data.links
        fid = model.getFrameId(LOAD_FRAME)
        theta = _link_configurations(self.robot, self.ds.q + self.robot.offsets)
        out = np.empty((len(theta), 6, model.nv))
        for pi, th in enumerate(theta):
            pin.computeJointJacobians(model, data, th)
            pin.updateFramePlacements(model, data)
            out[pi] = pin.getFrameJacobian(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
        return out

    @cached_property
    def pose_deflections(self) -> tuple[np.ndarray, ...]:
        """The deflection indices of each pose (ascending), one array per pose."""
        pose_of = self.ds.state_pose[self.ds.defl_state]
        order = np.argsort(pose_of, kind="stable")
        bounds = np.searchsorted(pose_of[order], np.arange(len(self.ds.pose_ids) + 1))
        return tuple(order[bounds[i]:bounds[i + 1]] for i in range(len(self.ds.pose_ids)))

    @cached_property
    def state_rank(self) -> tuple[np.ndarray, np.ndarray]:
        """Each state's place among its pose's states (ascending), and each pose's number of states."""
        sp = self.ds.state_pose
        order = np.argsort(sp, kind="stable")
        counts = np.bincount(sp, minlength=len(self.ds.pose_ids))
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.empty(len(sp), dtype=np.intp)
        rank[order] = np.arange(len(sp)) - start[sp[order]]
        return rank, counts


def _link_configurations(robot: Robot, theta: np.ndarray, link_angles: np.ndarray | None = None) -> np.ndarray:
    """``Robot.theta_links`` of many states at once: (S, N + springs) from (S, N) and (S, springs)."""
    out = np.zeros((len(theta), len(robot.link_joint_order)))
    out[:, robot.actuated_in_link_model] = theta
    if link_angles is not None:
        out[:, robot.springs_in_link_model] = link_angles
    return out


def _torques(pr: _Problem, theta_states: np.ndarray | None) -> np.ndarray:
    """Absolute gear torque (S, N) of each state."""
    robot, ds = pr.robot, pr.ds
    if pr.torque == "current":
        return ds.state_currents * robot.torque_constants
    comp = robot.compensator.nominal_parameters() if robot.compensator is not None else None
    theta = pr.nominal_theta if theta_states is None else np.ascontiguousarray(theta_states, dtype=float)
    # Robot.load_torque's J_f^T W - g(theta) - M e2, step for step, on the problem's Data (each
    # Pinocchio call below overwrites what the next one reads)
    model, data = robot.model, pr.data.rigid
    fid = model.getFrameId(LOAD_FRAME)
    world = pin.LOCAL_WORLD_ALIGNED
    c = robot.compensator.index if comp is not None else 0
    offset_c = robot.joints[c].offset
    out = np.empty((ds.n_states, robot.n_joints))
    for s in range(ds.n_states):
        th = theta[s]
        tau = np.zeros(model.nv)
        pin.computeJointJacobians(model, data, th)
        pin.updateFramePlacements(model, data)
        tau += pin.getFrameJacobian(model, data, fid, world).T @ ds.state_wrench[s]
        if robot.has_masses:
            tau -= pin.computeGeneralizedGravity(model, data, th)
        if comp is not None:
            tau[c] -= float(robot.compensator.torque(th[c] - offset_c, comp))
        out[s] = tau
    return out


def _context(pr: _Problem, tau: np.ndarray, estimate: np.ndarray | None = None) -> StaticContext:
    robot, ds = pr.robot, pr.ds
    delta_tau = tau - tau[ds.state_ref]
    # every state at once: the wrench change the torque change carries (J_act^T dW = dtau), and
    # what it puts on the link springs (J_spr^T dW)
    jac = pr.load_jacobians[ds.state_pose]
    j_act_t = np.swapaxes(jac[:, :, robot.actuated_in_link_model], 1, 2)
    j_spr_t = np.swapaxes(jac[:, :, robot.springs_in_link_model], 1, 2)
    if pr.torque == "current" and robot.n_joints != 6:
        # N joint torques of one 6-component wrench: least squares (N > 6), the least wrench (N < 6)
        delta_wrench = np.stack([np.linalg.lstsq(j_act_t[s], delta_tau[s], rcond=None)[0]
                                 for s in range(ds.n_states)])
    elif pr.torque == "current":
        try:
            delta_wrench = np.linalg.solve(j_act_t, delta_tau[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:       # a singular pose: least squares for that one
            delta_wrench = np.empty((ds.n_states, 6))
            for s in range(ds.n_states):
                try:
                    delta_wrench[s] = np.linalg.solve(j_act_t[s], delta_tau[s])
                except np.linalg.LinAlgError:
                    delta_wrench[s] = np.linalg.lstsq(j_act_t[s], delta_tau[s], rcond=None)[0]
    else:
        delta_wrench = ds.state_wrench - ds.state_wrench[ds.state_ref]
    delta_link = (j_spr_t @ delta_wrench[:, :, None])[:, :, 0]
    # the whole wrench: with currents the change is all they show (the reference carries none)
    wrench = delta_wrench.copy() if pr.torque == "current" else ds.state_wrench.copy()
    torque_noise = None
    if ds.sigma_current is not None and pr.torque == "current":
        torque_noise = robot.torque_constants * ds.sigma_current / np.sqrt(ds.state_n_currents)[:, None]
    return StaticContext(tau=tau, delta_tau=delta_tau, delta_link_moment=delta_link,
                         delta_wrench=delta_wrench, wrench=wrench, torque_noise=torque_noise, robot=robot,
                         dataset=ds,
                         state_is_reference=ds.state_ref == np.arange(ds.n_states),
                         deflection_dt=ds.defl_dt, n_deflections=ds.n_deflections, torque_source=pr.torque,
                         form=pr.form, estimate=estimate,
                         estimate_names=tuple(p for eff in pr.effects for p in eff.parameters), data=pr.data)


def _bases(pr: _Problem, ctx: StaticContext) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ds = pr.ds
    thetas, links, adds = [], [], []
    for eff in pr.effects:
        p = len(eff.parameters)
        if p == 0:
            continue
        b = eff.static_basis(ctx) if eff.static_basis is not None else StaticBasis()
        thetas.append(b.theta if b.theta is not None else np.zeros((ds.n_states, pr.robot.n_joints, p)))
        links.append(b.links if b.links is not None
                     else np.zeros((ds.n_states, len(pr.robot.link_spring_names), p)))
        adds.append(b.add if b.add is not None else np.zeros((ds.n_deflections, 3, p)))
    return np.concatenate(thetas, axis=2), np.concatenate(links, axis=2), np.concatenate(adds, axis=2)


def _kinematics(robot: Robot, theta10: np.ndarray, frames: Sequence[str],
                data: RobotData) -> tuple[np.ndarray, np.ndarray]:
    """Positions (M, 3) and position Jacobians (M, 3, 10) of frames in the link model."""
    pos, jac = _kinematics_batch(robot, np.asarray(theta10, dtype=float)[None], tuple(frames), data)
    return pos[0], jac[0]


def _kinematics_batch(robot: Robot, theta10: np.ndarray, frames: tuple[str, ...],
                      data: RobotData) -> tuple[np.ndarray, np.ndarray]:
    """Positions (S, M, 3) and position Jacobians (S, M, 3, 10) of frames in the link
    model at each of the configurations ``theta10`` (S, 10): one Pinocchio pass
    (joint Jacobians and frame placements) per configuration, into arrays made once, on the
    caller's ``data`` (``robot.create_data()``)."""
    model, pdata = robot.link_model, data.links
    fids = tuple(model.getFrameId(f) for f in frames)
    theta10 = np.ascontiguousarray(theta10, dtype=float)
    pos = np.empty((len(theta10), len(fids), 3))
    jac = np.empty((len(theta10), len(fids), 3, model.nv))
    world = pin.LOCAL_WORLD_ALIGNED
    for s, th in enumerate(theta10):
        pin.computeJointJacobians(model, pdata, th)
        pin.updateFramePlacements(model, pdata)
        for k, fid in enumerate(fids):
            pos[s, k] = pdata.oMf[fid].translation
            jac[s, k] = pin.getFrameJacobian(model, pdata, fid, world)[:3]
    return pos, jac


def _evaluate(pr: _Problem, beta: np.ndarray, bases, exact: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted deflections (D, 3), their Jacobian (D*3, p) and the marker positions
    (S, M, 3) the kinematics gave (exact: at the deflected configurations; first
    order: at the commanded ones)."""
    ds = pr.ds
    b_theta, b_links, b_add = bases
    if exact:
        theta10 = _link_configurations(pr.robot, pr.nominal_theta + b_theta @ beta, b_links @ beta)
        pos, jac = _kinematics_batch(pr.robot, theta10, pr.frames, pr.data)
    else:
        pos0, jac0 = pr.nominal_kinematics
        pos, jac = pos0[ds.state_pose], jac0[ds.state_pose]
    d_idx = np.arange(ds.n_deflections)
    m = ds.defl_marker
    sl, sr = ds.defl_state, ds.defl_ref
    j_act_l = jac[sl, m][:, :, pr.robot.actuated_in_link_model]
    j_act_r = jac[sr, m][:, :, pr.robot.actuated_in_link_model]
    j_spr_l = jac[sl, m][:, :, pr.robot.springs_in_link_model]
    j_spr_r = jac[sr, m][:, :, pr.robot.springs_in_link_model]
    if exact:
        a = (j_act_l @ b_theta[sl] - j_act_r @ b_theta[sr] + j_spr_l @ b_links[sl] - j_spr_r @ b_links[sr]
             + b_add[d_idx])
        pred = pos[sl, m] - pos[sr, m] + b_add @ beta
    else:
        a = j_act_l @ (b_theta[sl] - b_theta[sr]) + j_spr_l @ (b_links[sl] - b_links[sr]) + b_add
        pred = a @ beta
    return pred, a.reshape(-1, a.shape[2]), pos


def _absolute_bases(pr: _Problem, ctx: StaticContext) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's bases per state for absolute positions (Effect.absolute): theta (S, 6, p),
    links (S, 4, p) and add (S, M, 3, p)."""
    parts = [eff.absolute(ctx) for eff in pr.effects if eff.parameters]
    return (np.concatenate([b.theta for b in parts], axis=2), np.concatenate([b.links for b in parts], axis=2),
            np.concatenate([b.add for b in parts], axis=3))


def absolute_positions(robot: Robot, ds: StaticDataset, frames: Sequence[str], beta: np.ndarray,
                       bases: tuple[np.ndarray, np.ndarray, np.ndarray],
                       data: RobotData | None = None) -> np.ndarray:
    """Base positions (S, M, 3) of every state's markers under a model's absolute bases
    (:func:`_absolute_bases`): the joint angles carry the absolute torques, the link springs
    and the located compliance the moments of gravity and of the load."""
    b_theta, b_links, b_add = bases
    theta10 = _link_configurations(robot, ds.q[ds.state_pose] + robot.offsets + b_theta @ beta, b_links @ beta)
    data = robot.create_data() if data is None else data
    return _kinematics_batch(robot, theta10, tuple(frames), data)[0] + b_add @ beta


def _absolute_base(pr: _Problem, beta: np.ndarray, ctx: StaticContext) -> np.ndarray:
    """Base positions (S, M, 3) of every state's markers under the fitted model."""
    return absolute_positions(pr.robot, pr.ds, pr.frames, beta, _absolute_bases(pr, ctx), pr.data)


def _noise_blocks(pr: _Problem, beta: np.ndarray, bases,
                  sensitivity: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """Per-pose (row indices, covariance) of the deflection noise, or None
    when the data hold no repeated readings. ``sensitivity`` (S, N): d dtheta /
    d tau of each state (default: the joint compliances).

    Tracker noise: a deflection's own readings and those of its reference, which the
    deflections of one marker at one pose share. Current noise: through the
    compliance and the marker's Jacobian at the pose, into the loaded state and the
    reference of each deflection. The blocks of all poses of one shape in a few array operations."""
    robot, ds = pr.robot, pr.ds
    if ds.sigma_tracker is None and ds.defl_u95_var is None:
        return None
    sig_i = ds.sigma_current if (pr.torque == "current" and ds.sigma_current is not None) else None
    c = None
    if sig_i is not None:
        # d dtheta / d tau for each state: the joint-stiffness part of the basis,
        # plus what torque-dependent effects (backlash) add
        nj = robot.n_joints
        c = np.tile(beta[:nj], (ds.n_states, 1)) if sensitivity is None else sensitivity
        jac0 = pr.nominal_kinematics[1][:, :, :, robot.actuated_in_link_model]     # (P, M, 3, N)
        rank, n_states_of = pr.state_rank
        var_i = (robot.torque_constants * sig_i) ** 2 / ds.state_n_currents[:, None]   # (S, N)
        order = np.argsort(ds.state_pose, kind="stable")
    if ds.defl_u95_var is not None:          # the readings' own U95 (docs/import.md)
        v_ref, v_own = ds.defl_u95_var_ref, ds.defl_u95_var
    elif ds.abs_cov is not None:             # the tracker's law, per coordinate at each reading's range
        v_cell = np.trace(ds.abs_cov, axis1=-2, axis2=-1) / 3.0          # (S, M)
        v_ref = v_cell[ds.defl_ref, ds.defl_marker]
        v_own = v_ref + v_cell[ds.defl_state, ds.defl_marker]
    else:
        v_ref = ds.sigma_tracker**2 / ds.defl_n_ref
        v_own = v_ref + ds.sigma_tracker**2 / ds.defl_n
    # poses of one shape (deflections, states) are done together: every block of a group in
    # one array operation
    state_start = np.concatenate([[0], np.cumsum(n_states_of)[:-1]]) if sig_i is not None else None
    shapes: dict[tuple[int, int], list[int]] = {}
    for pi, dl in enumerate(pr.pose_deflections):
        if dl.size:
            shapes.setdefault((dl.size, int(n_states_of[pi]) if sig_i is not None else 0), []).append(pi)
    out: list = [None] * len(pr.pose_deflections)
    for (n, k), poses in shapes.items():
        dl = np.stack([pr.pose_deflections[pi] for pi in poses])          # (G, n)
        g_n = len(poses)
        mk = ds.defl_marker[dl]
        shared = np.where(mk[:, :, None] == mk[:, None, :], v_ref[dl][:, :, None], 0.0)
        shared[:, np.arange(n), np.arange(n)] = v_own[dl]
        cov = np.zeros((g_n, n, 3, n, 3))
        for i in range(3):
            cov[:, :, i, :, i] = shared
        cov = cov.reshape(g_n, 3 * n, 3 * n)
        if sig_i is not None:
            pis = np.array(poses)
            jm = jac0[pis[:, None], mk]                                   # (G, n, 3, N)
            g = np.zeros((g_n, n, 3, k, nj))
            at_g, at_d = np.arange(g_n)[:, None], np.arange(n)[None, :]
            g[at_g, at_d, :, rank[ds.defl_state[dl]], :] = jm * c[ds.defl_state[dl]][:, :, None, :]
            g[at_g, at_d, :, rank[ds.defl_ref[dl]], :] = -(jm * c[ds.defl_ref[dl]][:, :, None, :])
            g = g.reshape(g_n, 3 * n, nj * k)
            states = order[state_start[pis][:, None] + np.arange(k)]      # (G, k)
            var = var_i[states].reshape(g_n, nj * k)
            cov += (g * var[:, None, :]) @ np.swapaxes(g, 1, 2)
        rows = (3 * dl[:, :, None] + np.arange(3)).reshape(g_n, -1)
        for j, pi in enumerate(poses):
            out[pi] = (rows[j], cov[j])
    return [b for b in out if b is not None]


@dataclass(frozen=True, eq=False)
class Whitening:
    """The per-pose lower Cholesky factors ``L`` of a GLS fit's noise covariance
    (iterates as (row indices, L) pairs, pose by pose). ``L^-1 v`` is LAPACK's
    triangular solve of each block, called directly (the very call
    ``scipy.linalg.solve_triangular`` makes, without its per-call checks): the
    fit downstream of it (the absolute fits) is that sensitive to its last bits;
    ``L v`` is one batched product per block size."""

    blocks: tuple[tuple[np.ndarray, np.ndarray], ...]
    #: (rows (G, m), L (G, m, m)) per block size m
    stacks: tuple[tuple[np.ndarray, np.ndarray], ...]

    @classmethod
    def of(cls, blocks: Sequence[tuple[np.ndarray, np.ndarray]]) -> "Whitening":
        stacks = []
        sizes = np.array([len(rows) for rows, _ in blocks])
        for m in dict.fromkeys(sizes.tolist()):
            pick = [b for b, size in zip(blocks, sizes) if size == m]
            stacks.append((np.stack([r for r, _ in pick]), np.stack([c for _, c in pick])))
        return cls(tuple(blocks), tuple(stacks))

    def __iter__(self):
        return iter(self.blocks)

    def __len__(self) -> int:
        return len(self.blocks)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return self.blocks[i]

    def whiten(self, v: np.ndarray) -> np.ndarray:
        """``L^-1 v`` for a vector (N,) or the columns of a matrix (N, p)."""
        v = np.asarray(v, dtype=float)
        out = np.empty_like(v)
        if not self.blocks:
            return out
        trtrs = scipy.linalg.lapack.dtrtrs
        for rows, chol in self.blocks:
            # solve_triangular's call for a C-ordered lower factor: the transposed (upper,
            # Fortran-ordered) system, transposed back
            x, info = trtrs(chol.T, v[rows], lower=0, trans=1, unitdiag=0)
            if info != 0:
                raise np.linalg.LinAlgError(f"singular noise covariance block (trtrs info {info})")
            out[rows] = x
        return out

    def unwhiten(self, v: np.ndarray) -> np.ndarray:
        """``L v``."""
        v = np.asarray(v, dtype=float)
        out = np.empty_like(v)
        for rows, chol in self.stacks:
            x = v[rows]
            out[rows] = (chol @ x[..., None])[..., 0] if v.ndim == 1 else chol @ x
        return out


def _cholesky_blocks(blocks) -> Whitening | None:
    """Cholesky factors of the noise covariance blocks, or None when the data carry
    no noise to weight by (noise-free data: every block zero): the fit is then
    unweighted. Blocks of one size are factored together."""
    chol: list = [None] * len(blocks)
    sizes = np.array([len(cov) for _, cov in blocks])
    for m in dict.fromkeys(sizes.tolist()):
        idx = np.flatnonzero(sizes == m)
        covs = np.stack([blocks[i][1] for i in idx])
        trace = np.trace(covs, axis1=1, axis2=2)
        if not np.all(np.isfinite(trace)) or np.any(trace <= 0.0):
            return None
        jitter = 1e-12 * trace / max(m, 1)
        try:
            factors = np.linalg.cholesky(covs + jitter[:, None, None] * np.eye(m))
        except np.linalg.LinAlgError:
            return None
        for i, f in zip(idx, factors):
            chol[i] = f
    return Whitening.of([(rows, f) for (rows, _), f in zip(blocks, chol)])


def _whiten(whitening: Whitening, v: np.ndarray) -> np.ndarray:
    return whitening.whiten(v)


def _unwhiten(whitening: Whitening, v: np.ndarray) -> np.ndarray:
    return whitening.unwhiten(v)


def _select_columns(a: np.ndarray, names: Sequence[str],
                    later: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Column scales and the mask of identifiable columns (pivoted QR on the
    scaled regressor). ``later`` (int per column, 0 for the model's own): columns
    that count only for what the columns of lower order leave (a selectable
    effect's components never displace a joint spring they alias, nor a component
    of higher priority, Effect.priority)."""
    scale = np.linalg.norm(a, axis=0)
    # a column that is rounding noise next to the largest moves nothing (the twist of joint 6
    # seen by one marker on its axis): it is not identifiable, however the noise is scaled
    keep = scale > ZERO_COLUMN * float(np.max(scale, initial=0.0))
    mask = np.zeros(len(names), dtype=bool)
    order = np.zeros(len(names), dtype=int) if later is None else np.asarray(later, dtype=int)
    scaled = a / np.where(scale > 0, scale, 1.0)
    largest = None
    q = np.zeros((a.shape[0], 0))
    for level in np.unique(order):
        idx = np.flatnonzero(keep & (order == level))
        if idx.size == 0:
            continue
        block = scaled[:, idx] - q @ (q.T @ scaled[:, idx])
        qb, r, piv = scipy.linalg.qr(block, mode="economic", pivoting=True)
        diag = np.abs(np.diag(r))
        largest = diag[0] if largest is None else largest
        good = diag > RANK_TOL * max(largest, 1e-300) if level == 0 else diag > RANK_TOL * 1.0
        mask[idx[piv[good]]] = True
        q = np.column_stack([q, qb[:, good]])
    return np.where(scale > 0, scale, 1.0), mask


def _lstsq(a: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> np.ndarray:
    """Least squares, with rows weighted by ``w`` when given."""
    if w is None:
        return np.linalg.lstsq(a, y, rcond=None)[0]
    return np.linalg.lstsq(a * w[:, None], y * w, rcond=None)[0]


@one_blas_thread
def identify_static(robot: Robot, data: StaticTable | StaticDataset, *,
                    model: Sequence[str] = ("joint_stiffness",), torque: str = "current",
                    form: str = "exact", max_iter: int = 30, tol: float = 1e-10,
                    weighting: str = "gls", work: RobotData | None = None) -> StaticFit:
    """Fit the static model ``model`` (effect names, or effects restricted to
    some parameters) to a table or dataset.

    ``weighting``: ``gls`` (default) weights the residuals by the noise
    covariance the repeated readings give (generalised least squares: the
    variance of the parameters reaches the Cramér-Rao bound); ``ols`` is plain
    least squares with the sandwich covariance. Without repeated readings the
    fit is ordinary least squares either way.

    ``work``: the Pinocchio work buffers of the computation this fit is part of
    (``robot.create_data()``; a diagnosis passes one to all its fits), new ones when None."""
    work = robot.create_data() if work is None else work
    if torque not in TORQUE_SOURCES:
        raise InputError(f"must be current or force, got {torque!r}", argument="torque")
    if form not in FORMS:
        raise InputError(f"must be exact or first-order, got {form!r}", argument="form")
    ds = data if isinstance(data, StaticDataset) else build_dataset(data)
    if ds.tracker_rotation is None:
        # a tracker placed anywhere: the deflections turned back to base axes by the
        # registration of the nominal model, then by that of this model's fit
        first = identify_static(robot, in_base_axes(robot, ds), model=model, torque=torque, form=form,
                                max_iter=max_iter, tol=tol, work=work)
        refined = refine_registration(robot, ds, first.absolute_base)
        if refined is None:
            return first
        return identify_static(robot, refined, model=model, torque=torque, form=form, max_iter=max_iter, tol=tol, work=work)
    if torque == "current" and not ds.has_currents:
        raise InputError(("current-based identification needs the currents i1..iN in every row; use ",
                          Arg("torque", "force")), source=ds.source)
    if torque == "force" and not ds.has_wrench:
        raise InputError("force-based identification needs the wrench fx..mz of every loaded state",
                         source=ds.source)
    check_loads_changed(ds)          # loads that changed nothing determine nothing (identify/evidence.py)
    given = {m.name: m for m in model if isinstance(m, Effect)}   # effects restricted to some parameters
    names = tuple(dict.fromkeys(["joint_stiffness", *(m if isinstance(m, str) else m.name for m in model)]))
    effects = tuple(given.get(n) or get_effect(n, robot) for n in names)
    selections = []
    for k, eff in enumerate(effects):
        if eff.selectable and eff.selected_from is None:
            # the components the data support (identify/selection.py), from the fit with all of them
            from elastocal.identify.selection import confirm_selection, confounders, forward_select

            # (first-order: one linear solve; the kept components are then fitted in ``form``)
            full = identify_static(robot, ds, model=[*effects[:k], eff.restricted(eff.parameters), *effects[k + 1:]],
                                   torque=torque, form="first-order", max_iter=max_iter, tol=tol, work=work)
            sel = forward_select(full, eff.name, eff.parameters)
            if form != "first-order" and sel.kept:
                confirmed = confirm_selection(sel, lambda keep: identify_static(
                    robot, ds, model=[*effects[:k], eff.restricted(sel.fitted(keep)), *effects[k + 1:]],
                    torque=torque, form=form, max_iter=max_iter, tol=tol, work=work), n=ds.dP.size)
                if confirmed.kept != sel.kept:     # the controls of what stays
                    sel = replace(confirmed, controls=confounders(full, confirmed.kept, eff.parameters))
            selections.append(sel)
            # the kept components and the controls (fitted, not named: identify/selection.py)
            effects = (*effects[:k], eff.restricted(sel.fitted()), *effects[k + 1:])
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    for m in ds.markers:
        robot.frame_id(m)
    complementary = "complementary_stiffness" in names
    pr = _Problem(robot, ds, effects, torque, form, complementary, frames, work)
    exact = form == "exact"
    tau_dependent = torque == "force" and (exact or complementary)
    #: effects whose basis depends on the current estimate (static_friction's saturation)
    iterative = any(eff.iterative for eff in effects)

    tau = _torques(pr, None)
    ctx = _context(pr, tau)
    if torque == "force" and not np.any(ctx.delta_wrench[ds.defl_state]):
        raise InputError("every loaded state carries the wrench of its unloaded reference (all zero?): the loads "
                         "change no torque, so they determine nothing; a table without loads is a geometric "
                         "calibration table: give every row load 0", source=ds.source, column="fx")
    for eff in effects:
        if "static" not in eff.seen_in and eff.static_refusal is None:
            words = f"{eff.name} cannot be identified from static data"
            raise EffectRefused(eff.name, words, message=words, argument="model")
        reason = eff.static_refusal(ctx) if eff.static_refusal is not None else None
        if reason:
            raise EffectRefused(eff.name, reason, argument="model")
    beta_names = tuple(p for eff in effects for p in eff.parameters)
    bases = _bases(pr, ctx)
    y = ds.dP.reshape(-1)
    if y.size < len(beta_names):
        raise UnidentifiableError(f"{y.size} deflection components cannot determine the model's {len(beta_names)} "
                                  "parameters (measure more poses, loads or markers)", source=ds.source)

    # first-order linear solve: starting point, and the answer for form=first-order
    _, a, _ = _evaluate(pr, np.zeros(len(beta_names)), bases, exact=False)
    later = np.array([0 if eff.selected_from is None else 1 + (0 if eff.priority is None else eff.priority[i])
                      for eff in effects for i in range(len(eff.parameters))], dtype=int)
    scale, mask = _select_columns(a, beta_names, later if later.any() else None)
    if not mask.any():
        raise UnidentifiableError("no parameter of the model changes the predicted deflections (loads that change "
                                  "no torque?)", source=ds.source)
    beta = np.zeros(len(beta_names))
    # rows weighted by the readings' U95 when the table has them (1 / sigma, mean weight 1)
    w = None if ds.defl_u95_var is None else np.repeat(1.0 / np.sqrt(ds.defl_u95_var), 3)
    if w is not None:
        w = w / np.sqrt(np.mean(w ** 2))
    beta[mask] = _lstsq(a[:, mask] / scale[mask], y, w) / scale[mask]
    state = {"ctx": ctx, "bases": bases, "tau": tau}

    def gauss_newton(beta: np.ndarray, whitening) -> tuple[np.ndarray, int]:
        """Iterate to the (weighted) least-squares solution from ``beta``."""
        iterations = 0
        for iterations in range(1, max_iter + 1):
            if tau_dependent:
                theta_states = pr.nominal_theta + state["bases"][0] @ beta
                state["tau"] = _torques(pr, theta_states)
            if tau_dependent or iterative:
                state["ctx"] = _context(pr, state["tau"], beta if iterative else None)
                state["bases"] = _bases(pr, state["ctx"])
            pred, a, _ = _evaluate(pr, beta, state["bases"], exact=exact)
            r = y - pred.reshape(-1)
            x = a[:, mask] / scale[mask]
            if whitening is not None:
                x, r = _whiten(whitening, x), _whiten(whitening, r)
            step = np.zeros_like(beta)
            step[mask] = (np.linalg.lstsq(x, r, rcond=None)[0] if whitening is not None
                          else _lstsq(x, r, w)) / scale[mask]
            beta = beta + step
            if not (exact or tau_dependent or iterative):
                break                       # linear: one solve is the solution
            if np.max(np.abs(step[mask] * scale[mask])) < tol * max(1.0, float(np.max(np.abs(y)))):
                break
        return beta, iterations

    def noise_blocks(beta: np.ndarray):
        sensitivity = np.tile(beta[:robot.n_joints], (ds.n_states, 1))
        offset = 0
        for eff in effects:
            k = len(eff.parameters)
            if eff.torque_sensitivity is not None:
                sensitivity = sensitivity + eff.torque_sensitivity(state["ctx"], beta[offset:offset + k])
            offset += k
        return _noise_blocks(pr, beta, state["bases"], sensitivity)

    iterations = 1
    if exact or tau_dependent or iterative:
        beta, it = gauss_newton(beta, None)
        iterations += it
    blocks = noise_blocks(beta)
    whitening = None
    if blocks is not None and weighting == "gls" and w is None:
        # generalised least squares: weighted by the noise covariance the fit knows
        # (tracker noise, shared references, current noise through the compliance)
        whitening = _cholesky_blocks(blocks)
        if whitening is not None:
            beta, it = gauss_newton(beta, whitening)
            iterations += it
            blocks = noise_blocks(beta)
            whitening = _cholesky_blocks(blocks)
    ctx, bases, tau = state["ctx"], state["bases"], state["tau"]
    pred, a, _ = _evaluate(pr, beta, bases, exact=exact)
    resid = ds.dP - pred
    r = resid.reshape(-1)
    rss = float(r @ r)
    n = r.size
    p = int(mask.sum())
    a_k = a[:, mask]
    scaled = a_k / scale[mask]
    sv = np.linalg.svd(scaled, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else float("inf")
    w2 = np.ones(n) if w is None else w ** 2
    rss_w = None
    if whitening is not None:
        aw = _whiten(whitening, scaled)
        rw = _whiten(whitening, r)
        rss_w = float(rw @ rw)
        m_inv_s = np.linalg.pinv(aw.T @ aw)
        inflation = max(1.0, rss_w / max(n - p, 1))
        cov_k = m_inv_s / np.outer(scale[mask], scale[mask]) * inflation
        # what noise alone leaves in the (unweighted) residual: tr(L (I - QQ') L')
        qw = np.linalg.svd(aw, full_matrices=False)[0][:, : p]
        lq = _unwhiten(whitening, qw)
        trace_sigma = sum(float(np.trace(c)) for _, c in blocks)
        expected = trace_sigma - float((lq * lq).sum())
        noise_floor = float(np.sqrt(max(expected, 0.0) / n))
    elif blocks is not None:
        m_inv = np.linalg.pinv(a_k.T @ a_k if w is None else a_k.T @ (w2[:, None] * a_k))
        meat = np.zeros((p, p))
        trace_sigma = 0.0
        cross = 0.0             # trace(H Sigma), H = A M A^T W the weighted hat matrix
        for rows, cov in blocks:
            ab = a_k[rows]
            wab = ab if w is None else w2[rows][:, None] * ab
            meat += wab.T @ cov @ wab
            trace_sigma += float(np.trace(cov))
            if w is not None:
                cross += float(np.trace(m_inv @ (wab.T @ cov @ ab)))
        if w is None:
            expected = trace_sigma - float(np.trace(m_inv @ meat))
        else:   # E[r^T r] = tr(Sigma) - 2 tr(H Sigma) + tr(H Sigma H^T); unweighted: tr(Sigma) - tr(M meat)
            expected = trace_sigma - 2.0 * cross + float(np.trace(m_inv @ meat @ m_inv @ (a_k.T @ a_k)))
        inflation = max(1.0, rss / expected) if expected > 0 else 1.0
        cov_k = m_inv @ meat @ m_inv * inflation
        noise_floor = float(np.sqrt(max(expected, 0.0) / n))
    else:
        m_inv = np.linalg.pinv(a_k.T @ a_k if w is None else a_k.T @ (w2[:, None] * a_k))
        expected = None
        s2 = (rss if w is None else float(r @ (w2 * r))) / max(n - p, 1)
        cov_k = m_inv * s2
        noise_floor = None
    cov = np.zeros((len(beta_names), len(beta_names)))
    cov[np.ix_(mask, mask)] = cov_k
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))

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
        own_std = deriv * std[sl]
        if eff.report_with_model is not None:
            values, own_std = eff.report_with_model(beta_names, beta, cov, sl)
        units = eff.report_units or eff.units
        names_out = [f"k{c[1:]}" for c in eff.parameters] if eff.name == "joint_stiffness" else list(eff.reported_names)
        for i in range(k):
            if not mask[sl][i]:
                unident.append(names_out[i])
                continue
            params.append(Parameter(names_out[i], float(values[i]), float(abs(own_std[i])), units[i]))
    return StaticFit(model=names, torque=torque, form=form, parameters=tuple(params),
                     absolute_model=(pr, beta, ctx),
                     unidentifiable=tuple(unident), beta_names=beta_names, beta=beta, beta_cov=cov,
                     predicted=pred, residuals=resid, rms=float(np.sqrt(rss / n)),
                     max=float(np.max(np.abs(r))), n=n, rss=rss, n_params=p, noise_floor=noise_floor,
                     expected_rss=expected, condition_number=cond, iterations=iterations, dataset=ds,
                     design=a_k, noise_blocks=None if blocks is None else tuple(blocks),
                     design_names=tuple(nm for nm, m in zip(beta_names, mask) if m), selections=tuple(selections),
                     effects=effects, whitening=whitening, rss_whitened=rss_w)
