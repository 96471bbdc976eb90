"""backlash: lost motion when a joint's torque changes sign.

Parameters b1..b6 [rad], the total play of each joint. The play is taken up
over a small torque band: the joint angle gains (b/2) tanh(tau / TAU_BAND_NM),
tau the absolute gear torque of the state (currents, or the force model with
gravity). Static data show the play of a joint only where a load state moves
its torque across zero from the unloaded reference (a hung weight on a wrist
joint that carries almost nothing unloaded, a pull against the gravity torque);
a joint whose torque keeps its sign in every state has a zero basis column and
is reported unidentifiable instead of fitted to noise.

On a table without loads (one absolute reading per pose) the torques are the
robot's own weight at each pose: the play shows where a joint's gravity torque
changes sign across the poses (the gear rests on one flank in some poses, on the
other in others), as a step between those two groups of poses. A joint whose
weight keeps pressing the same flank shows only a constant, which a joint offset
absorbs: it is not determined.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import (
    Effect,
    StaticBasis,
    StaticContext,
    diagonal_basis,
    strongest,
    joint_names,
    joint_units,
    wrong_sign,
)

#: torque over which the play is taken up [N·m]
TAU_BAND_NM = 20.0
#: lost motion beyond this is no gear's play (catalogue gears: a few arcmin) [rad]
MAX_PLAY_RAD = np.radians(1.0)
#: with repeated readings, a load state shows a joint's play only when its torque
#: change is this many noise std (a joint whose torque moves by noise only has no
#: identifiable play)
NOISE_MARGIN = 3.0
#: a joint shows its play only if some load state changes tanh(tau/band)/2 by at
#: least this fraction of the play (one tenth of it)
MIN_VISIBLE_FRACTION = 0.1
#: without loads, a joint shows its play only with this many poses on each flank (its take-up at
#: least half MIN_VISIBLE_FRACTION either way): a step needs poses on both sides
MIN_POSES_PER_FLANK = 3
#: the smallest play worth finding: 0.1 arcmin, a tenth of a precision gear's catalogue
#: value, 30 µm at 1 m [rad]
DESIGN_PLAY_RAD = np.radians(0.1 / 60.0)


def take_up(tau: np.ndarray) -> np.ndarray:
    """Fraction of the play taken up at torque ``tau`` (-0.5 .. 0.5)."""
    return 0.5 * np.tanh(np.asarray(tau, dtype=float) / TAU_BAND_NM)


def visible_joints(ctx: StaticContext) -> np.ndarray:
    """(N,) bool: joints whose play some load state of these data shows."""
    frac = take_up(ctx.tau)
    if ctx.n_deflections == 0:
        return _flanks(frac)
    ref = take_up(ctx.tau - ctx.delta_tau)
    loaded = ~ctx.state_is_reference
    change = np.abs(frac - ref)[loaded]
    if change.size == 0:
        return np.zeros(ctx.tau.shape[1], dtype=bool)
    visible = change >= MIN_VISIBLE_FRACTION
    if ctx.torque_noise is not None:
        # the torque change must be more than its noise: a joint whose torque moves by
        # noise only (joint 1 under a hung weight) shows no play, only noise
        ref_noise = ctx.torque_noise[_reference_index(ctx)[loaded]]
        noise = np.hypot(ctx.torque_noise[loaded], ref_noise)
        visible &= np.abs(ctx.delta_tau[loaded]) > NOISE_MARGIN * noise
    return visible.any(axis=0)


def _flanks(frac: np.ndarray) -> np.ndarray:
    """(N,) bool, without loads: joints whose weight torque leans on both flanks of the gear,
    each in at least MIN_POSES_PER_FLANK poses (a take-up of half MIN_VISIBLE_FRACTION or more)."""
    edge = 0.5 * MIN_VISIBLE_FRACTION
    return ((np.sum(frac >= edge, axis=0) >= MIN_POSES_PER_FLANK)
            & (np.sum(frac <= -edge, axis=0) >= MIN_POSES_PER_FLANK))


def _reference_index(ctx: StaticContext) -> np.ndarray:
    """(S,) index of each state's reference state (the pose's unloaded one)."""
    ds = ctx.dataset
    if ds is not None:
        return np.asarray(ds.state_ref)
    return np.arange(len(ctx.tau))


def _basis(ctx: StaticContext) -> StaticBasis:
    values = take_up(ctx.tau) * visible_joints(ctx)
    return StaticBasis(theta=diagonal_basis(values))


def _sensitivity(ctx: StaticContext, values: np.ndarray) -> np.ndarray:
    """d/dtau of (b/2) tanh(tau/band): current noise near zero torque moves the
    joint through its play."""
    sech2 = 1.0 / np.cosh(np.clip(ctx.tau / TAU_BAND_NM, -350.0, 350.0)) ** 2
    return 0.5 * values * visible_joints(ctx) * sech2 / TAU_BAND_NM


def _refusal(ctx: StaticContext) -> str | None:
    if np.any(visible_joints(ctx)):
        return None
    if ctx.n_deflections == 0:
        return (f"no joint's gravity torque changes sign across the poses (at least {MIN_POSES_PER_FLANK} poses "
                "leaning on each flank of its gear), so no play can show; add poses that turn a joint's weight "
                "torque over")
    return "no load state reverses the torque of any joint, so no play can show; add loads that do"


def _describe(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str:
    k = strongest(names, values, stds)
    return (f"a step in deflection where a load reverses the torque of joint {names[k][1:]} "
            f"(play {values[k] * 180 / np.pi * 60:.2f} arcmin)")


def _plausibility(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str | None:
    reason = wrong_sign(names, values, stds, "a lost motion")
    if reason:
        return reason
    k = int(np.argmax(np.abs(values)))
    if abs(values[k]) > MAX_PLAY_RAD:
        return (f"a lost motion of {values[k] * 180 / np.pi * 60:.0f} arcmin on joint {names[k][1:]} "
                f"(no gear has more than {MAX_PLAY_RAD * 180 / np.pi * 60:.0f} arcmin)")
    return None


def _absolute_only_refusal(robot, ds) -> str | None:
    """A table without loads shows the play where a joint's weight torque changes sign: it needs the masses."""
    if not robot.has_masses:
        return ("needs the link masses (mass and com per [[joint]]): the play shows where a joint's weight torque "
                "changes sign")
    return None


def make(robot=None) -> Effect:
    """The effect for ``robot``'s joints (a six-axis revolute arm without one)."""
    return Effect(
        name="backlash",
        parameters=joint_names("b", robot),
        units=joint_units("rad", "m", robot),
        seen_in=("static", "runs"),
        explanation="a gear has play that shows as a jump when the torque on the joint reverses",
        evidence="a step in deflection when a load reverses the torque of a joint",
        static_basis=_basis,
        static_refusal=_refusal,
        torque_sensitivity=_sensitivity,
        describe=_describe,
        plausibility=_plausibility,
        sized=make,
        design_size=lambda c: np.full(len(c), DESIGN_PLAY_RAD),
        static_model="each joint angle gains (b_j/2) tanh(tau_j / 20 N·m) besides the spring's c_j tau_j",
        run_model="at a direction reversal the motor turns through the play before the link follows; "
                  "it shows in tracked positions, not in currents",
        absolute_only_refusal=_absolute_only_refusal,
        # on a table without loads: the play under the robot's own weight, with the twist the same
        # weight gives the springs (an arm carrying its weight twists its gears)
        self_weight=True,
        fitted_with=("joint_stiffness",),
    )


EFFECT = make()
