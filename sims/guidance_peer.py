"""The cycle of a simulated robot controller under external guidance (EGM and RSI share it).

Every cycle the controller sends its state to the guiding computer and waits for the
answer until the cycle ends: an answer in time moves the simulated robot
(:class:`~elastocal.sims.guided.GuidedRobot`) to its target; none, or one too late, holds
the robot where it is and is counted. A controller that hears nothing for
``comm_timeout_s`` stops guiding (as EGM's communication timeout and RSI's late-packet limit
do) and stops sending. Everything goes to the computer's address on this machine only.

Two clocks: on the wall clock (``lockstep=False``) each cycle lasts ``cycle_s`` of this
machine's time and an answer that misses the cycle's end is late, as on a real controller, so
a busy machine makes late cycles. In ``lockstep`` (simulated time) each cycle waits for its
answer up to ``comm_timeout_s`` of wall time and then advances the controller's clock by
exactly one cycle: the guiding computer sees the controller's time only, and a cycle is late
only when a fault is injected (a lost message, silence) or the computer does not answer at
all. Both pace the cycles at most as fast as the wall clock, so a sensor streaming on the
wall clock keeps up.
"""

from __future__ import annotations

import abc
import enum
import select
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from elastocal.sims.guided import Faults, GuidedRobot


class PeerState(enum.Enum):
    IDLE = "idle"            # not started
    GUIDING = "guiding"
    STOPPED = "stopped"      # guidance ended: communication timeout, late limit, a fault


@dataclass(frozen=True)
class PeerStats:
    cycles: int              # cycles run
    sent: int                # state messages sent
    answered: int            # answers in time, applied
    late: int                # cycles without an answer in time
    state: PeerState
    reason: str              # why it stopped ('' while it guides)


class SimGuidedController(abc.ABC):
    """Base of the simulated EGM and RSI controllers (see the module docstring)."""

    def __init__(self, robot: GuidedRobot, computer: tuple[str, int], *, cycle_s: float,
                 faults: Faults = Faults(), comm_timeout_s: float = 0.5, bind_host: str = "127.0.0.1",
                 lockstep: bool = False) -> None:
        if not computer[0].startswith("127."):
            raise ValueError("a simulated controller talks to this machine only (127.0.0.0/8)")
        self.robot = robot
        self.computer = (computer[0], int(computer[1]))
        self.cycle_s = float(cycle_s)
        self.faults = faults
        self.comm_timeout_s = float(comm_timeout_s)
        self.lockstep = bool(lockstep)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((bind_host, 0))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._cycles = self._sent = self._answered = self._late = 0
        self._state = PeerState.IDLE
        self._reason = ""
        self._t0_ns = 0

    # --------------------------------------------------------------- control
    def start(self) -> "SimGuidedController":
        if self._thread is None:
            self._t0_ns = time.monotonic_ns()
            self._state = PeerState.GUIDING
            self._thread = threading.Thread(target=self._run, name=f"sim-{type(self).__name__}", daemon=True)
            self._thread.start()
        return self

    def wait_stopped(self, timeout_s: float) -> bool:
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._sock.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def stats(self) -> PeerStats:
        with self._lock:
            return PeerStats(cycles=self._cycles, sent=self._sent, answered=self._answered, late=self._late,
                             state=self._state, reason=self._reason)

    def controller_ms(self, cycle: int) -> int:
        """The controller's clock [ms] at ``cycle``: its interpolation clock, one cycle per cycle (a
        real controller's is hard real-time; this process's thread may run late on a loaded
        machine, and the robot's time must not jump when it does)."""
        return int(round(cycle * self.cycle_s * 1000))

    # ------------------------------------------------------------ the cycle
    def _run(self) -> None:
        cycle_ns = int(round(self.cycle_s * 1e9))
        next_ns = time.monotonic_ns()
        last_answer_ns = next_ns
        cycle = 0
        while not self._stop.is_set():
            silent = self.faults.silent_from_cycle is not None and cycle >= self.faults.silent_from_cycle
            deadline = next_ns + cycle_ns
            target = None
            if not silent:
                sent = cycle not in self.faults.lost_cycles
                if sent:
                    self._sock.sendto(self._state_message(cycle, next_ns), self.computer)
                    with self._lock:
                        self._sent += 1
                if not self.lockstep:
                    target = self._wait_answer(cycle, deadline)
                elif sent:         # simulated time: the cycle ends when its answer comes
                    target = self._wait_answer(cycle, time.monotonic_ns() + int(self.comm_timeout_s * 1e9))
            t_s = self.controller_ms(cycle) * 1e-3
            if target is not None:
                self.robot.step(target, t_s)
                last_answer_ns = time.monotonic_ns()
                with self._lock:
                    self._answered += 1
            else:
                self.robot.hold(t_s)
                with self._lock:
                    self._late += 1
            with self._lock:
                self._cycles += 1
            if time.monotonic_ns() - last_answer_ns > self.comm_timeout_s * 1e9:
                self._finish(f"no answer for {self.comm_timeout_s:g} s: guidance stopped")
                return
            cycle += 1
            next_ns = deadline
            pause = (next_ns - time.monotonic_ns()) * 1e-9
            if pause > 0:
                time.sleep(pause)
            else:
                next_ns = time.monotonic_ns()      # overrun: the next cycle starts now

    def _wait_answer(self, cycle: int, deadline_ns: int) -> np.ndarray | None:
        """Answers until the cycle's deadline; the joint target of the first one that answers
        this cycle (earlier cycles' stragglers are dropped), None when none does."""
        while True:
            left = (deadline_ns - time.monotonic_ns()) * 1e-9
            if left <= 0:
                return None
            ready, _, _ = select.select([self._sock], [], [], left)
            if not ready:
                return None
            try:
                data, _ = self._sock.recvfrom(65536)
            except OSError:
                return None
            target = self._answer_target(data, cycle)
            if target is not None:
                return target

    def _finish(self, reason: str) -> None:
        with self._lock:
            self._state = PeerState.STOPPED
            self._reason = reason

    @abc.abstractmethod
    def _state_message(self, cycle: int, t_ns: int) -> bytes: ...

    @abc.abstractmethod
    def _answer_target(self, data: bytes, cycle: int) -> np.ndarray | None:
        """The joint target [rad] an answer carries when it answers ``cycle``; None otherwise."""
