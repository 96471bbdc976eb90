"""The stream's cycle: the controller's state in, the corrected joint targets out (docs/stream.md).

Each cycle, when the controller's state message arrives: the path time is the controller's
own clock since its first message (so the path runs at the robot's pace whatever this
computer's scheduling does); the wrench comes from the force source; the correction from the
plan (:mod:`elastocal.stream.correction`), within its limits; the answer is the planned joints
plus the correction. A cycle is *late* when the message waited longer than the budget before
the loop got to it, when the force source has no fresh wrench, or when the computation ran
past the budget: the answer then holds the last correction (the plan still advances), and
the cycle is counted. Three late cycles in a row stop the stream (:class:`WatchdogFault`).
Lateness is judged on the injected ``clock_ns`` (the wall clock for a real controller, the
controller's own time for a simulated one in lockstep: :mod:`elastocal.stream.clock`); the
computation's time is measured on ``measure_ns`` (default the same clock).
Messages the controller lost are counted from the jumps of its clock. Nothing here prints
or writes a file: every cycle and event goes to the ``sink``.
"""

from __future__ import annotations

import enum
import gc
import time
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from elastocal.drivers.guidance import ControllerRefused, Guidance
from elastocal.errors import DeviceFault, InputError
from elastocal.stream.correction import Limits, limit, model_correction
from elastocal.stream.plan import StreamPlan


#: what the default budget leaves of the cycle for the network and the controller [s]
BUDGET_MARGIN_S = 0.0005


class LateCause(enum.Enum):
    SCHEDULE = "schedule"      # the state message waited past the budget before the loop got to it
    FORCE = "force"            # no fresh wrench from the force source
    COMPUTE = "compute"        # the cycle's computation ran past the budget


class StreamFault(DeviceFault):
    """The stream stopped itself: the robot holds the last target the controller received."""


class WatchdogFault(StreamFault):
    """Too many late cycles in a row; ``cause`` is the last one's."""

    def __init__(self, message: str, cause: LateCause) -> None:
        self.cause = cause
        super().__init__(message)


class NotAtStart(StreamFault):
    """The robot is not where the path starts: the stream would jump to it."""


@dataclass(frozen=True)
class StreamSettings:
    limits: Limits = Limits()
    #: how long after its state message arrived the answer may leave (default: the controller's cycle
    #: less BUDGET_MARGIN_S: the answer is then at the controller before its next cycle)
    budget_s: float | None = None
    max_late_in_row: int = 3
    #: how far the robot may stand from the path's first point when guidance starts [rad]
    start_tolerance_rad: float = 1e-3
    #: the path's last point is held this long after its end (the controller's program ends guidance)
    end_hold_s: float = 0.5
    #: how long to wait for the controller's first message (the operator starts its program)
    first_state_timeout_s: float = 60.0


@dataclass(frozen=True)
class CycleRecord:
    """What one cycle did."""

    cycle: int
    sequence: int
    t_ns: int                          # the state message's arrival
    t_path_s: float
    q_planned: np.ndarray
    correction: np.ndarray             # sent [rad]
    wanted: np.ndarray | None          # what the model asked for (None in a late cycle)
    q_sent: np.ndarray
    q_measured: np.ndarray
    wrench: np.ndarray | None          # base axes, on the load point (None: no fresh wrench)
    wrench_age_ns: int | None
    compute_ns: int                    # from taking up the message to the answer's send
    response_ns: int                   # from the message's arrival to the answer's send
    period_ns: int                     # since the previous message's arrival (0 for the first)
    late: LateCause | None
    limited: bool
    lost_before: int                   # controller messages lost just before this one


class Sink(Protocol):
    def cycle(self, record: CycleRecord) -> None: ...

    def event(self, kind: str, **fields) -> None: ...


@dataclass(frozen=True)
class StreamResult:
    cycles: int
    late: int
    lost: int
    limited: int
    compute_ns: np.ndarray
    response_ns: np.ndarray
    period_ns: np.ndarray
    cycle_s: float


class _Counters:
    def __init__(self) -> None:
        self.late = self.lost = self.limited = self.late_run = 0
        self.compute: list[int] = []
        self.response: list[int] = []
        self.period: list[int] = []


