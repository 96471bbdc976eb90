"""The stream's clock on a simulated controller's own time (``elastocal stream --sim``).

A real controller keeps hard real-time and the stream judges its answers on this computer's
wall clock (:func:`time.monotonic_ns`): a busy computer is late, and that is the point. A
simulated controller in lockstep (it waits for each answer, then advances its clock by one
cycle) has no wall-clock deadline to miss, so the stream judges it on the controller's time:
:class:`ControllerTime` wraps the guidance channel, stamps each state message's arrival with
the controller's clock (``controller_time_ms``) and gives the loop that instant as "now". The
computation's own time is still measured (on the wall clock) and recorded, but not judged;
late cycles then come only from what the cell injects (lost messages, a silent controller or
sensor) or a computer that does not answer at all.
"""

from __future__ import annotations

import dataclasses
import time

from elastocal.drivers.guidance import ControllerState, Guidance

#: where the controller's clock starts on the stream's time line [ns] (any constant does)
ORIGIN_NS = 1_000_000_000


class ControllerTime:
    """The guidance channel with arrivals on the controller's clock; ``clock_ns`` is "now" for the loop."""

    def __init__(self, guidance: Guidance) -> None:
        self.guidance = guidance
        self._now_ns = ORIGIN_NS
        self._first_ms: int | None = None

    @property
    def kind(self):
        return self.guidance.kind

    @property
    def name(self) -> str:
        return self.guidance.name

    @property
    def n_joints(self) -> int:
        return self.guidance.n_joints

    @property
    def cycle_s(self) -> float:
        return self.guidance.cycle_s

    @property
    def address(self):
        return self.guidance.address

    def receive(self, timeout_s: float | None = None) -> ControllerState:
        state = self.guidance.receive(timeout_s)
        if self._first_ms is None:
            self._first_ms = state.controller_time_ms
        # the controller's clock counts from its first message; a 32-bit millisecond counter wraps
        # after 49 days, far beyond one stream
        self._now_ns = ORIGIN_NS + (state.controller_time_ms - self._first_ms) * 1_000_000
        return dataclasses.replace(state, t_ns=self._now_ns)

    def send(self, q_target) -> None:
        self.guidance.send(q_target)

    def clock_ns(self) -> int:
        """Now on the controller's time: the arrival of its newest state message."""
        return self._now_ns


#: the computation's own time is measured on this clock whatever the stream is judged on
measure_ns = time.monotonic_ns
