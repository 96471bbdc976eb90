"""Static identification from before/after-load deflections (Y35, Y39-42, K37).

Pure functions: a robot and a table (or dataset) in, a frozen :class:`StaticFit`
out. The model is a set of effects (model/effects), each entering linearly
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

Why one module over 500 lines: the fit's two forms (first order, exact secant
Gauss-Newton), its noise weighting (the per-pose blocks and their Cholesky
factors) and its uncertainty share the typed state of one solve (:class:`_Solve`,
:class:`_Linearisation`); the dataset is in identify/dataset.py, the static model
in identify/staticmodel.py, the effects' physics in model/effects, one module each.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from elastocal.errors import Arg, EffectRefused, InputError, UnidentifiableError
from elastocal.identify.blas import one_blas_thread, scipy_linalg
from elastocal.identify.dataset import StaticDataset, build_dataset
from elastocal.identify.evidence import check_loads_changed, mark_stiffness, mark_twins
from elastocal.identify.registration import in_base_axes, refine_registration
from elastocal.identify.staticmodel import Problem, evaluate, fitted_positions, state_torques, static_bases, static_context
from elastocal.model.effects import BASE_EFFECT, get_effect
from elastocal.model.effects.base import Effect, StaticContext
from elastocal.model.kinds import KinematicForm, TorqueSource, Weighting, expect
from elastocal.model.robot import MARKER_PREFIX, Robot, RobotData
from elastocal.formats.tables import StaticTable

#: what other modules take from here (the dataset is made in identify/dataset.py)
__all__ = ["StaticDataset", "StaticFit", "Parameter", "build_dataset", "identify_static", "Whitening"]

#: a pivoted-QR diagonal below this fraction of the largest marks a parameter
#: the data cannot separate from the others
RANK_TOL = 1e-7
#: a regressor column this small next to the largest is zero
ZERO_COLUMN = 1e-10


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
    torque: TorqueSource
    form: KinematicForm
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

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque, "torque")
        expect(KinematicForm, self.form, "form")

    @property
    def absolute_base(self) -> np.ndarray | None:
        """(S, M, 3) the model's absolute marker positions of every state, base frame."""
        if self.absolute_model is None:
            return None
        pr, beta, ctx = self.absolute_model
        return fitted_positions(pr, beta, ctx)

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

    @property
    def undetermined(self) -> dict[str, str]:
        """Joint stiffnesses these data do not determine (name -> why): each follows which of two
        link-compliance components the data cannot tell apart was fitted, or a component left out for
        its sign that the data still allow positive (identify/selection.py)."""
        out: dict[str, str] = {}
        for sel in self.selections:
            for spring, why in sel.undetermined().items():
                out[spring] = f"{out[spring]}; {why}" if spring in out else why
        return out

    def to_json(self) -> dict:
        """The ``identify --json`` object of docs/cli.md."""
        out = {
            "model": list(self.model),
            "torque": self.torque,
            "form": self.form,
            "parameters": mark_twins(mark_stiffness({p.name: {"value": p.value, "std": p.std, "unit": p.unit}
                                                     for p in self.parameters}), self.undetermined),
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


def _noise_blocks(pr: Problem, beta: np.ndarray, bases,
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
    sig_i = ds.sigma_current if (pr.torque is TorqueSource.CURRENT and ds.sigma_current is not None) else None
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
    elif ds.reading_cov is not None:         # each reading's own noise (its law at its range), per coordinate
        v_cell = np.trace(ds.reading_cov, axis1=-2, axis2=-1) / 3.0      # (S, M)
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
        trtrs = scipy_linalg().lapack.dtrtrs
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
        qb, r, piv = scipy_linalg().qr(block, mode="economic", pivoting=True)     # numpy's QR has no pivoting
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


@dataclass(frozen=True, eq=False)
class _Linearisation:
    """What the model's bases were last built on: each state's gear torques, the context
    the effects read and the bases (theta, links, add). Rebuilt as the fit iterates when
    the torques follow the deflection or a basis depends on the estimate."""

    tau: np.ndarray
    ctx: StaticContext
    bases: tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True, eq=False)
class _Solve:
    """The fixed parts of one solve: the problem, the measured deflection components, the
    identifiable columns and their scales, and the rows' weights from the readings' U95."""

    pr: Problem
    y: np.ndarray                 # (3D,) measured deflections, x y z of each
    mask: np.ndarray              # (p,) the identifiable parameters
    scale: np.ndarray             # (p,) column scales of the regressor
    w: np.ndarray | None          # (3D,) row weights (1 / sigma, mean weight 1), None without U95
    max_iter: int
    tol: float

    @property
    def exact(self) -> bool:
        return self.pr.form is KinematicForm.EXACT

    @property
    def tau_dependent(self) -> bool:
        """Force-based torques taken at the deflected configuration: they change with the estimate."""
        return self.pr.torque is TorqueSource.FORCE and (self.exact or self.pr.torque_at_deflection)

    @property
    def iterative(self) -> bool:
        """An effect's basis depends on the current estimate (static_friction's saturation)."""
        return any(eff.iterative for eff in self.pr.effects)

    @property
    def nonlinear(self) -> bool:
        return self.exact or self.tau_dependent or self.iterative


@dataclass(frozen=True, eq=False)
class _Iterated:
    """The solution and the noise weighting it was reached with."""

    beta: np.ndarray
    lin: _Linearisation
    blocks: list | None           # per-pose (rows, covariance) of the deflection noise
    whitening: Whitening | None
    iterations: int


@dataclass(frozen=True, eq=False)
class _Uncertainty:
    """Covariance of the identifiable parameters (scaled back) and what noise alone leaves."""

    cov: np.ndarray
    expected_rss: float | None
    noise_floor: float | None
    rss_whitened: float | None


@one_blas_thread
def identify_static(robot: Robot, data: StaticTable | StaticDataset, *,
                    model: Sequence[str] = ("joint_stiffness",), torque: TorqueSource = TorqueSource.CURRENT,
                    form: KinematicForm = KinematicForm.EXACT, max_iter: int = 30, tol: float = 1e-10,
                    weighting: Weighting = Weighting.GLS, work: RobotData | None = None) -> StaticFit:
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
    expect(TorqueSource, torque, "torque")
    expect(KinematicForm, form, "form")
    expect(Weighting, weighting, "weighting")
    ds = data if isinstance(data, StaticDataset) else build_dataset(data)
    if ds.tracker_rotation is None:
        # a tracker placed anywhere: the deflections turned back to base axes by the
        # registration of the nominal model, then by that of this model's fit
        first = identify_static(robot, in_base_axes(robot, ds), model=model, torque=torque, form=form,
                                max_iter=max_iter, tol=tol, weighting=weighting, work=work)
        refined = refine_registration(robot, ds, first.absolute_base)
        if refined is None:
            return first
        return identify_static(robot, refined, model=model, torque=torque, form=form, max_iter=max_iter, tol=tol,
                               weighting=weighting, work=work)
    _check_torque_source(ds, torque)
    check_loads_changed(ds)          # loads that changed nothing determine nothing (identify/evidence.py)
    names, effects, selections = _model_effects(robot, ds, model, torque=torque, form=form, max_iter=max_iter,
                                                tol=tol, work=work)
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    for m in ds.markers:
        robot.frame_id(m)
    pr = Problem(robot, ds, effects, torque, form, frames, work)
    tau = state_torques(pr, None)
    ctx = static_context(pr, tau)
    _check_shown(pr, ctx)
    lin = _Linearisation(tau, ctx, static_bases(pr, ctx))
    solve, beta = _first_order(pr, lin, max_iter=max_iter, tol=tol)
    done = _iterate(solve, beta, lin, weighting)
    return _result(solve, names, tuple(selections), done)


def _check_torque_source(ds: StaticDataset, torque: TorqueSource) -> None:
    """Refuse a torque source the table does not carry."""
    if torque is TorqueSource.CURRENT and not ds.has_currents:
        raise InputError(("current-based identification needs the currents i1..iN in every row; use ",
                          Arg("torque", "force")), source=ds.source)
    if torque is TorqueSource.FORCE and not ds.has_wrench:
        raise InputError("force-based identification needs the wrench fx..mz of every loaded state",
                         source=ds.source)


def _model_effects(robot: Robot, ds: StaticDataset, model: Sequence, *, torque: TorqueSource, form: KinematicForm,
                   max_iter: int, tol: float, work: RobotData) -> tuple[tuple[str, ...], tuple[Effect, ...], list]:
    """The model's names (joint_stiffness first), its effects sized for the robot, and the
    selections of its selectable effects: each restricted to the components the data
    support (identify/selection.py), from the fit with all of them."""
    given = {m.name: m for m in model if isinstance(m, Effect)}   # effects restricted to some parameters
    names = tuple(dict.fromkeys([BASE_EFFECT, *(m if isinstance(m, str) else m.name for m in model)]))
    effects = tuple(given.get(n) or get_effect(n, robot) for n in names)
    selections = []
    for k, eff in enumerate(effects):
        if eff.selectable and eff.selected_from is None:
            from elastocal.identify.selection import at_bound, confirm_selection, confounders, forward_select, twins

            # (first-order: one linear solve; the kept components are then fitted in ``form``)
            full = identify_static(robot, ds, model=[*effects[:k], eff.restricted(eff.parameters), *effects[k + 1:]],
                                   torque=torque, form=KinematicForm.FIRST_ORDER, max_iter=max_iter, tol=tol, work=work)
            sel = forward_select(full, eff.name, eff.parameters)
            if form is not KinematicForm.FIRST_ORDER and sel.kept:
                confirmed = confirm_selection(sel, lambda keep: identify_static(
                    robot, ds, model=[*effects[:k], eff.restricted(sel.fitted(keep)), *effects[k + 1:]],
                    torque=torque, form=form, max_iter=max_iter, tol=tol, work=work), n=ds.dP.size)
                if confirmed.kept != sel.kept:     # the controls of what stays, and those found before
                    # (a control the first pass needed still matters: of two components the data cannot
                    # tell apart, the recount beside the other may pass it over)
                    again = set(confounders(full, confirmed.kept, eff.parameters)) | set(sel.controls)
                    sel = replace(confirmed, controls=tuple(n for n in eff.parameters
                                                            if n in again and n not in confirmed.kept))
            base = effects[0]        # the joint springs (BASE_EFFECT first)
            springs = dict(zip(base.parameters, base.parameters if base.report_with_model is not None
                               else base.reported_names))
            sel = replace(sel, twins=twins(full, sel, eff.parameters, springs))
            sel = replace(sel, at_bound=at_bound(full, sel, eff.parameters, springs))
            selections.append(sel)
            # the kept components and the controls (fitted, not named: identify/selection.py)
            effects = (*effects[:k], eff.restricted(sel.fitted()), *effects[k + 1:])
    return names, effects, selections


def _check_shown(pr: Problem, ctx: StaticContext) -> None:
    """Refuse loads that change no torque, and an effect these static data cannot show (its reason)."""
    if pr.torque is TorqueSource.FORCE and not np.any(ctx.delta_wrench[pr.ds.defl_state]):
        raise InputError("every loaded state carries the wrench of its unloaded reference (all zero?): the loads "
                         "change no torque, so they determine nothing; a table without loads is a geometric "
                         "calibration table: give every row load 0", source=pr.ds.source, column="fx")
    for eff in pr.effects:
        if "static" not in eff.seen_in and eff.static_refusal is None:
            words = f"{eff.name} cannot be identified from static data"
            raise EffectRefused(eff.name, words, message=words, argument="model")
        reason = eff.static_refusal(ctx) if eff.static_refusal is not None else None
        if reason:
            raise EffectRefused(eff.name, reason, argument="model")


def _beta_names(pr: Problem) -> tuple[str, ...]:
    return tuple(p for eff in pr.effects for p in eff.parameters)


def _first_order(pr: Problem, lin: _Linearisation, *, max_iter: int, tol: float) -> tuple[_Solve, np.ndarray]:
    """The first-order linear solve: which parameters the data identify, and the starting
    point (the answer for form=first-order)."""
    ds = pr.ds
    beta_names = _beta_names(pr)
    y = ds.dP.reshape(-1)
    if y.size < len(beta_names):
        raise UnidentifiableError(f"{y.size} deflection components cannot determine the model's {len(beta_names)} "
                                  "parameters (measure more poses, loads or markers)", source=ds.source)
    _, a, _ = evaluate(pr, np.zeros(len(beta_names)), lin.bases, exact=False)
    later = np.array([0 if eff.selected_from is None else 1 + (0 if eff.priority is None else eff.priority[i])
                      for eff in pr.effects for i in range(len(eff.parameters))], dtype=int)
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
    return _Solve(pr, y, mask, scale, w, max_iter, tol), beta


def _relinearised(solve: _Solve, beta: np.ndarray, lin: _Linearisation) -> _Linearisation:
    """The torques, context and bases at ``beta`` when they depend on it (else ``lin``)."""
    pr = solve.pr
    tau = lin.tau
    if solve.tau_dependent:
        tau = state_torques(pr, pr.nominal_theta + lin.bases[0] @ beta)
    if not (solve.tau_dependent or solve.iterative):
        return lin
    ctx = static_context(pr, tau, beta if solve.iterative else None)
    return _Linearisation(tau, ctx, static_bases(pr, ctx))


def _gauss_newton(solve: _Solve, beta: np.ndarray, lin: _Linearisation,
                  whitening: Whitening | None) -> tuple[np.ndarray, int, _Linearisation]:
    """Iterate to the (weighted) least-squares solution from ``beta``."""
    mask, scale, y = solve.mask, solve.scale, solve.y
    iterations = 0
    for iterations in range(1, solve.max_iter + 1):
        lin = _relinearised(solve, beta, lin)
        pred, a, _ = evaluate(solve.pr, beta, lin.bases, exact=solve.exact)
        r = y - pred.reshape(-1)
        x = a[:, mask] / scale[mask]
        if whitening is not None:
            x, r = _whiten(whitening, x), _whiten(whitening, r)
        step = np.zeros_like(beta)
        step[mask] = (np.linalg.lstsq(x, r, rcond=None)[0] if whitening is not None
                      else _lstsq(x, r, solve.w)) / scale[mask]
        beta = beta + step
        if not solve.nonlinear:
            break                       # linear: one solve is the solution
        if np.max(np.abs(step[mask] * scale[mask])) < solve.tol * max(1.0, float(np.max(np.abs(y)))):
            break
    return beta, iterations, lin


def _noise_at(pr: Problem, beta: np.ndarray, lin: _Linearisation):
    """The deflection noise blocks at ``beta``: current noise through the joint compliances plus
    what torque-dependent effects add to d dtheta / d tau (Effect.torque_sensitivity)."""
    sensitivity = np.tile(beta[:pr.robot.n_joints], (pr.ds.n_states, 1))
    offset = 0
    for eff in pr.effects:
        k = len(eff.parameters)
        if eff.torque_sensitivity is not None:
            sensitivity = sensitivity + eff.torque_sensitivity(lin.ctx, beta[offset:offset + k])
        offset += k
    return _noise_blocks(pr, beta, lin.bases, sensitivity)


def _iterate(solve: _Solve, beta: np.ndarray, lin: _Linearisation, weighting: Weighting) -> _Iterated:
    """From the first-order start to the solution: Gauss-Newton when the model is nonlinear,
    then generalised least squares weighted by the noise covariance the fit knows (tracker
    noise, shared references, current noise through the compliance)."""
    iterations = 1
    if solve.nonlinear:
        beta, it, lin = _gauss_newton(solve, beta, lin, None)
        iterations += it
    blocks = _noise_at(solve.pr, beta, lin)
    whitening = None
    if blocks is not None and weighting is Weighting.GLS and solve.w is None:
        whitening = _cholesky_blocks(blocks)
        if whitening is not None:
            beta, it, lin = _gauss_newton(solve, beta, lin, whitening)
            iterations += it
            blocks = _noise_at(solve.pr, beta, lin)
            whitening = _cholesky_blocks(blocks)
    return _Iterated(beta, lin, blocks, whitening, iterations)


def _uncertainty(solve: _Solve, a_k: np.ndarray, r: np.ndarray, blocks, whitening: Whitening | None) -> _Uncertainty:
    """The identifiable parameters' covariance and the residual noise alone leaves: GLS (the
    whitened metric), the sandwich of an unweighted fit with known noise, or the residual's
    scatter when the data hold no repeats."""
    mask, scale, w = solve.mask, solve.scale, solve.w
    rss, n, p = float(r @ r), r.size, int(mask.sum())
    scaled = a_k / scale[mask]
    w2 = np.ones(n) if w is None else w ** 2
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
        return _Uncertainty(cov_k, expected, float(np.sqrt(max(expected, 0.0) / n)), rss_w)
    m_inv = np.linalg.pinv(a_k.T @ a_k if w is None else a_k.T @ (w2[:, None] * a_k))
    if blocks is None:
        s2 = (rss if w is None else float(r @ (w2 * r))) / max(n - p, 1)
        return _Uncertainty(m_inv * s2, None, None, None)
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
    return _Uncertainty(m_inv @ meat @ m_inv * inflation, expected, float(np.sqrt(max(expected, 0.0) / n)), None)


def _reported(effects: Sequence[Effect], beta: np.ndarray, mask: np.ndarray, cov: np.ndarray,
              beta_names: tuple[str, ...]) -> tuple[list[Parameter], list[str]]:
    """The parameters as reported (each effect's reported values and units), and the names of
    those the data do not identify."""
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
        names_out = eff.reported_names
        for i in range(k):
            if not mask[sl][i]:
                unident.append(names_out[i])
                continue
            params.append(Parameter(names_out[i], float(values[i]), float(abs(own_std[i])), units[i]))
    return params, unident


def _result(solve: _Solve, names: tuple[str, ...], selections: tuple, done: _Iterated) -> StaticFit:
    pr, mask, beta = solve.pr, solve.mask, done.beta
    ds, beta_names = pr.ds, _beta_names(pr)
    pred, a, _ = evaluate(pr, beta, done.lin.bases, exact=solve.exact)
    resid = ds.dP - pred
    r = resid.reshape(-1)
    rss, n, p = float(r @ r), r.size, int(mask.sum())
    a_k = a[:, mask]
    sv = np.linalg.svd(a_k / solve.scale[mask], compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else float("inf")
    unc = _uncertainty(solve, a_k, r, done.blocks, done.whitening)
    cov = np.zeros((len(beta_names), len(beta_names)))
    cov[np.ix_(mask, mask)] = unc.cov
    params, unident = _reported(pr.effects, beta, mask, cov, beta_names)
    return StaticFit(model=names, torque=pr.torque, form=pr.form, parameters=tuple(params),
                     absolute_model=(pr, beta, done.lin.ctx),
                     unidentifiable=tuple(unident), beta_names=beta_names, beta=beta, beta_cov=cov,
                     predicted=pred, residuals=resid, rms=float(np.sqrt(rss / n)),
                     max=float(np.max(np.abs(r))), n=n, rss=rss, n_params=p, noise_floor=unc.noise_floor,
                     expected_rss=unc.expected_rss, condition_number=cond, iterations=done.iterations, dataset=ds,
                     design=a_k, noise_blocks=None if done.blocks is None else tuple(done.blocks),
                     design_names=tuple(nm for nm, m in zip(beta_names, mask) if m), selections=selections,
                     effects=pr.effects, whitening=done.whitening, rss_whitened=unc.rss_whitened)
