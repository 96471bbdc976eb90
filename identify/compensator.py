"""Gravity-compensator parameters from joint-2 currents over a sweep (Yang §4.1, Klimchik §III).

Joint 2 moves slowly through a range, forward and backward, the other joints
held. (On any chain the swept joint is the one the ``+``/``-`` runs move, the
compensator's: joint 3 of an arm on a track; "joint 2", "q2" and "q3" below
are that joint and the next one.) At one q2 the load torque joint 2 carries is the same both ways and
friction changes sign (the drive supplies it in the direction of motion, docs/formats.md §3:
``xi i = tau_load + f sign(dq)``), so
the mean of the two directions is friction-free::

    xi2 (i_fwd + i_bwd)/2 = tau2_load = [J^T W]_2 - g2(theta) - M(q2)

``M`` is the compensator's balancing torque (Y31-32): hydro-pneumatic
``M = C b sqrt(a^2+h^2) cos(alpha - q2) / (l (l_c - l))`` (Y11, Y34) or spring
``M = K_c (1 - s0/s) a L sin(alpha - q2)`` (K7); formulas and geometry are the
robot description's :class:`~elastocal.model.robot.CompensatorSpec`.

Gravity ``g2`` comes either from the robot model (link masses in robot.toml,
Pinocchio RNEA) or, when the masses are unknown, is identified at the same
time: ``g(theta) = Y(theta) pi`` is linear in the links' inertial parameters
(Pinocchio's joint-torque regressor at zero speed and acceleration); only the
combinations the sweeps excite are kept (an SVD of the stacked joint-2 rows).
One sweep excites two of them (the distal body's mass moment about axis 2);
sweeps at two or more q3 separate link 2's from link 3's. The compensator is
then told apart from gravity only by the shape of ``M(q2)``, which is not a
sinusoid of q2: wide sweeps (about 120 degrees or more) are needed, and the
reported standard deviations say how well it worked.

All fits are least squares on the friction-free mean torques, with the
covariance ``s^2 (J^T J)^-1`` from the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from elastocal.errors import InputError, UnidentifiableError
from elastocal.model.effects import get_effect
from elastocal.model.robot import LOAD_FRAME, Robot
from elastocal.identify.sweepfit import fit_sweeps, sweep_terms
from elastocal.model.kinds import CompensatorKind


@dataclass(frozen=True, eq=False)
class SweepMeans:
    """Friction-free joint-2 torque along the forward/backward sweeps."""

    theta: np.ndarray        # (n, N) link-side configuration at each forward sample
    q2: np.ndarray           # (n,) compensator coordinate (link-side q2) [rad]
    torque: np.ndarray       # (n,) xi2 (i_fwd + i_bwd)/2 [N·m]
    friction: np.ndarray     # (n,) xi2 (i_fwd - i_bwd)/2 at forward speed: joint-2 friction [N·m], > 0
    wrench: np.ndarray       # (n, 6) external wrench on the load point [N, N·m]
    sweep: np.ndarray        # (n,) index of the sweep (same held joints and load)
    #: (n,) variance of the interpolated backward reading per unit variance of one reading,
    #: ``(1 - f)^2 + f^2``: the mean's noise variance is ``xi2^2 sigma2^2 (1 + weight) / 4``
    weight: np.ndarray | None = None
    joint: int = 1           # 0-based index of the swept joint (1: joint 2)


@dataclass(frozen=True, eq=False)
class CompensatorFit:
    """Identified compensator parameters (C, l_c or K_c, s0)."""

    kind: CompensatorKind
    names: tuple[str, str]
    units: tuple[str, str]
    values: np.ndarray               # (2,)
    covariance: np.ndarray           # (2, 2)
    gravity: str                     # "model" (robot masses) or "identified"
    gravity_values: np.ndarray       # (r,) excited gravity combinations [N·m]; empty with "model"
    gravity_covariance: np.ndarray   # (r, r)
    q2: np.ndarray                   # (n,) [rad]
    balancing_torque: np.ndarray     # (n,) M measured: tau2^0 - xi2 i2 with gravity as used [N·m]
    residuals: np.ndarray            # (n,) measured minus modelled joint-2 torque [N·m]
    friction: np.ndarray             # (n,) joint-2 friction torque along the sweeps [N·m]

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2)))

    def parameters(self) -> dict[str, dict[str, float | str]]:
        """docs/formats.md §4 entries for the compensator parameters."""
        return {n: {"value": float(v), "std": float(s), "unit": u}
                for n, v, s, u in zip(self.names, self.values, self.std, self.units)}


# --------------------------------------------------------------- sweep means
#: held joints of two runs closer than this belong to one sweep [rad]
HELD_TOL_RAD = 1e-3


def swept_joint(q: np.ndarray, direction: np.ndarray, run: np.ndarray | None = None,
                 source: str | None = None) -> int:
    """0-based index of the joint the ``+``/``-`` runs move (the one of widest travel in each
    run; ``run`` None: contiguous samples of one direction). Every sweep must move the same one."""
    sweeps = np.isin(direction, ("+", "-"))
    if run is None:
        new = np.ones(len(q), dtype=bool)
        new[1:] = direction[1:] != direction[:-1]
        run = np.cumsum(new).astype(str)
    moved = set()
    for r in dict.fromkeys(run[sweeps]):
        qr = q[(run == r) & sweeps]
        if len(qr) > 1:
            moved.add(int(np.argmax(np.ptp(qr, axis=0))))
    if len(moved) > 1:
        raise InputError("the +/- sweeps move joints " + " and ".join(str(j + 1) for j in sorted(moved)) +
                         "; sweeps of one joint (the compensator's) are one model", source=source,
                         column="direction")
    return moved.pop() if moved else 1


def _sweep_groups(q: np.ndarray, direction: np.ndarray, load: np.ndarray, run: np.ndarray,
                  joint: int) -> list[np.ndarray]:
    """Sample indices of each sweep: the ``+``/``-`` runs with the same load whose
    held joints (all but the swept one) agree within HELD_TOL_RAD."""
    held = np.delete(q, joint, axis=1)
    groups: list[tuple[str, np.ndarray, list[int]]] = []
    for r in dict.fromkeys(run[np.isin(direction, ("+", "-"))]):
        idx = np.flatnonzero(run == r)
        ld, h = str(load[idx[0]]), np.median(held[idx], axis=0)
        for g_load, g_held, members in groups:
            if g_load == ld and np.max(np.abs(g_held - h)) < HELD_TOL_RAD:
                members.extend(idx.tolist())
                break
        else:
            groups.append((ld, h, idx.tolist()))
    return [np.array(members) for _, _, members in groups]


def _contiguous_runs(q: np.ndarray, direction: np.ndarray, load: np.ndarray, joint: int) -> np.ndarray:
    """Run labels from contiguous samples of one direction, load and held configuration."""
    held = np.delete(q, joint, axis=1)
    new = np.ones(len(q), dtype=bool)
    new[1:] = ((direction[1:] != direction[:-1]) | (load[1:] != load[:-1])
               | (np.max(np.abs(np.diff(held, axis=0)), axis=1) >= HELD_TOL_RAD))
    return np.cumsum(new).astype(str)


def sweep_means(robot: Robot, q: np.ndarray, currents: np.ndarray, direction: np.ndarray, load: np.ndarray,
                wrench: np.ndarray | None = None, *, run: np.ndarray | None = None,
                stiffness: Sequence[float] | None = None, source: str | None = None) -> SweepMeans:
    """Pair forward (``+``) and backward (``-``) samples of each sweep at equal q2.

    Runs (``run`` labels; default: contiguous samples of one direction, load
    and held configuration) with the
    same held joints (all but joint 2, within 1 mrad) and the same load form one
    sweep. The backward torque is interpolated in q2 at the forward
    samples inside the common range. ``stiffness`` (N,) [N·m/rad, N/m], when given,
    puts the joints at their deflected angles ``q + offset + xi i / k``. The swept joint
    is the one the runs move (:func:`swept_joint`).
    """
    q = np.asarray(q, dtype=float)
    currents = np.asarray(currents, dtype=float)
    direction = np.asarray(direction, dtype=str)
    load = np.asarray(load, dtype=str)
    n = len(q)
    w = np.zeros((n, 6)) if wrench is None else np.array(wrench, dtype=float)
    unknown = ~np.all(np.isfinite(w), axis=1)
    if np.any(unknown & (load != "0")):
        bad = int(np.flatnonzero(unknown & (load != "0"))[0])
        raise InputError(f"load {load[bad]} has no wrench; the sweep model needs the payload's wrench "
                         "(fx..mz) or load 0", source=source, column="fx")
    w[unknown] = 0.0
    xi = robot.torque_constants
    j = swept_joint(q, direction, None if run is None else np.asarray(run, dtype=str), source)
    run = _contiguous_runs(q, direction, load, j) if run is None else np.asarray(run, dtype=str)
    groups = _sweep_groups(q, direction, load, run, j)
    theta, q2s, torque, friction, wrenches, sweep, weights = [], [], [], [], [], [], []
    for g, idx in enumerate(groups):
        fwd = idx[direction[idx] == "+"]
        bwd = idx[direction[idx] == "-"]
        if len(fwd) < 2 or len(bwd) < 2:
            continue
        if not (np.all(np.isfinite(currents[fwd, j])) and np.all(np.isfinite(currents[bwd, j]))):
            raise InputError(f"a joint-{j + 1} sweep has empty currents; the compensator needs i{j + 1}",
                             source=source, column=f"i{j + 1}")
        tau_f = xi[j] * currents[fwd, j]
        tau_b = xi[j] * currents[bwd, j]
        qb = q[bwd, j]
        order = np.argsort(qb, kind="stable")
        qb, tb = qb[order], tau_b[order]
        inside = (q[fwd, j] >= qb[0]) & (q[fwd, j] <= qb[-1])
        fwd, tau_f = fwd[inside], tau_f[inside]
        tb_at = np.interp(q[fwd, j], qb, tb)
        right = np.clip(np.searchsorted(qb, q[fwd, j]), 1, len(qb) - 1)
        span = qb[right] - qb[right - 1]
        frac = np.clip(np.where(span > 0, (q[fwd, j] - qb[right - 1]) / np.where(span > 0, span, 1.0), 0.0), 0, 1)
        mean = (tau_f + tb_at) / 2.0
        th = robot.theta(q[fwd])
        if stiffness is not None:
            k = np.asarray(stiffness, dtype=float)
            i_mean = currents[fwd].copy()
            i_mean[:, j] = mean / xi[j]
            th = th + xi * i_mean / k
        theta.append(th)
        q2s.append(th[:, j] - robot.joints[j].offset)
        torque.append(mean)
        friction.append((tau_f - tb_at) / 2.0)
        wrenches.append(w[fwd])
        sweep.append(np.full(len(fwd), g))
        weights.append((1.0 - frac) ** 2 + frac ** 2)
    if not torque:
        raise InputError(f"no joint-{j + 1} sweep run both forward (+) and backward (-) under the same load "
                         "and held joints", source=source, column="direction")
    return SweepMeans(theta=np.vstack(theta), q2=np.concatenate(q2s), torque=np.concatenate(torque),
                      friction=np.concatenate(friction), wrench=np.vstack(wrenches), sweep=np.concatenate(sweep),
                      weight=np.concatenate(weights), joint=j)


# --------------------------------------------------------------- the fit
def _external_torque(robot: Robot, theta: np.ndarray, wrench: np.ndarray, joint: int) -> np.ndarray:
    out = np.zeros(len(theta))
    nz = np.any(wrench != 0.0, axis=1)
    data = robot.create_data()
    for k in np.flatnonzero(nz):
        jac = robot.jacobians(theta[k], [LOAD_FRAME], data=data)[0]
        out[k] = (jac.T @ wrench[k])[joint]
    return out


def known_torque(robot: Robot, means: SweepMeans, *, gravity: bool = True) -> np.ndarray:
    """``y`` of identify/sweepfit.py: the mean torque less the external wrench's, plus the
    description's gravity (``gravity=False``: without it)."""
    y = means.torque - _external_torque(robot, means.theta, means.wrench, means.joint)
    if gravity and robot.has_masses:
        data = robot.create_data()
        y = y + np.array([robot.gravity_torque(th, data=data)[means.joint] for th in means.theta])
    return y


