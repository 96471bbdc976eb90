"""Where each cycle's process wrench comes from (docs/stream.md, "Force sources").

* ``sensor``: a force/torque sensor on the tool (ATI Net F/T); its wrench, in the sensor's
  axes (taken as the load point frame's), is turned into base axes with the tool's
  orientation at the plan's unloaded pose. Latency: the sensor's record period plus the
  network; a sample older than ``max_age_s`` makes the cycle late.
* ``currents``: the motor currents the controller sends each cycle (RSI ``MACur``, EGM test
  signals): the change of the joint torques ``xi i`` from the calibrated model's unloaded
  torques, through ``(J^T)^+``. No extra hardware; its noise is the currents' noise through
  ``J^-T``, and anything the model's unloaded torques miss (friction while moving, a wrong
  gravity model) shows up as a wrench.
* ``path``: the wrench the path file gives per sample, or one constant wrench: no
  measurement at all, as the offline program assumes.

Every source returns a :class:`WrenchReading` or None (no fresh value: the cycle is late).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Callable

import numpy as np

from elastocal.drivers.force import ForceSensor
from elastocal.drivers.guidance import ControllerState
from elastocal.errors import InputError, ProtocolError
from elastocal.stream.correction import wrench_from_currents
from elastocal.stream.plan import StreamPlan


class ForceSourceKind(enum.Enum):
    SENSOR = "sensor"
    CURRENTS = "currents"
    PATH = "path"


@dataclass(frozen=True)
class WrenchReading:
    wrench: np.ndarray         # (6,) on the load point, base axes [N, N·m]
    t_ns: int                  # when it was measured (the sample's or the controller message's arrival)


class SensorSource:
    """``bias``: the sensor's reading with the tool off the workpiece (its weight, the gauges'
    offset), in the sensor's axes, taken away from every sample (:func:`tare`)."""

    kind = ForceSourceKind.SENSOR

    def __init__(self, sensor: ForceSensor, plan: StreamPlan, *, max_age_s: float,
                 bias: np.ndarray | None = None, age_clock_ns: Callable[[], int] | None = None) -> None:
        self.sensor = sensor
        self.plan = plan
        self.max_age_ns = int(max_age_s * 1e9)
        self.bias = np.zeros(6) if bias is None else np.asarray(bias, dtype=float)
        # the clock the samples' arrivals are stamped on, when the loop runs on another one (a
        # simulated controller's time): the age is taken on it, the reading put on the loop's
        self.age_clock_ns = age_clock_ns

    def read(self, state: ControllerState, i: int, w: float, now_ns: int) -> WrenchReading | None:
        sample = self.sensor.latest()          # raises what stopped the sensor's stream
        if sample is None:
            return None
        age_ns = (now_ns if self.age_clock_ns is None else self.age_clock_ns()) - sample.t_ns
        if age_ns > self.max_age_ns:
            return None
        rot = self.plan.at(self.plan.tool_rotation, i, w)
        local = sample.wrench - self.bias
        wrench = np.concatenate((rot @ local[:3], rot @ local[3:]))
        return WrenchReading(wrench=wrench, t_ns=now_ns - age_ns)


def tare(sensor: ForceSensor, duration_s: float, *, clock=None) -> np.ndarray:
    """The mean of the sensor's distinct samples over ``duration_s`` (the tool off the workpiece)."""
    import time

    clock = clock or time.monotonic
    seen: dict[int, np.ndarray] = {}
    end = clock() + duration_s
    while clock() < end or not seen:
        s = sensor.latest()
        if s is not None:
            seen[s.sequence] = s.wrench
        time.sleep(0.0005)
        if clock() > end + 1.0:
            break
    if not seen:
        return np.zeros(6)
    return np.mean(np.array(list(seen.values())), axis=0)


class CurrentsSource:
    """``filter_s``: the time constant of a first-order low-pass on the estimated wrench (the
    currents' noise through ``J^-T`` is large; the process force changes slowly): its price is
    a lag of about ``filter_s`` behind a changing force."""

    kind = ForceSourceKind.CURRENTS

    def __init__(self, plan: StreamPlan, *, filter_s: float, cycle_s: float) -> None:
        if not filter_s >= 0:
            raise InputError(f"the current filter's time constant must be >= 0 s, got {filter_s!r}",
                             argument="current_filter_s")
        if plan.torque_constants is None:
            raise InputError("the motor currents give torques only with a torque_constant for every joint in the "
                             "robot description", argument="source")
        self.plan = plan
        self.alpha = 1.0 if filter_s == 0 else 1.0 - float(np.exp(-cycle_s / filter_s))
        self._state: np.ndarray | None = None

    def read(self, state: ControllerState, i: int, w: float, now_ns: int) -> WrenchReading | None:
        if state.currents_a is None:
            raise ProtocolError("the controller sends no motor currents: declare DEF_MACur in the RSI "
                                "configuration, or the TestSignDefine channels of the EGM program (docs/stream.md)")
        raw = wrench_from_currents(self.plan, i, w, state.currents_a)
        self._state = raw if self._state is None else self._state + self.alpha * (raw - self._state)
        return WrenchReading(wrench=self._state.copy(), t_ns=state.t_ns)


class PathSource:
    kind = ForceSourceKind.PATH

    def __init__(self, plan: StreamPlan, wrench: np.ndarray) -> None:
        wrench = np.asarray(wrench, dtype=float)
        if wrench.shape == (6,):
            wrench = np.tile(wrench, (len(plan.t), 1))
        if wrench.shape != (len(plan.t), 6) or not np.all(np.isfinite(wrench)):
            raise InputError("the path's wrench needs 6 finite values per sample", argument="wrench")
        self.plan = plan
        self.wrench = wrench

    def read(self, state: ControllerState, i: int, w: float, now_ns: int) -> WrenchReading:
        return WrenchReading(wrench=self.plan.at(self.wrench, i, w), t_ns=now_ns)
