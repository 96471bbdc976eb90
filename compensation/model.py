"""The static model compensation uses: joint springs, gravity, compensator, process wrench.

``CompensationModel`` is the robot description plus a calibration (docs/formats.md
§4): joint stiffness ``k1..k6`` and, optionally, the compensator parameters.
The load torque the joints carry is the full static one (docs/formats.md sign)::

    tau(theta, W) = J_f(theta)^T W - g(theta) - M(q2) e2

and the joints deflect by ``dtheta = c ⊙ tau`` (``c = 1/k``), so a command
``q`` puts the links at the fixed point ``theta = q + offset + c ⊙ tau(theta, W)``.

Gravity ``g`` needs the link masses of robot.toml; the compensator torque
``M`` needs them too (alone it would be a large unbalanced torque, so it is
used only together with gravity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from elastocal.compensation.chain import Angles, BatchedChain, ChainState, log6_local
from elastocal.errors import Arg, InputError
from elastocal.formats.calibration import Calibration
from elastocal.model.kinds import CompensatorKind
from elastocal.model.robot import LOAD_FRAME, Robot
from elastocal.model.effects import having

#: fixed-point tolerance on the joint angles [rad]
FIXED_POINT_TOL_RAD = 1e-13
MAX_FIXED_POINT_ITER = 100


@dataclass(frozen=True, eq=False)
class CompensationModel:
    """Robot and calibrated parameters; immutable."""

    robot: Robot
    stiffness: np.ndarray                          # (N,) k [N·m/rad; N/m for a prismatic joint]
    compensator: tuple[float, float] | None = None  # (C, l_c) or (K_c, s0)
    #: the drawing's robot when ``robot`` carries a geometric calibration (kinematic_errors):
    #: a path planned on the drawing means the pose the drawing gives (reference "nominal")
    nominal: Robot | None = None
    #: the frame the path positions: the load point, or a marker (a tool the tracker sees)
    tool: str = LOAD_FRAME
    #: the base's tilt from level about its x and y axes [rad] (a calibration's tilt_x, tilt_y):
    #: the weight pulls along gravity turned into base axes (identify/level.py)
    tilt_rad: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        k = np.asarray(self.stiffness, dtype=float).reshape(-1)
        n = self.robot.n_joints
        if k.shape != (n,) or not np.all(np.isfinite(k)) or np.any(k <= 0):
            raise InputError(f"joint stiffness k1..k{n} must be {n} positive finite values (one per joint of "
                             f"{self.robot.name!r})")
        object.__setattr__(self, "stiffness", k)
        if self.compensator is not None:
            if self.robot.compensator is None:
                raise InputError("compensator parameters given but the robot description has no [compensator]",
                                 source=self.robot.source)
            object.__setattr__(self, "compensator", (float(self.compensator[0]), float(self.compensator[1])))

    @property
    def compliance(self) -> np.ndarray:
        return 1.0 / self.stiffness

    @property
    def uses_gravity(self) -> bool:
        return self.robot.has_masses

    @property
    def uses_compensator(self) -> bool:
        return self.uses_gravity and self.compensator is not None and self.robot.compensator is not None

    @classmethod
    def from_calibration(cls, robot: Robot, cal: Calibration, *, source: str = "calibration") -> "CompensationModel":
        """Stiffness and compensator from a calibration file; the compensator
        falls back to the robot description's nominal values when the
        calibration does not hold them."""
        if cal.robot and cal.robot != robot.name:
            raise InputError(f"the calibration is for robot {cal.robot!r}, the description is {robot.name!r}",
                             source=source, column="robot")
        missing = [f"k{j}" for j in range(1, robot.n_joints + 1) if not cal.has(f"k{j}")]
        if missing:
            raise InputError(f"missing joint stiffness {', '.join(missing)}", source=source, column="parameters")
        k = np.array([cal.value(f"k{j}") for j in range(1, robot.n_joints + 1)])
        bad = np.flatnonzero(~(k > 0))
        if bad.size:
            raise InputError(f"stiffness must be positive, got {k[bad[0]]}", source=source,
                             column=f"parameters.k{bad[0] + 1}")
        comp = None
        spec = robot.compensator
        if spec is not None:
            names = spec.parameter_names
            if all(cal.has(n) for n in names):
                comp = tuple(cal.value(n) for n in names)
            elif any(cal.has(n) for n in names):
                raise InputError(f"give both compensator parameters {' and '.join(names)}", source=source,
                                 column="parameters")
            else:
                nominal = spec.nominal_parameters()
                comp = None if nominal is None else (float(nominal[0]), float(nominal[1]))
            other = ("K_c", "s0") if spec.kind == CompensatorKind.HYDROPNEUMATIC else ("C", "l_c")
            if any(cal.has(n) for n in other):
                raise InputError(f"compensator parameters {', '.join(other)} do not fit the robot's "
                                 f"{spec.kind} compensator", source=source, column="parameters")
        from elastocal.identify.level import TILT_NAMES

        tilt = tuple(float(cal.value(n)) if cal.has(n) else 0.0 for n in TILT_NAMES)
        if having("geometry", cal.model):        # the calibration's geometry: the real robot's
            from elastocal.identify.accuracy import calibrated_robot

            return cls(robot=calibrated_robot(robot, cal), stiffness=k, compensator=comp, nominal=robot, tilt_rad=tilt)
        return cls(robot=robot, stiffness=k, compensator=comp, tilt_rad=tilt)

    def with_tool(self, tool: str) -> "CompensationModel":
        """The same model positioning ``tool`` (the load point or a marker name)."""
        from dataclasses import replace

        self.robot.frame_id(tool)
        return replace(self, tool=tool)




def unmodelled_effects(cal: Calibration) -> dict[str, list[str]]:
    """Effects of the calibration that deflect the robot but compensation leaves out, with
    the calibration's parameters of each (cal.json names them; docs/cli.md's effect table)."""
    from elastocal.model.effects import get_effect
    from elastocal.model.effects.base import Compensation

    out = {}
    for name in cal.model:
        # each effect's module says whether compensation models it or it moves no tool point of a
        # path (Effect.compensation)
        if get_effect(name).compensation is not Compensation.UNMODELLED:
            continue
        names = get_effect(name).parameters
        out[name] = [p for p in cal.names if p in names] or [p for p in names if cal.has(p)]
    return out


def refuse_unmodelled(cal: Calibration, without: str | None, *, source: str) -> dict[str, list[str]]:
    """The calibration's unmodelled effects (:func:`unmodelled_effects`), refused by name unless
    ``without`` (comma-separated, the ``--without`` flag) leaves them out knowingly: a compensation
    that silently drops a deflection the calibration found is a wrong path."""
    unmodelled = unmodelled_effects(cal)
    names = {w.strip() for w in (without or "").split(",") if w.strip()}
    unknown = sorted(names - set(cal.model))
    if unknown:
        raise InputError(f"{', '.join(unknown)} not in the calibration's model ({', '.join(cal.model)})",
                         argument="without")
    refused = {e: p for e, p in unmodelled.items() if e not in names}
    if refused:
        what = "; ".join(f"{e} ({', '.join(p) or 'no parameters'})" for e, p in refused.items())
        raise InputError((f"the calibration holds {what}, which compensation does not model: the compensated path "
                          f"would leave {'their' if len(refused) > 1 else 'its'} deflection uncorrected; give ",
                          Arg("without", ",".join(refused)), " to compensate the rest knowingly"), source=source)
    return unmodelled


#: samples per block of the batched evaluation: numpy calls on rows of this length amortise their
#: per-call cost and the work arrays (a few MB) stay in cache (4096 was the fastest of 512..8192)
BLOCK_SAMPLES = 4096
#: the fixed points are first solved at every WARM_STRIDE-th sample along the path, and the others
#: start from the deflection interpolated between those (a warm start from their neighbours)
WARM_STRIDE = 16


def _blocks(n: int) -> list[slice]:
    return [slice(i, min(i + BLOCK_SAMPLES, n)) for i in range(0, n, BLOCK_SAMPLES)]


class StaticKernel:
    """The static model evaluated over whole paths: configurations (n, 6) in, arrays out.

    The kinematics and statics run batched over blocks of samples (:class:`BatchedChain`, from
    the robot's Pinocchio model); the fixed points are iterated for all samples of a block at
    once, each sample until its own step is below ``FIXED_POINT_TOL_RAD``, warm-started from its
    neighbours along the path. The cosines and sines of the planned angles are computed once
    per path; the small deflections from them by their Taylor series."""

    def __init__(self, model: CompensationModel) -> None:
        self.m = model
        pin_model = model.robot.model
        if any(model.tilt_rad):           # a copy carries the turned gravity; the robot's model stays as it is
            from elastocal.identify.level import gravity_in_base

            pin_model = pin.Model(pin_model)
            pin_model.gravity = pin.Motion(gravity_in_base(pin_model.gravity.linear, model.tilt_rad), np.zeros(3))
        self.chain = BatchedChain(pin_model)
        self.fid = model.robot.frame_id(LOAD_FRAME)
        self.tool_fid = model.robot.frame_id(model.tool)
        self.offsets = model.robot.offsets
        #: the compensator's joint (0-based) and its offset
        self.comp_index = model.robot.compensator.index if model.robot.compensator is not None else 0
        self.comp_offset = float(model.robot.joints[self.comp_index].offset)
        self.c = model.compliance
        self.spec = model.robot.compensator
        self.gravity = model.uses_gravity
        self.with_compensator = model.uses_compensator

    # ------------------------------------------------------ (6, n) arrays
    def _torque(self, ang: Angles, wrench: np.ndarray | None, *, gravity: bool = True
                ) -> tuple[np.ndarray, ChainState]:
        """``J^T W - g - M e2`` (6, n) at ``ang`` for the wrench (6, n) (None: none; without
        ``gravity`` only ``J^T W``), and the chain's state there."""
        passive = gravity and self.gravity
        st = self.chain.state(ang, masses=passive)
        tau = self.chain.torque(st, force=None if wrench is None else wrench[:3],
                                moment=None if wrench is None else wrench[3:], frame_id=self.fid)
        if passive and self.with_compensator:
            c = self.comp_index
            tau[c] -= self.spec.torque(ang.theta[c] - self.comp_offset, self.m.compensator)
        return tau, st

    def _iterate(self, base: Angles, wrench: np.ndarray | None, theta: np.ndarray) -> np.ndarray:
        """Fixed points ``theta = base + c ⊙ tau(theta, W)`` of the samples (6, n) in place, from
        ``theta``, each sample until its step is below the tolerance. Returns the columns whose
        iteration diverged or did not converge (their ``theta`` is left as it was then)."""
        c = self.c[:, None]
        active = np.arange(theta.shape[1])
        failed = [np.zeros(0, dtype=int)]
        ang, w, th = base, wrench, theta
        for _ in range(MAX_FIXED_POINT_ITER):
            with np.errstate(all="ignore"):
                new = ang.theta + c * self._torque(ang.near(th), w)[0]
                bad = ~np.all(np.isfinite(new), axis=0) | np.any(np.abs(new) > 1e3, axis=0)
                step = np.max(np.abs(new - th), axis=0)
            going = step >= FIXED_POINT_TOL_RAD
            if np.any(bad):
                failed.append(active[bad])
                ok = ~bad
                theta[:, active[ok]] = new[:, ok]
                going &= ok
            else:
                theta[:, active] = new
            if not np.any(going):
                return np.concatenate(failed)
            if not np.all(going):
                active, keep = active[going], np.flatnonzero(going)
                ang, th = ang.take(keep), new[:, keep]
                w = None if w is None else w[:, keep]
            else:
                th = new
        return np.concatenate(failed + [active])

    def _solve(self, base: Angles, wrench: np.ndarray | None, theta: np.ndarray, samples: np.ndarray) -> np.ndarray:
        """:meth:`_iterate` block by block (``samples``: the path index of each column); returns
        the path indices of the samples without a fixed point."""
        failed = [samples[b][self._iterate(_part(base, b), None if wrench is None else wrench[:, b], theta[:, b])]
                  for b in _blocks(theta.shape[1])]
        return np.concatenate(failed) if failed else np.zeros(0, dtype=int)

    def fixed_points(self, base: Angles, wrench: np.ndarray | None, start: np.ndarray) -> np.ndarray:
        """Link angles (6, n) at the fixed points ``theta = base + c ⊙ tau(theta, W)`` along the path,
        warm-started along it (:func:`_along_path`). Raises :class:`NotConverged` naming the first
        sample of the path without a fixed point."""
        def solve(index: np.ndarray, theta: np.ndarray) -> np.ndarray:
            return self._solve(base.take(index), None if wrench is None else wrench[:, index], theta, index)

        theta, failed = _along_path(solve, start)
        if failed.size:
            raise NotConverged(int(failed.min()))
        return theta

    # ------------------------------------------------------ (n, 6) arrays
    def base_angles(self, q: np.ndarray) -> Angles:
        """The planned link angles ``q + offset`` (6, n) with their cosines and sines."""
        return Angles.of((q + self.offsets).T)

    def positions(self, theta: np.ndarray, base: Angles | None = None) -> np.ndarray:
        """Tool-point positions (n, 3) in the base frame (the load point unless the model names a
        tool); ``base``: angles near ``theta`` whose cosines and sines are known."""
        th = theta.T
        out = np.empty((3, th.shape[1]))
        for b in _blocks(th.shape[1]):
            out[:, b] = self.chain.position(self.chain.state(_angles(th, b, base)), self.tool_fid)
        return out.T

    def torque(self, theta: np.ndarray, wrench: np.ndarray, base: Angles | None = None, *,
               with_positions: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Full static load torque ``J^T W - g - M e2`` (n, 6) (and with ``with_positions`` the
        tool-point positions (n, 3) there); ``base``: angles near ``theta`` whose cosines and
        sines are known."""
        th = theta.T
        w = _soa(wrench)
        out = np.empty_like(th)
        pos = np.empty((3, th.shape[1])) if with_positions else None
        for b in _blocks(th.shape[1]):
            out[:, b], st = self._torque(_angles(th, b, base), None if w is None else w[:, b])
            if pos is not None:
                pos[:, b] = self.chain.position(st, self.tool_fid)
        return (out.T, pos.T) if with_positions else out.T

    def first_order(self, base: Angles, wrench: np.ndarray, *, passive: bool) -> tuple[np.ndarray, np.ndarray]:
        """Yang's first-order correction at the planned angles ``base``, in one pass: the joint
        deflections ``c ⊙ J^T W`` (with ``passive`` ``c ⊙ (J^T W - g - M e2)``) (n, 6) and the
        load-point displacement ``J_p dtheta`` (n, 3) they make."""
        w = _soa(wrench)
        n = base.theta.shape[1]
        dtheta = np.zeros((len(self.c), n))
        moved = np.zeros((3, n))
        if w is None and not (passive and self.gravity):
            return dtheta.T, moved.T
        for b in _blocks(n):
            tau, st = self._torque(_part(base, b), None if w is None else w[:, b], gravity=passive)
            dtheta[:, b] = self.c[:, None] * tau
            moved[:, b] = self.chain.point_velocity(st, self.fid, dtheta[:, b])
        return dtheta.T, moved.T

    def equilibrium(self, q: np.ndarray, wrench: np.ndarray, start: np.ndarray | None = None,
                    base: Angles | None = None) -> np.ndarray:
        """Link angles (n, 6) at the fixed points ``theta = q + offset + c ⊙ tau(theta, W)``,
        from ``start`` (default ``q + offset``); ``base``: :meth:`base_angles` of ``q``."""
        base = self.base_angles(q) if base is None else base
        w = _soa(wrench)
        if not self.gravity and w is None:
            return base.theta.T.copy()
        start = base.theta if start is None else np.asarray(start, dtype=float).T
        return self.fixed_points(base, w, start).T

    def nominal_targets(self, q: np.ndarray, *, tol: float = 1e-12, max_iter: int = 50) -> np.ndarray:
        """Link angles (n, 6) at which the calibrated robot's tool frame has the
        pose the drawing's robot gives it at ``q`` (Newton on the SE(3) error, batched
        over the path and warm-started along it, each sample until ``max |log6| < tol``)."""
        nominal = self.m.nominal if self.m.nominal is not None else self.m.robot
        nchain = BatchedChain(nominal.model)
        nfid = nominal.frame_id(self.m.tool)
        rot_target = np.empty((3, 3, len(q)))
        pos_target = np.empty((3, len(q)))
        drawn = Angles.of((q + nominal.offsets).T)
        for b in _blocks(len(q)):
            st = nchain.state(_part(drawn, b))
            rot_target[:, :, b], pos_target[:, b] = nchain.rotation(st, nfid), nchain.position(st, nfid)
        base = self.base_angles(q)

        def solve(index: np.ndarray, theta: np.ndarray) -> np.ndarray:
            failed = [index[b][self._newton(base.take(index[b]), rot_target[:, :, index[b]], pos_target[:, index[b]],
                                            theta[:, b], tol, max_iter)] for b in _blocks(len(index))]
            return np.concatenate(failed) if failed else np.zeros(0, dtype=int)

        theta, failed = _along_path(solve, base.theta)
        if failed.size:
            raise InputError(f"no configuration of the calibrated robot reaches point {int(failed.min()) + 1} of "
                             "the path as the drawing does (singular or out of reach)")
        return theta.T

    def _newton(self, base: Angles, rot_target: np.ndarray, pos_target: np.ndarray, theta: np.ndarray,
                tol: float, max_iter: int) -> np.ndarray:
        """Newton steps ``theta += J_local^-1 log6(M(theta)^-1 M_target)`` for the samples (6, n) in
        place until each one's error is below ``tol``; returns the columns that did not get there
        (singular Jacobian, no convergence in ``max_iter`` steps)."""
        active = np.arange(theta.shape[1])
        failed = [np.zeros(0, dtype=int)]
        for _ in range(max_iter):
            th = theta[:, active]
            st = self.chain.state(base.take(active).near(th))
            rot = self.chain.rotation(st, self.tool_fid)
            err = log6_local(rot, self.chain.position(st, self.tool_fid), rot_target[:, :, active],
                             pos_target[:, active])
            going = ~(np.max(np.abs(err), axis=0) < tol)
            if not np.any(going):
                return np.concatenate(failed)
            keep = np.flatnonzero(going)
            jac = self.chain.jacobian(st, self.tool_fid)[:, :, keep]
            # LOCAL axes: the frame's own (rotations R^T of the base-aligned rows)
            local = np.concatenate((np.einsum("kan,kjn->ajn", rot[:, :, keep], jac[:3]),
                                    np.einsum("kan,kjn->ajn", rot[:, :, keep], jac[3:])))
            mats = np.moveaxis(local, 2, 0)
            # more joints than the pose has coordinates (an arm on a track): the least joint motion,
            # J^T (J J^T)^-1 err; six: J^-1 err
            redundant = mats.shape[2] > mats.shape[1]
            square = mats @ np.swapaxes(mats, 1, 2) if redundant else mats
            det = np.linalg.det(square)
            singular = ~(np.abs(det) > 1e-12)
            if np.any(singular):
                failed.append(active[keep[singular]])
                keep, mats, square = keep[~singular], mats[~singular], square[~singular]
            step = np.linalg.solve(square, np.moveaxis(err[:, keep], 1, 0)[:, :, None])
            step = (np.swapaxes(mats, 1, 2) @ step)[:, :, 0] if redundant else step[:, :, 0]
            theta[:, active[keep]] = th[:, keep] + step.T
            active = active[keep]
        return np.concatenate(failed + [active])


def _along_path(solve, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve a per-sample problem along a path, warm-started from the neighbours: every
    WARM_STRIDE-th sample (and the last) from ``start`` (6, n), the others from ``start`` plus
    the correction interpolated between those (on a dense path most of them then need one
    iteration, which confirms the tolerance). ``solve(index, theta)`` solves the samples
    ``index`` in place from ``theta`` (6, len(index)) and returns the path indices of those it
    could not; returns the solution and those indices."""
    n = start.shape[1]
    theta = np.array(start, dtype=float)
    if n <= 2 * WARM_STRIDE:
        return theta, solve(np.arange(n), theta)
    coarse = np.append(np.arange(0, n - 1, WARM_STRIDE), n - 1)
    is_fine = np.ones(n, dtype=bool)
    is_fine[coarse] = False
    fine = np.flatnonzero(is_fine)
    solved = theta[:, coarse]
    failed = solve(coarse, solved)
    guess = theta[:, fine]
    if failed.size == 0:                     # (a sample without a solution gives its neighbours no start)
        guess += _interpolate(solved - theta[:, coarse], coarse, fine)
    failed = np.concatenate([failed, solve(fine, guess)])
    theta[:, coarse] = solved
    theta[:, fine] = guess
    return theta, failed


def _interpolate(values: np.ndarray, coarse: np.ndarray, fine: np.ndarray) -> np.ndarray:
    """``values`` (6, len(coarse)) at the samples ``coarse`` (every WARM_STRIDE-th and the last)
    interpolated to the samples ``fine`` between them: cubic through the four nearest where they
    are evenly spaced, linear between the two nearest at the ends."""
    k = fine // WARM_STRIDE                                 # coarse[k] < i < coarse[k + 1]
    t = (fine - coarse[k]) / (coarse[k + 1] - coarse[k])
    lo, hi = np.maximum(k - 1, 0), np.minimum(k + 2, len(coarse) - 1)
    cubic = (k >= 1) & (hi == k + 2) & (coarse[hi] - coarse[lo] == 3 * WARM_STRIDE)
    w0 = np.where(cubic, -t * (t - 1.0) * (t - 2.0) / 6.0, 0.0)
    w1 = np.where(cubic, (t + 1.0) * (t - 1.0) * (t - 2.0) / 2.0, 1.0 - t)
    w2 = np.where(cubic, -(t + 1.0) * t * (t - 2.0) / 2.0, t)
    w3 = np.where(cubic, (t + 1.0) * t * (t - 1.0) / 6.0, 0.0)
    return values[:, lo] * w0 + values[:, k] * w1 + values[:, k + 1] * w2 + values[:, hi] * w3


def _soa(wrench: np.ndarray) -> np.ndarray | None:
    """The wrench (n, 6) as (6, n) rows, None when it is zero everywhere."""
    return np.ascontiguousarray(wrench.T) if np.any(wrench) else None


def _part(ang: Angles, b: slice) -> Angles:
    return Angles(ang.theta[:, b], ang.cos[:, b], ang.sin[:, b])


def _angles(theta: np.ndarray, b: slice, base: Angles | None) -> Angles:
    """Block ``b`` of the angles ``theta`` (6, n), from the cos/sin of ``base`` when given."""
    return Angles.of(theta[:, b]) if base is None else _part(base, b).near(theta[:, b])


class NotConverged(InputError):
    """The equilibrium of sample ``sample`` (0-based; the first such sample of the path) has no
    fixed point: the load is too large for the stiffness. The command names the file, line and column of the sample."""

    def __init__(self, sample: int) -> None:
        self.sample = sample
        super().__init__(f"the static model does not converge at sample {sample + 1} of the path "
                         "(stiffness too low for the load?)")
