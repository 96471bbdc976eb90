"""nonlinear_stiffness: gear stiffness that changes with the torque it carries.

Gear makers publish torque-stiffness curves: a strain-wave or cycloid gear is
softer at small torque and stiffer at large (hardening), docs/physics.md's
``dtau/dtheta = k0 (1 + |tau| / T)``. Integrated, the twist of joint ``j`` is

    theta_j = c_j g(tau_j, h_j),   g(tau, h) = sign(tau) ln(1 + h |tau|) / h,

``c_j = 1/k0_j`` and ``h_j = 1/T_j`` (h < 0: softening). The fit's parameter is
``phi_j = c_j h_j`` [rad/(N·m)^2], which enters as ``phi_j (g - tau) / h``: the
basis is rebuilt from the current estimate at every iteration
(``Effect.iterative``), and starts from its small-h limit ``-tau |tau| / 2``.
Reported per joint: ``T1..T6`` [N·m], the torque at which the stiffness has
doubled (negative: softening, the torque at which it would reach zero), ``T_j = c_j / phi_j`` with its std by
the delta method.

A joint shows it only where the loads span a torque range: the torque change
and the spread of the carried torque over the load states must exceed the
torque noise many times (:data:`VISIBLE_NOISE`); other joints have a zero basis
column and are reported unidentifiable, not fitted to noise.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import Effect, StaticBasis, StaticContext, diagonal_basis, strongest
from elastocal.model.effects.base import joint_names, joint_units
from elastocal.model.kinds import TorqueSource

#: a joint shows a torque-dependent stiffness when its torque change and the spread of
#: the torque it carries over the loads exceed this many torque-noise std
VISIBLE_NOISE = 10.0
#: the torque at which the stiffness doubles, for the smallest nonlinearity worth finding
#: (phi = c / T): gear makers' curves change slope within a few kN·m on arm gears [N·m]
DESIGN_DOUBLING_NM = 3000.0
#: torque noise assumed without repeated readings [N·m]
DEFAULT_TORQUE_NOISE_NM = 1.0


def _estimates(ctx: StaticContext) -> tuple[np.ndarray, np.ndarray]:
    n = ctx.tau.shape[1]
    c = np.array([ctx.estimated(f"c{j}") or 0.0 for j in range(1, n + 1)])
    phi = np.array([ctx.estimated(f"nl{j}") or 0.0 for j in range(1, n + 1)])
    return c, phi


def _h(c: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return np.where(c > 0, phi / np.where(c > 0, c, 1.0), 0.0)


def _secant(tau: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(g(tau, h) - tau) / h, with its limit -tau |tau| / 2 at small h |tau|."""
    x = h * np.abs(tau)
    small = np.abs(x) < 1e-6
    safe_h = np.where(small, 1.0, h)
    safe_x = np.where(small, 0.0, np.maximum(x, -0.999999))
    exact = (np.sign(tau) * np.log1p(safe_x) / safe_h - tau) / safe_h
    return np.where(small, -0.5 * tau * np.abs(tau), exact)


def visible_joints(ctx: StaticContext) -> np.ndarray:
    noise = ctx.torque_noise if ctx.torque_noise is not None else np.full_like(ctx.tau, DEFAULT_TORQUE_NOISE_NM)
    loaded = ~ctx.state_is_reference
    if not np.any(loaded):
        return np.zeros(ctx.tau.shape[1], dtype=bool)
    sigma = noise.max(axis=0)
    change = np.abs(ctx.delta_tau[loaded]).max(axis=0)
    spread = np.ptp(np.abs(ctx.tau), axis=0)
    return (change > VISIBLE_NOISE * sigma) & (spread > VISIBLE_NOISE * sigma)


def _basis(ctx: StaticContext) -> StaticBasis:
    c, phi = _estimates(ctx)
    values = _secant(ctx.tau, _h(c, phi)[None, :]) * visible_joints(ctx)
    return StaticBasis(theta=diagonal_basis(values))


def _sensitivity(ctx: StaticContext, values: np.ndarray) -> np.ndarray:
    """What the effect adds to d theta / d tau: c / (1 + h |tau|) - c."""
    c, _ = _estimates(ctx)
    h = _h(c, values)
    return (c / (1.0 + np.maximum(h * np.abs(ctx.tau), -0.999999)) - c) * visible_joints(ctx)


def _refusal(ctx: StaticContext) -> str | None:
    if ctx.torque_source is TorqueSource.FORCE:
        return ("with force-based torques a stiffness law cannot be told from static friction taking part of "
                "each load (both bend the deflection-load line); test it with the currents")
    if not np.any(visible_joints(ctx)):
        return ("no joint's torque changes over a range the noise can resolve, so a stiffness that changes "
                "with the torque cannot show; add loads that span a torque range")
    return None


def _report_with_model(names, beta, cov, own: slice):
    """T_j = c_j / phi_j and its std from the covariance of (c_j, phi_j)."""
    n = own.stop - own.start
    c = beta[:n]
    phi = beta[own]
    safe = np.where(phi != 0, phi, np.nan)
    t = c / safe
    std = np.empty(n)
    idx = np.arange(own.start, own.stop)
    for j in range(n):
        g = np.array([1.0 / safe[j], -c[j] / safe[j] ** 2])   # dT/dc, dT/dphi
        sub = cov[np.ix_([j, idx[j]], [j, idx[j]])]
        std[j] = float(np.sqrt(max(g @ sub @ g, 0.0)))
    return t, std


def _describe(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str:
    k = strongest(names, 1.0 / np.where(values != 0, values, np.inf), stds / np.maximum(values**2, 1e-300))
    word = "hardens" if values[k] > 0 else "softens"
    return (f"deflection not proportional to the torque: joint {names[k][1:]} {word} with the torque it carries "
            f"(its stiffness {'doubles' if values[k] > 0 else 'halves'} at about {abs(values[k]):.3g} N*m)")


def make(robot=None) -> Effect:
    """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
    return Effect(
        name="nonlinear_stiffness",
        parameters=joint_names("nl", robot),
        units=joint_units("rad/(N*m)^2", "m/N^2", robot),
        report_names=joint_names("T", robot),
        report_units=joint_units("N*m", "N", robot),
        seen_in=("static",),
        explanation="a gear's stiffness changes with the torque it carries (hardening or softening, as gear makers' "
                    "torque-stiffness curves show), so deflection is not proportional to the load",
        evidence="deflection grows less (or more) than in proportion to the joint torque",
        static_basis=_basis,
        static_refusal=_refusal,
        iterative=True,
        torque_sensitivity=_sensitivity,
        describe=_describe,
        report_with_model=_report_with_model,
        sized=make,
        design_size=lambda c: np.asarray(c, dtype=float) / DESIGN_DOUBLING_NM,
        static_model="each joint angle is c_j sign(tau) ln(1 + |tau|/T_j) T_j instead of c_j tau: stiffness "
                     "k_j (1 + |tau|/T_j)",
        run_model="not in the torque model: the spring law changes positions, not joint torques",
    )


EFFECT = make()
