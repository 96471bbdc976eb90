"""One cycle's joint correction from the plan and the wrench, within limits on size and rate.

``correction = -c ⊙ J(theta*)^T W`` at the cycle's path time (:mod:`elastocal.stream.plan`);
then each joint's correction is clamped to ``max_rad`` and its change from the last cycle's
to ``max_rate_rad_s`` times the cycle. A clamped correction is still sent, and marked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.errors import InputError
from elastocal.stream.plan import StreamPlan

#: defaults of the limits: a correction of 0.2 degrees is several millimetres at the tool of a
#: 2 m robot, above any process deflection a calibration should correct; 0.5 degrees per second
#: lets the correction follow a force that rises by its full size in well under a second
DEFAULT_MAX_CORRECTION_RAD = np.radians(0.2)
DEFAULT_MAX_RATE_RAD_S = np.radians(0.5)


@dataclass(frozen=True)
class Limits:
    """Per-joint limits of the correction: size [rad] and rate of change [rad/s]."""

    max_rad: float = float(DEFAULT_MAX_CORRECTION_RAD)
    max_rate_rad_s: float = float(DEFAULT_MAX_RATE_RAD_S)

    def __post_init__(self) -> None:
        for name in ("max_rad", "max_rate_rad_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{name} must be a positive number, got {v!r}", argument=name)


@dataclass(frozen=True)
class Correction:
    """The correction of one cycle."""

    wanted: np.ndarray         # what the model asks for [rad]
    sent: np.ndarray           # within the limits [rad]
    limited: bool              # some joint clamped (size or rate)


def model_correction(plan: StreamPlan, i: int, w: float, wrench: np.ndarray) -> np.ndarray:
    """``-c ⊙ J(theta*)^T W`` at (i, w) of the path [rad]."""
    return plan.at(plan.gain, i, w) @ wrench


def limit(wanted: np.ndarray, previous: np.ndarray, limits: Limits, dt_s: float) -> Correction:
    """``wanted`` clamped to the size limit, then its change from ``previous`` to the rate limit."""
    sized = np.clip(wanted, -limits.max_rad, limits.max_rad)
    step = limits.max_rate_rad_s * dt_s
    sent = np.clip(sized, previous - step, previous + step)
    return Correction(wanted=wanted, sent=sent, limited=bool(np.any(sent != wanted)))


def wrench_from_currents(plan: StreamPlan, i: int, w: float, currents_a: np.ndarray) -> np.ndarray:
    """The process wrench the motor currents show (base axes, on the load point): the change of
    the joint torques ``xi i`` from the unloaded model's, through ``(J^T)^+`` (least squares
    for a robot of fewer than six joints: the wrench of least norm that explains them)."""
    torque_change = plan.torque_constants * currents_a - plan.at(plan.tau_unloaded, i, w)
    return plan.at(plan.wrench_of_torque, i, w) @ torque_change