def run_stream(guidance: Guidance, source, plan: StreamPlan, sink: Sink, *,
               settings: StreamSettings = StreamSettings(), clock_ns: Callable[[], int] = time.monotonic_ns,
               should_stop: Callable[[], bool] = lambda: False,
               measure_ns: Callable[[], int] | None = None) -> StreamResult:
    """Guide the robot along ``plan`` with the corrections of ``source``'s wrenches (see the
    module docstring). Raises the typed faults of the loop and of the devices.

    Python's cyclic garbage collector is off while the stream runs: a full collection over a
    large heap stops every thread for tens of milliseconds, a dozen cycles; the loop makes no
    reference cycles (its objects go by reference counting), and the collector is back on
    afterwards."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        return _run(guidance, source, plan, sink, settings, clock_ns, should_stop, measure_ns)
    finally:
        if collecting:
            gc.enable()


def _run(guidance, source, plan, sink, settings, clock_ns, should_stop, measure_ns) -> StreamResult:
    if plan.n_joints != guidance.n_joints:
        raise InputError(f"the path has {plan.n_joints} joints, the guidance channel {guidance.n_joints}")
    cycle_s = guidance.cycle_s
    budget_s = settings.budget_s if settings.budget_s is not None else max(cycle_s - BUDGET_MARGIN_S, 0.5 * cycle_s)
    budget_ns = int(budget_s * 1e9)
    state = guidance.receive(settings.first_state_timeout_s)
    if not state.ready:
        raise ControllerRefused(f"{guidance.name}: motors off or the program not running; start the guided program")
    off = np.abs(state.q - plan.q[0])
    if np.max(off) > settings.start_tolerance_rad:
        j = int(np.argmax(off))
        raise NotAtStart(f"the robot stands {np.degrees(off[j]):.4f} deg from the path's start at q{j + 1} "
                         f"(tolerance {np.degrees(settings.start_tolerance_rad):.4f} deg); move it to the first "
                         "point of the path before guidance starts")
    sink.event("run_start", run="stream", q=plan.q[0].tolist())
    t0_ms = state.controller_time_ms
    end_s = plan.duration_s + settings.end_hold_s
    previous = np.zeros(plan.n_joints)
    count = _Counters()
    cycle, lost, prev_t_ns, prev_ms = 0, 0, None, None
    while True:
        now = clock_ns()
        started = now if measure_ns is None else measure_ns()
        t_path = (state.controller_time_ms - t0_ms) * 1e-3
        i, w = plan.locate(t_path)
        q_plan = plan.at(plan.q, i, w)
        late, reading, wanted, limited = None, None, None, False
        sent = previous
        if now - state.t_ns > budget_ns:
            late = LateCause.SCHEDULE
        else:
            reading = source.read(state, i, w, now)
            if reading is None:
                late = LateCause.FORCE
            else:
                wanted = model_correction(plan, i, w, reading.wrench)
                corr = limit(wanted, previous, settings.limits, cycle_s * (1 + lost))
                if clock_ns() - state.t_ns > budget_ns:
                    late = LateCause.COMPUTE
                else:
                    sent, limited = corr.sent, corr.limited
        q_sent = q_plan + sent
        guidance.send(q_sent)
        compute_ns = (clock_ns() if measure_ns is None else measure_ns()) - started
        record = CycleRecord(
            cycle=cycle, sequence=state.sequence, t_ns=state.t_ns, t_path_s=t_path, q_planned=q_plan,
            correction=sent, wanted=wanted, q_sent=q_sent, q_measured=state.q,
            wrench=None if reading is None else reading.wrench,
            wrench_age_ns=None if reading is None else now - reading.t_ns, compute_ns=compute_ns,
            response_ns=now - state.t_ns + compute_ns, period_ns=0 if prev_t_ns is None else state.t_ns - prev_t_ns,
            late=late, limited=limited, lost_before=lost)
        _count(count, record, prev_t_ns is not None)
        sink.cycle(record)
        if late is not None and count.late_run >= settings.max_late_in_row:
            raise WatchdogFault(f"{count.late_run} late cycles in a row (the last: {late.value}); the robot holds "
                                f"the last target it received; {_late_hint(late)}", late)
        previous = sent
        if t_path >= end_s or should_stop():
            break
        prev_t_ns, prev_ms = state.t_ns, state.controller_time_ms
        state = guidance.receive()
        lost = max(0, int(round((state.controller_time_ms - prev_ms) * 1e-3 / cycle_s)) - 1 - state.skipped)
        if state.skipped:          # messages this computer fell behind on: never answered, so late
            count.late += state.skipped
            count.late_run += state.skipped
            sink.event("gap", device=guidance.name, missing=state.skipped,
                       text=f"{state.skipped} state message(s) left unanswered: this computer fell behind")
        if lost:
            count.lost += lost
            sink.event("gap", device=guidance.name, missing=lost,
                       text=f"{lost} state message(s) of the controller lost")
        cycle += 1
    return StreamResult(cycles=cycle + 1, late=count.late, lost=count.lost, limited=count.limited,
                        compute_ns=np.array(count.compute, dtype=np.int64),
                        response_ns=np.array(count.response, dtype=np.int64),
                        period_ns=np.array(count.period, dtype=np.int64), cycle_s=cycle_s)


def _count(count: _Counters, record: CycleRecord, has_period: bool) -> None:
    count.compute.append(record.compute_ns)
    count.response.append(record.response_ns)
    if has_period:
        count.period.append(record.period_ns)
    if record.late is not None:
        count.late += 1
        count.late_run += 1
    else:
        count.late_run = 0
    if record.limited:
        count.limited += 1


def _late_hint(cause: LateCause) -> str:
    return {LateCause.SCHEDULE: "this computer answered too slowly: give the stream a core of its own",
            LateCause.FORCE: "the force source delivered no fresh wrench: check the sensor and its cable",
            LateCause.COMPUTE: "the correction took longer than the budget"}[cause]
