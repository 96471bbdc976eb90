"""The simulated world every simulated device of a cell reads from.

:class:`SimWorld` holds what the physical cell would: the commanded joint
coordinates ``q`` (moving toward a requested pose at a finite speed, on a
straight joint-space line), the external wrench on the load point (the load the
operator hangs), and time (``time.monotonic_ns``, or a :class:`SimClock` in lockstep; t = 0 at
creation). Its
physics is :class:`elastocal.sims.cell.SimCell`.

Its noise is a function of the seed and of what happened, not of the wall
clock: the world counts *readings* (a new one begins when the robot starts a
motion, when a load changes and when a tracker takes aim at a marker,
:meth:`select_marker`), and at rest every device reads the same noise for the
whole reading, drawn from ``numpy.random.default_rng((seed, device, reading))``
(the reading as (rest, marker, k): the k-th aim at the marker since the last
move or load change) (the drives' currents one device, the tracker one per
marker). So the average of a reading does not depend on how many samples the
wall clock let into it, and two runs of one procedure with one seed read the
same numbers. During a motion and before a rest's first aim (settling; a cell
whose tracker its own software reads) no reading is under way: the noise is
drawn per sample, seeded by the sample's time as well.

The whole API:

* commands (the simulated cell controller calls them):
  :meth:`move_to` ``(q, speed_rad_s)`` and :meth:`run` ``(u, v, speed_rad_s)``
  (approach ``u`` at the move speed, then a slow constant-speed run to ``v``);
  both return the motion's duration and refuse while the robot moves;
* the operator: :meth:`set_load` ``(wrench)`` and :meth:`remove_load`
  (only at rest);
* readings (the simulated devices call them): :meth:`sample` (q, dq and noisy
  motor currents at a time; friction during motion from
  ``SimCell.motion_currents``, static friction on load changes from
  ``SimCell.equilibrium(reference=...)``) and :meth:`read_tracker` (a marker
  through ``SimCell.read_tracker``, drift and noise included);
* waiting: :meth:`is_moving`, :meth:`wait_idle`, :meth:`q_now`.

A motion is planned before it starts: the equilibria and friction currents
along the path are computed on a grid (a few hundred Pinocchio solves) and
interpolated in time, so devices can be read at 1 kHz.
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.sims.cell import CellTruth, Equilibrium, SimCell

#: grid spacing of a planned motion along its largest joint move [rad]
PLAN_STEP_RAD = 0.004
PLAN_MAX_POINTS = 301

#: the devices whose noise the world draws (the second entry of each generator's seed)
NOISE_DRIVES = 1
NOISE_TRACKER = 2


@dataclass(frozen=True)
class WorldSample:
    """The robot as the drives see it at ``t_ns`` (do not modify the arrays: samples may share them)."""

    t_ns: int
    q: np.ndarray            # commanded (motor-side) joint coordinates [rad]
    dq: np.ndarray           # joint velocities [rad/s]
    currents_a: np.ndarray   # motor currents with noise [A] (xi i = load torque carried)
    moving: bool


@dataclass(frozen=True)
class _Segment:
    t0_ns: int
    duration_s: float
    q0: np.ndarray
    q1: np.ndarray
    s_grid: np.ndarray                 # path parameter of the grid points, 0..1
    theta: np.ndarray                  # (n, 6) deflected joint angles at the grid
    link_angles: np.ndarray            # (n, 4)
    gear_torque: np.ndarray            # (n, 6) static gear torque
    currents: np.ndarray               # (n, 6) noise-free currents during the motion (friction on)
    wrench: np.ndarray

    @property
    def dq(self) -> np.ndarray:
        if self.duration_s <= 0:
            return np.zeros(len(self.q0))
        return (self.q1 - self.q0) / self.duration_s

    def s_at(self, t_ns: int) -> float:
        if self.duration_s <= 0:
            return 1.0
        return min(max((t_ns - self.t0_ns) / 1e9 / self.duration_s, 0.0), 1.0)

    def end_ns(self) -> int:
        return self.t0_ns + int(round(self.duration_s * 1e9))


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a




def _interp_rows(grid: np.ndarray, values: np.ndarray, s: float) -> np.ndarray:
    i = int(np.searchsorted(grid, s, side="right")) - 1
    i = min(max(i, 0), len(grid) - 2)
    w = (s - grid[i]) / (grid[i + 1] - grid[i])
    return values[i] * (1.0 - w) + values[i + 1] * w


class SimClock:
    """Simulated time in lockstep [ns]: it stands still until whoever drives the simulation (the
    procedure, acquisition/lockstep.py) advances it, so what happens at an instant does not hang on
    how busy this computer is. ``now_ns`` is the clock a :class:`SimWorld` takes."""

    #: where simulated time starts (any constant does; not 0, so no time reads as "unset")
    ORIGIN_NS = 1_000_000_000

    def __init__(self, start_ns: int = ORIGIN_NS) -> None:
        self._now_ns = int(start_ns)

    def now_ns(self) -> int:
        return self._now_ns

    def advance_to(self, t_ns: int) -> None:
        if t_ns < self._now_ns:
            raise ValueError(f"simulated time runs forward only: {t_ns} < {self._now_ns}")
        self._now_ns = int(t_ns)


class SimWorld:
    """Shared, thread-safe state of the simulated cell (see the module docstring)."""

    def __init__(self, cell: SimCell, *, start_q: Sequence[float], markers: Sequence[str] | None = None,
                 seed: int = 0, move_speed_rad_s: float = 0.5, run_speed_rad_s: float = 0.05,
                 clock_ns=time.monotonic_ns) -> None:
        self.cell = cell
        self.robot = cell.robot
        self.markers = tuple(markers) if markers is not None else tuple(cell.robot.marker_names)
        for m in self.markers:
            self.robot.frame_id(m)
        self.move_speed_rad_s = float(move_speed_rad_s)
        self.run_speed_rad_s = float(run_speed_rad_s)
        self._clock_ns = clock_ns
        self._t0_ns = clock_ns()
        self._seed = int(seed) & (2 ** 64 - 1)      # SeedSequence takes non-negative integers
        #: start time of each reading (module docstring), ascending, and its key: (rest, marker, k), the rest
        #: counting moves and load changes, k the marker's k-th aim in that rest (marker 1.., 0: no aim yet). Local
        #: keys, not one running count: a reading the procedure takes again (a drive lost samples on a busy
        #: host) changes its own draw, not every draw after it
        self._reading_starts = [self._t0_ns]
        self._reading_keys: list[tuple[int, int, int]] = [(0, 0, 0)]
        self._aims: dict[int, int] = {}
        self._rest_noise: dict[tuple, np.ndarray] = {}
        self._lock = threading.RLock()
        self._idle = threading.Condition(self._lock)
        self._planning = False
        q = self._check_q(start_q, "start_q")
        self._wrench = np.zeros(6)
        self._zero_speed = _read_only(np.zeros(self.robot.n_joints))
        self._segments: tuple[_Segment, ...] = ()
        self._reference = cell.equilibrium(q, self._wrench)
        self._set_rest(q, self._reference)

    @classmethod
    def from_config(cls, robot, sim, markers: Sequence[str] | None = None, *,
                    clock_ns=time.monotonic_ns) -> "SimWorld":
        """A world for :class:`elastocal.sims.config.SimConfig` ``sim``; ``clock_ns`` its time
        (this computer's monotonic clock, or a :class:`SimClock`'s ``now_ns`` in lockstep)."""
        for key in ("start_q", "coulomb_nm", "viscous_nm_s_rad", "load_friction", "gear_ratios"):
            if len(getattr(sim, key)) != robot.n_joints:
                raise InputError(f"{len(getattr(sim, key))} values; the robot {robot.name!r} has {robot.n_joints} "
                                 "joints, one each", column=f"sim.{key}")
        truth = CellTruth.for_robot(robot, coulomb=np.array(sim.coulomb_nm), viscous=np.array(sim.viscous_nm_s_rad),
                                    load_friction=np.array(sim.load_friction), tracker_noise_m=sim.tracker_noise_m,
                                    current_noise_a=sim.current_noise_a)
        try:
            truth = truth.with_hidden(sim.hidden)
        except ValueError as exc:
            raise InputError(str(exc), column="sim.hidden") from None
        return cls(SimCell(robot, truth), start_q=sim.start_q, markers=markers, seed=sim.seed,
                   move_speed_rad_s=sim.move_speed_rad_s, run_speed_rad_s=sim.run_speed_rad_s, clock_ns=clock_ns)

    # ------------------------------------------------------------- time
    def now_ns(self) -> int:
        return self._clock_ns()

    def t_s(self, t_ns: int | None = None) -> float:
        """World time [s] since creation."""
        return ((self._clock_ns() if t_ns is None else t_ns) - self._t0_ns) / 1e9

    # --------------------------------------------------------- commands
    def _check_q(self, q: Sequence[float], name: str) -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1)
        n = self.robot.n_joints
        if q.shape != (n,) or not np.all(np.isfinite(q)):
            raise InputError(f"{name}: expected {n} finite joint values, got {q}")
        if np.any(q < self.robot.lower) or np.any(q > self.robot.upper):
            raise InputError(f"{name}: {np.round(q, 4).tolist()} is outside the joint limits")
        return q

    def _plan(self, q0: np.ndarray, q1: np.ndarray, speed: float, wrench: np.ndarray, t0_ns: int) -> _Segment:
        dist = float(np.max(np.abs(q1 - q0)))
        duration = dist / speed
        n = int(min(max(math.ceil(dist / PLAN_STEP_RAD) + 1, 2), PLAN_MAX_POINTS))
        s_grid = np.linspace(0.0, 1.0, n)
        dq = (q1 - q0) / duration if duration > 0 else np.zeros(len(q0))
        thetas, links, gears, currents = [], [], [], []
        for s in s_grid:
            q = q0 + (q1 - q0) * s
            eq = self.cell.equilibrium(q, wrench)
            tau = eq.gear_torque
            thetas.append(eq.theta)
            links.append(eq.link_angles)
            gears.append(tau)
            # the drive supplies the friction in the direction of motion on top of the load
            currents.append((tau + self.cell.friction_torque(dq, tau)) / self.robot.torque_constants)
        return _Segment(t0_ns=t0_ns, duration_s=duration, q0=q0, q1=q1, s_grid=s_grid, theta=np.array(thetas),
                        link_angles=np.array(links), gear_torque=np.array(gears), currents=np.array(currents),
                        wrench=wrench.copy())

    def _start(self, legs: list[tuple[np.ndarray, float]]) -> float:
        with self._lock:
            if self._planning or self._moving_locked(self._clock_ns()):
                raise InputError("the robot is moving; wait until it stops")
            self._planning = True
            q0 = self._rest_q
            wrench = self._wrench.copy()
        try:
            planned = []
            q = q0
            for target, speed in legs:
                if np.max(np.abs(target - q)) > 0:
                    planned.append(self._plan(q, target, speed, wrench, 0))
                    q = target
            end_eq = self.cell.equilibrium(q, wrench)
        except BaseException:
            with self._lock:
                self._planning = False
            raise
        with self._lock:
            t = self._clock_ns()
            self._new_reading_locked(t)
            segments = []
            for seg in planned:
                seg = replace(seg, t0_ns=t)
                segments.append(seg)
                t = seg.end_ns()
            self._segments = tuple(segments)
            self._reference = end_eq
            self._set_rest(q, end_eq)
            self._planning = False
            self._idle.notify_all()
            return sum(s.duration_s for s in segments)

    def move_to(self, q: Sequence[float], speed_rad_s: float | None = None) -> float:
        """Move to ``q`` at ``speed_rad_s`` on the fastest joint; returns the duration [s]."""
        target = self._check_q(q, "target")
        speed = self.move_speed_rad_s if speed_rad_s is None else float(speed_rad_s)
        if not speed > 0:
            raise InputError(f"speed must be > 0, got {speed}")
        return self._start([(target, speed)])

    def run(self, u: Sequence[float], v: Sequence[float], speed_rad_s: float | None = None) -> float:
        """Approach ``u`` (move speed), then run slowly and steadily to ``v``; returns the duration [s]."""
        a = self._check_q(u, "path start")
        b = self._check_q(v, "path end")
        speed = self.run_speed_rad_s if speed_rad_s is None else float(speed_rad_s)
        if not speed > 0:
            raise InputError(f"speed must be > 0, got {speed}")
        return self._start([(a, self.move_speed_rad_s), (b, speed)])

    # --------------------------------------------------------- operator
    def set_load(self, wrench: Sequence[float]) -> None:
        """Hang a load: ``wrench`` (fx, fy, fz, mx, my, mz) on the load point, base axes [N, N·m].

        Static friction (a hidden effect) may absorb part of the change; the
        reference is the equilibrium the robot stopped in."""
        w = np.asarray(wrench, dtype=float).reshape(-1)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise InputError(f"wrench: expected 6 finite values, got {wrench!r}")
        with self._lock:
            if self._planning or self._moving_locked(self._clock_ns()):
                raise InputError("cannot change the load while the robot moves")
            q = self._rest_q
            reference = self._reference
        eq = self.cell.equilibrium(q, w, reference=reference)
        with self._lock:
            self._new_reading_locked(self._clock_ns())
            self._wrench = w
            self._set_rest(self._rest_q, eq)

    def remove_load(self) -> None:
        self.set_load(np.zeros(6))

    def wrench(self) -> np.ndarray:
        with self._lock:
            return self._wrench.copy()

    # ----------------------------------------------------------- noise
    def select_marker(self, marker: str) -> None:
        """A tracker takes aim at ``marker``: a new reading begins (module docstring)."""
        if marker not in self.markers:
            raise InputError(f"unknown marker {marker!r}; the cell has {', '.join(self.markers)}")
        with self._lock:
            self._new_reading_locked(self._clock_ns(), self.markers.index(marker) + 1)

    def _new_reading_locked(self, t_ns: int, marker: int | None = None) -> None:
        """A new reading from ``t_ns``: a tracker's aim at ``marker`` (its index + 1), or a new rest (None)."""
        rest = self._reading_keys[-1][0]
        if marker is None:
            rest, marker, self._aims = rest + 1, 0, {}
        self._aims[marker] = k = self._aims.get(marker, 0) + 1
        self._reading_starts.append(max(t_ns, self._reading_starts[-1]))
        self._reading_keys.append((rest, marker, k))
        self._rest_noise = {}

    def reading_at(self, t_ns: int) -> tuple[int, int, int]:
        """The key of the reading under way at ``t_ns``: (rest, marker, k) (see ``__init__``)."""
        with self._lock:
            return self._reading_keys[max(bisect.bisect_right(self._reading_starts, t_ns) - 1, 0)]

    def _noise(self, device: tuple[int, ...], sigma: float, size: int, t_ns: int, moving: bool) -> np.ndarray:
        """The noise ``device`` reads at ``t_ns``: one draw per reading at rest, one per sample in motion."""
        reading = self.reading_at(t_ns)
        # before the first aim of a rest (settling; a cell whose tracker its own software reads) no reading is
        # under way: a draw per sample, as in motion
        moving = moving or reading[1] == 0
        key = (*device, *reading) if not moving else (*device, *reading, int(t_ns) & (2 ** 64 - 1))
        if not moving:
            with self._lock:
                cached = self._rest_noise.get(key)
            if cached is not None:
                return cached
        noise = np.random.default_rng((self._seed, *key)).normal(0.0, sigma, size=size)
        if not moving:
            noise.flags.writeable = False
            with self._lock:
                if reading == self._reading_keys[-1]:     # only the reading under way is kept
                    self._rest_noise[key] = noise
        return noise

    # ----------------------------------------------------------- state
    def _set_rest(self, q: np.ndarray, eq: Equilibrium) -> None:
        """The pose the robot stops in (call with the lock held, or before other threads run).

        What the devices read at rest is computed here once, not per reading:
        the noise-free currents, and (on the first tracker reading) the
        noise-free marker positions."""
        self._rest_q = q
        self._rest_eq = eq
        self._rest_q_ro = _read_only(q)
        self._rest_currents = self.cell.currents(eq)
        self._rest_markers: dict[str, np.ndarray] | None = None

    def _moving_locked(self, t_ns: int) -> bool:
        return bool(self._segments) and t_ns < self._segments[-1].end_ns()

    def is_moving(self, t_ns: int | None = None) -> bool:
        with self._lock:
            return self._planning or self._moving_locked(self._clock_ns() if t_ns is None else t_ns)

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until the robot stands still (True) or ``timeout_s`` passes (False)."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                if not self._planning and not self._moving_locked(self._clock_ns()):
                    return True
                end = self._segments[-1].end_ns() if self._segments else self._clock_ns()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            wait = max(min(remaining, (end - self._clock_ns()) / 1e9), 0.001)
            with self._idle:
                self._idle.wait(wait)

    def _segment_at(self, t_ns: int) -> _Segment | None:
        for seg in self._segments:
            if t_ns < seg.end_ns():
                return seg if t_ns >= seg.t0_ns else None
        return None

    def q_now(self, t_ns: int | None = None) -> np.ndarray:
        t = self._clock_ns() if t_ns is None else t_ns
        with self._lock:
            seg = self._segment_at(t)
            if seg is None:
                return self._rest_q.copy() if not self._moving_locked(t) else self._segments[0].q0.copy()
            return seg.q0 + (seg.q1 - seg.q0) * seg.s_at(t)

    def sample(self, t_ns: int | None = None) -> WorldSample:
        """q, dq and noisy motor currents at ``t_ns`` (default: now)."""
        t = self._clock_ns() if t_ns is None else t_ns
        with self._lock:
            seg = self._segment_at(t)
            if seg is None:
                if self._moving_locked(t):   # before the first segment of a plan started
                    seg = self._segments[0]
                    t = seg.t0_ns
                else:
                    # SimCell.read_currents(self._rest_eq, rng), with the noise-free currents computed once
                    noise = self._noise((NOISE_DRIVES,), self.cell.truth.current_noise_a, self.robot.n_joints, t,
                                        moving=False)
                    return WorldSample(t, self._rest_q_ro, self._zero_speed, self._rest_currents + noise, False)
            s = seg.s_at(t)
            q = seg.q0 + (seg.q1 - seg.q0) * s
            i = _interp_rows(seg.s_grid, seg.currents, s)
            noise = self._noise((NOISE_DRIVES,), self.cell.truth.current_noise_a, self.robot.n_joints, t, moving=True)
            return WorldSample(t, q, seg.dq, i + noise, True)

    def equilibrium_at(self, t_ns: int | None = None) -> Equilibrium:
        """The (interpolated during motion) equilibrium of the robot at ``t_ns``."""
        t = self._clock_ns() if t_ns is None else t_ns
        with self._lock:
            seg = self._segment_at(t)
            if seg is None:
                if not self._moving_locked(t):
                    return self._rest_eq
                seg = self._segments[0]
                t = seg.t0_ns
            s = seg.s_at(t)
            q = seg.q0 + (seg.q1 - seg.q0) * s
            return Equilibrium(q=q, theta=_interp_rows(seg.s_grid, seg.theta, s),
                               link_angles=_interp_rows(seg.s_grid, seg.link_angles, s),
                               gear_torque=_interp_rows(seg.s_grid, seg.gear_torque, s),
                               wrench=seg.wrench, friction_torque=np.zeros(self.robot.n_joints))

    def read_tracker(self, marker: str, t_ns: int | None = None) -> np.ndarray:
        """A tracker reading of ``marker`` at ``t_ns`` [m], in the tracker's frame (``CellTruth.tracker_rotation``)."""
        if marker not in self.markers:
            raise InputError(f"unknown marker {marker!r}; the cell has {', '.join(self.markers)}")
        t = self._clock_ns() if t_ns is None else t_ns
        device = (NOISE_TRACKER, self.markers.index(marker))
        truth = self.cell.truth
        with self._lock:
            if self._segment_at(t) is None and not self._moving_locked(t):
                # at rest: SimCell.read_tracker with the noise-free positions computed once per pose
                if self._rest_markers is None:
                    p = self.cell.marker_positions(self._rest_eq, self.markers)
                    self._rest_markers = {m: p[i:i + 1] for i, m in enumerate(self.markers)}
                p = self._rest_markers[marker] + truth.drift_velocity * self.t_s(t)
                noise = self._noise(device, truth.tracker_noise_m, 3, t, moving=False)
                return self.cell.to_tracker(p + noise)[0]
        eq = self.equilibrium_at(t)
        rng = np.random.default_rng((self._seed, *device, *self.reading_at(t), int(t) & (2 ** 64 - 1)))
        return self.cell.read_tracker(eq, [marker], self.t_s(t), rng)[0]
