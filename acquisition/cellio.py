"""What a procedure needs from a cell: move, sample, and (simulated) loads.

:class:`CellIO` is the one interface the procedure engine drives. Samples carry
their acquisition time in integer ns from the IO's monotonic clock
(``CellIO.clock``), the clock the recorder stamps events with.

* :class:`elastocal.acquisition.drivercell.DriverCellIO` drives a real or
  simulated cell through elastocal.drivers (CANopen/Modbus drives, tracker,
  cell controller).
* :class:`VirtualCellIO` samples :class:`elastocal.sims.cell.SimCell` physics on
  a virtual clock, faster than real time, with no devices: for benchmarks
  (an hour of 1 kHz samples in minutes) and for fast tests of the engine.

A :class:`LoadWorld` is the simulated world in which loads are hung: with
``--yes`` on a simulated cell the automatic operator hangs each load there.
"""

from __future__ import annotations

import abc
import math
import time
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np

from elastocal.drivers.samples import DriveSample, TrackerSample
from elastocal.model.robot import Robot


@dataclass(frozen=True)
class SampleGap:
    """Samples a device stream lost (reported by the driver, recorded as a ``gap`` event)."""

    device: str
    start_ns: int
    end_ns: int
    missing: int
    reason: str
    joint: int | None = None    # the drive's joint, None for other devices


@dataclass(frozen=True)
class Samples:
    """Samples acquired by one :meth:`CellIO.poll`, each list in time order."""

    drives: tuple[DriveSample, ...]
    tracker: tuple[TrackerSample, ...]
    gaps: tuple[SampleGap, ...] = ()


class LoadWorld(Protocol):
    """Where a simulated load is hung: ``hang(wrench)`` with (fx, fy, fz, mx, my, mz)
    on the load point in base axes, ``None`` to remove every load."""

    def hang(self, wrench: Sequence[float] | None) -> None: ...


class CellIO(abc.ABC):
    """The cell as the procedure engine sees it."""

    robot: Robot
    #: monotonic clock of every timestamp [ns]
    clock: Callable[[], int]
    #: False when the tracker is not read by elastocal but by its own software: the procedure
    #: then settles on the drives, its readings are time windows without tracker samples, and the
    #: software's export is paired with the log by ``elastocal import`` (docs/import.md)
    reads_tracker: bool = True

    @abc.abstractmethod
    def start_move(self, q: Sequence[float], speed_rad_s: float) -> None:
        """Start a joint move to ``q``; the fastest joint moves at ``speed_rad_s``."""

    def start_run(self, start: Sequence[float], end: Sequence[float], speed_rad_s: float) -> None:
        """Start a slow constant-speed pass from ``start`` (where the robot stands)
        to ``end``; the fastest joint moves at ``speed_rad_s``."""
        self.start_move(end, speed_rad_s)

    @abc.abstractmethod
    def move_done(self) -> bool:
        """True when the controller reports the last move finished (in position)."""

    @abc.abstractmethod
    def poll(self, markers: Sequence[str], duration_s: float) -> Samples:
        """Samples acquired over the next ``duration_s`` (drives, and the tracker
        measuring ``markers``); returns after about ``duration_s``."""

    def begin_reading(self, marker: str) -> None:
        """A static reading of ``marker`` starts now: its window opens when this returns (the
        tracker has taken aim at the marker, so nothing read before belongs to the reading)."""

    def motion_reported(self) -> str | None:
        """What says the robot moves (e.g. "the cell controller reports a motion"), None when
        nothing does; the joints' own speeds are judged from the samples."""
        return None if self.move_done() else "a move is running"

    def world(self) -> LoadWorld | None:
        """The simulated world to hang loads in, None for a real cell."""
        return None

    def start(self) -> None:
        """Start acquiring (called once the log is ready, just before the first step)."""

    def close(self) -> None:
        """Stop moving and release the devices."""

    def __enter__(self) -> "CellIO":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------ virtual
@dataclass(frozen=True)
class VirtualTiming:
    """Rates and transients of :class:`VirtualCellIO`."""

    drive_rate_hz: float = 1000.0
    tracker_rate_hz: float = 1000.0
    physics_rate_hz: float = 50.0     # physics evaluated on this grid, interpolated between
    ring_amplitude_m: float = 150e-6  # marker vibration after a move or a load change
    ring_speed_rad_s: float = 0.01    # joint speed vibration after a move or a load change
    ring_tau_s: float = 0.08
    ring_hz: float = 6.0
    start_ns: int = 1_000_000_000
    #: real seconds slept per simulated second in poll (0: as fast as possible)
    pace: float = 0.0


