"""thermal_drift: tracker readings drift linearly with time.

Parameters vx, vy, vz [m/s] in the tracker (base) frame; deflection d gains
v * (t_loaded - t_reference), the mean times of the loaded and reference
readings. Needs the time column of the static table. Typical causes: the room,
the tracker or the robot base warming up (a few tenths of a millimetre per hour
in the first hour). Absolute positions (identify/absolute.py) see it in every
reading: v times the time since the table's first reading.
"""

from __future__ import annotations

import numpy as np

from elastocal.model.effects.base import AbsoluteBasis, Compensation, Effect, StaticBasis, StaticContext

#: drift faster than this is no room warming up (typical: tenths of a mm/h) [m/s]
MAX_DRIFT_M_S = 5e-3 / 3600.0


def _basis(ctx: StaticContext) -> StaticBasis:
    add = np.zeros((ctx.n_deflections, 3, 3))
    for axis in range(3):
        add[:, axis, axis] = ctx.deflection_dt
    return StaticBasis(add=add)


def _absolute_basis(ctx: StaticContext) -> AbsoluteBasis:
    t = ctx.dataset.abs_t
    if t is None or not np.any(np.isfinite(t)):
        return AbsoluteBasis()
    add = np.zeros((*t.shape, 3, 3))
    for axis in range(3):
        add[:, :, axis, axis] = t - np.nanmin(t)
    return AbsoluteBasis(add=add)


def _refusal(ctx: StaticContext) -> str | None:
    if not np.all(np.isfinite(ctx.deflection_dt)):
        return "the static table has no times (column t), so a drift with time cannot be seen"
    if np.all(ctx.deflection_dt == 0.0):
        return "loaded and reference readings were taken at the same times"
    return None


def _describe(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str:
    speed = float(np.linalg.norm(values))
    axis = names[int(np.argmax(np.abs(values)))][-1]
    return (f"deflections grow with the time since the reference reading: {speed * 3.6e6:.2f} mm/h, "
            f"mostly along {axis}")


def _plausibility(names: tuple[str, ...], values: np.ndarray, stds: np.ndarray) -> str | None:
    speed = float(np.linalg.norm(values))
    if speed > MAX_DRIFT_M_S:
        return (f"a drift of {speed * 3.6e6:.3g} mm/h, faster than a room or a tracker warms "
                f"(at most {MAX_DRIFT_M_S * 3.6e6:.0f} mm/h)")
    return None


def _absolute_only_refusal(robot, ds) -> str | None:
    """A table without loads shows a drift only through the times of its readings: every reading
    needs its time, and they must span more than an instant."""
    t = ds.abs_t
    if t is None or not (t == t).all():
        return "needs the time t of every reading (a drift shows as the positions creeping with time)"
    if float(np.ptp(t)) <= 0.0:
        return "its readings were all taken at the same time, so a drift with time cannot be seen"
    return None


EFFECT = Effect(
    name="thermal_drift",
    parameters=("vx", "vy", "vz"),
    units=("m/s",) * 3,
    seen_in=("static", "runs"),
    explanation="the tracker's readings creep with time as the room or the robot warms up",
    evidence="deflections grow with the time between the reference and the loaded readings",
    static_basis=_basis,
    absolute_basis=_absolute_basis,
    static_refusal=_refusal,
    describe=_describe,
    plausibility=_plausibility,
    static_model="each deflection gains v (t_loaded - t_reference)",
    run_model="tracked positions of a run gain v t; joint torques are not affected",
    session=True,
    absolute_shows_more=True,
    shown_by_times=True,
    absolute_only_refusal=_absolute_only_refusal,
    compensation=Compensation.NO_PATH_DEFLECTION,
)