def identify_compensator(robot: Robot, means: SweepMeans, *, gravity: str = "model",
                         initial: Sequence[float] | None = None) -> CompensatorFit:
    """Compensator parameters from friction-free sweep torques.

    ``gravity="model"``: g2 from the robot's link masses (they must be given);
    ``gravity="identify"``: the excited gravity combinations are fitted too (their
    values are the whole gravity, not corrections to the description's).
    The terms are the effect modules' (identify/sweepfit.py).
    """
    spec = robot.compensator
    if spec is None:
        raise InputError("the robot description has no [compensator]", source=robot.source)
    if gravity not in ("model", "identify"):
        raise ValueError("gravity must be 'model' or 'identify'")
    if gravity == "model" and not robot.has_masses:
        raise InputError("the robot description gives no link masses: identify the gravity with the "
                         "compensator (sweeps at two or more q3)", source=robot.source)
    effects = [get_effect("compensator")] + ([get_effect("gravity")] if gravity == "identify" else [])
    terms, refused = sweep_terms(robot, means.q2, means.theta, effects, means.joint)
    if refused:
        name, reason = next(iter(refused.items()))
        raise UnidentifiableError(f"{name}: {reason}")
    comp = terms["compensator"]
    if initial is not None:
        comp = replace(comp, start=lambda y, other: np.asarray(initial, dtype=float))
    fitted = [("compensator", comp)] + ([("gravity", terms["gravity"])] if gravity == "identify" else [])
    y = known_torque(robot, means, gravity=gravity == "model")
    fit = fit_sweeps(y, fitted)
    c = fit.slice_of("compensator")
    grav = fit.slice_of("gravity") if gravity == "identify" else slice(2, 2)
    g_values = fit.values[1] if gravity == "identify" else np.zeros(0)
    balancing = -(y + (terms["gravity"].torque(g_values) if gravity == "identify" else 0.0))
    units = tuple(spec.parameter_units[n] for n in spec.parameter_names)
    return CompensatorFit(kind=spec.kind, names=spec.parameter_names, units=units, values=fit.values[0].copy(),
                          covariance=fit.covariance[c, c].copy(),
                          gravity="model" if gravity == "model" else "identified",
                          gravity_values=g_values.copy(), gravity_covariance=fit.covariance[grav, grav].copy(),
                          q2=means.q2, balancing_torque=balancing, residuals=fit.residuals.copy(),
                          friction=means.friction)


def compensator_from_run_table(robot: Robot, table, *, gravity: str = "auto",
                               stiffness: Sequence[float] | None = None) -> CompensatorFit:
    """:func:`identify_compensator` on the ``+``/``-`` sweeps of a run table.

    ``gravity="auto"`` uses the robot's link masses when it has them and
    identifies the gravity otherwise.
    """
    if gravity == "auto":
        gravity = "model" if robot.has_masses else "identify"
    sweeps = np.isin(table.direction, ("+", "-"))
    if not np.any(sweeps):
        raise InputError("the table has no joint sweeps (direction + and -)", source=table.source,
                         column="direction")
    sub = table.subset(sweeps)
    means = sweep_means(robot, sub.q, sub.currents, sub.direction, sub.load, sub.wrench, run=sub.run,
                        stiffness=stiffness, source=table.source)
    return identify_compensator(robot, means, gravity=gravity)