class VirtualCellIO(CellIO):
    """SimCell physics sampled on a virtual clock (no devices, no real waiting).

    Joint moves are straight lines in joint space at constant speed; after a
    move ends or a load changes, markers and joint speeds ring down
    (``VirtualTiming``), so settle detection has something to wait for. During
    motion the currents follow ``SimCell.motion_currents`` (friction on).
    """

    def __init__(self, cell, *, q0: Sequence[float] | None = None, seed: int = 0,
                 timing: VirtualTiming = VirtualTiming()) -> None:
        self.cell = cell
        self.robot = cell.robot
        self.timing = timing
        self._rng = np.random.default_rng(seed)
        self._t_ns = timing.start_ns
        self._next_drive_ns = timing.start_ns
        self._next_tracker_ns = timing.start_ns
        self._tracker_seq = 0
        q0 = np.zeros(6) if q0 is None else np.asarray(q0, dtype=float)
        self._move = (q0, q0, self._t_ns, self._t_ns)  # start, end, t_start, t_end
        self._wrench = np.zeros(6)
        self._ring_start_ns = -(10**18)
        self._cache: dict[tuple, tuple] = {}
        self.clock = self._clock

    def _clock(self) -> int:
        return self._t_ns

    # ------------------------------------------------------------ commands
    def start_move(self, q: Sequence[float], speed_rad_s: float) -> None:
        if speed_rad_s <= 0:
            raise ValueError("speed_rad_s must be positive")
        start = self._q_at(self._t_ns)
        end = np.asarray(q, dtype=float)
        duration_s = float(np.max(np.abs(end - start))) / speed_rad_s
        self._move = (start, end, self._t_ns, self._t_ns + int(duration_s * 1e9))
        if duration_s > 0:
            self._ring_start_ns = self._move[3]

    def move_done(self) -> bool:
        return self._t_ns >= self._move[3]

    def world(self) -> "VirtualCellIO":
        return self

    def hang(self, wrench: Sequence[float] | None) -> None:
        self._wrench = np.zeros(6) if wrench is None else np.asarray(wrench, dtype=float)
        self._ring_start_ns = self._t_ns

    # ------------------------------------------------------------ motion
    def _q_at(self, t_ns: int) -> np.ndarray:
        start, end, t0, t1 = self._move
        if t_ns >= t1 or t1 == t0:
            return end
        if t_ns <= t0:
            return start
        return start + (end - start) * ((t_ns - t0) / (t1 - t0))

    def _dq_at(self, t_ns: int) -> np.ndarray:
        start, end, t0, t1 = self._move
        if t0 <= t_ns < t1 and t1 > t0:
            return (end - start) / ((t1 - t0) * 1e-9)
        return np.zeros(6)

    def _ring(self, t_ns: int) -> float:
        dt = (t_ns - self._ring_start_ns) * 1e-9
        if dt < 0 or dt > 20 * self.timing.ring_tau_s:
            return 0.0
        return math.exp(-dt / self.timing.ring_tau_s) * math.sin(2 * math.pi * self.timing.ring_hz * dt)

    def _physics(self, q: np.ndarray, dq: np.ndarray, markers: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(currents (6,), marker positions (len(markers), 3)), noise-free."""
        key = (q.tobytes(), dq.tobytes(), self._wrench.tobytes())
        hit = self._cache.get(key)
        if hit is None:
            if len(self._cache) > 64:
                self._cache.clear()
            eq = self.cell.equilibrium(q, self._wrench)
            currents = self.cell.motion_currents(q, dq, self._wrench) if np.any(dq) else self.cell.currents(eq)
            hit = self._cache[key] = (eq, currents, {})
        eq, currents, positions = hit
        if markers not in positions:
            positions[markers] = (self.cell.to_tracker(self.cell.marker_positions(eq, markers)) if markers
                                  else np.zeros((0, 3)))
        return currents, positions[markers]

    def _state(self, t_ns: int, markers: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Physics at ``t_ns``, linearly interpolated between points of the physics grid."""
        period = int(1e9 / self.timing.physics_rate_hz)
        start, end, t0, t1 = self._move
        if not (t0 <= t_ns < t1):
            return self._physics(self._q_at(t_ns), self._dq_at(t_ns), markers)
        ta = t0 + (t_ns - t0) // period * period
        tb = min(ta + period, t1 - 1)
        dq = self._dq_at(t_ns)
        ca, pa = self._physics(self._q_at(ta), dq, markers)
        cb, pb = self._physics(self._q_at(tb), dq, markers)
        w = 0.0 if tb <= ta else (t_ns - ta) / (tb - ta)
        return ca + (cb - ca) * w, pa + (pb - pa) * w

    # ------------------------------------------------------------ sampling
    def poll(self, markers: Sequence[str], duration_s: float) -> Samples:
        markers = tuple(markers)
        end_ns = self._t_ns + max(int(duration_s * 1e9), 1)
        drive_period = int(1e9 / self.timing.drive_rate_hz)
        tracker_period = int(1e9 / self.timing.tracker_rate_hz)
        truth = self.cell.truth
        drives: list[DriveSample] = []
        tracker: list[TrackerSample] = []
        while self._next_drive_ns <= end_ns:
            t = self._next_drive_ns
            q = self._q_at(t)
            dq = self._dq_at(t) + self.timing.ring_speed_rad_s * self._ring(t)
            currents, _ = self._state(t, ())
            n_joints = len(q)
            noise = self._rng.normal(0.0, truth.current_noise_a, n_joints)
            for j in range(n_joints):
                drives.append(DriveSample(t_ns=t, joint=j + 1, position_rad=float(q[j]), velocity_rad_s=float(dq[j]),
                                          current_a=float(currents[j] + noise[j]), status=0x0237))
            self._next_drive_ns += drive_period
        if markers:
            while self._next_tracker_ns <= end_ns:
                t = self._next_tracker_ns
                _, positions = self._state(t, markers)
                ring = self.timing.ring_amplitude_m * self._ring(t)
                t_s = (t - self.timing.start_ns) * 1e-9
                noisy = (positions + self.cell.tracker_drift * t_s + ring
                         + self._rng.normal(0.0, truth.tracker_noise_m, positions.shape))
                for m, p in zip(markers, noisy):
                    self._tracker_seq += 1
                    tracker.append(TrackerSample(t_ns=t, seq=self._tracker_seq, device_time_s=t_s, marker=m,
                                                 tracker_p_marker=(float(p[0]), float(p[1]), float(p[2]))))
                self._next_tracker_ns += tracker_period
        else:
            self._next_tracker_ns = max(self._next_tracker_ns, end_ns)
        self._t_ns = end_ns
        if self.timing.pace > 0:
            time.sleep(self.timing.pace * duration_s)
        return Samples(tuple(drives), tuple(tracker))
