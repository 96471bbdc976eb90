"""A :class:`CellIO` over elastocal.drivers: drive streams, the tracker, the cell controller.

* Drives stream at their configured rate from :meth:`DriverCellIO.start`; each
  :meth:`DriverCellIO.poll` drains the streams (gaps the drivers report are
  passed on and recorded).
* The tracker measures one reflector at a time: ``poll`` selects the marker
  and takes measurements at the tracker's configured rate.
* The cell controller's requests block until the robot is in position, so
  moves and runs run in a worker thread while ``poll`` keeps sampling;
  :meth:`move_done` re-raises the worker's device error, if any.
* Joint moves use the controller's own move speed (its handshake has no speed
  for joint targets); runs are taught paths (``[[controller.path]]`` in
  cell.toml), found by their end points and run at the plan's speed.
"""

from __future__ import annotations

import threading
import time
from typing import Sequence

import numpy as np

from elastocal.acquisition.cellio import CellIO, LoadWorld, SampleGap, Samples
from elastocal.drivers.samples import DriveSample, TrackerSample
from elastocal.errors import BeamBroken, DeviceTimeout, InputError

#: two joint vectors closer than this are the same pose [rad]
SAME_Q_RAD = 1e-6


class SimWorldLoads:
    """:class:`LoadWorld` over a simulated world with ``set_load(wrench)`` and ``remove_load()``."""

    def __init__(self, world) -> None:
        self._world = world

    @classmethod
    def of(cls, world) -> LoadWorld | None:
        """``world`` as a :class:`LoadWorld` (one already, or a simulated world to wrap; None stays None)."""
        if world is None or hasattr(world, "hang"):
            return world
        return cls(world)

    def hang(self, wrench: Sequence[float] | None) -> None:
        if wrench is None:
            self._world.remove_load()
        else:
            self._world.set_load(wrench)


class DriverCellIO(CellIO):
    """The procedure's view of a cell whose devices are already open.

    ``drives`` (one per joint, any order), ``tracker`` (or None), ``controller``
    and the cell config (for rates, taught paths and timeouts). ``world`` is
    the simulated world when the devices are simulated (loads are hung there
    on confirmation); None for a real cell. The IO closes the drive streams it
    started; closing the devices stays with whoever opened them.
    """

    def __init__(self, robot, config, *, drives, tracker, controller, world=None) -> None:
        self.robot = robot
        self.config = config
        self.clock = time.monotonic_ns
        self._drives = sorted(drives, key=lambda d: d.joint)
        if [d.joint for d in self._drives] != list(range(1, robot.n_joints + 1)):
            raise InputError(f"the cell needs one [[drive]] for each of joints 1..{robot.n_joints} of "
                             f"{robot.name!r}", source=config.source, column="drive")
        self._tracker = tracker
        self.reads_tracker = tracker is not None
        self._controller = controller
        if controller is None:
            raise InputError("the guided procedure needs a [controller] to move the robot", source=config.source,
                             column="controller")
        self._world = SimWorldLoads.of(world)
        self._tracker_period_s = 1.0 / config.tracker.rate_hz if config.tracker is not None else 0.01
        self._selected: str | None = None
        self._worker: threading.Thread | None = None
        self._worker_error: BaseException | None = None
        self._streams = []
        self._blocked: list[SampleGap] = []      # measurements the beam could not make, since the last poll

    def start(self) -> None:
        """Start the drive streams (they buffer every sample until polled)."""
        if self._streams:
            return
        try:
            for d in self._drives:
                self._streams.append(d.stream(self.config.drive(d.joint).rate_hz))
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------ motion
    def _launch(self, what: str, fn, *args, **kwargs) -> None:
        if self._worker is not None and self._worker.is_alive():
            raise RuntimeError("a move is already in progress")
        self._worker_error = None

        def work() -> None:
            try:
                fn(*args, **kwargs)
            except BaseException as exc:  # handed to the procedure thread by move_done()
                self._worker_error = exc

        self._worker = threading.Thread(target=work, name=f"elastocal {what}", daemon=True)
        self._worker.start()

    def start_move(self, q: Sequence[float], speed_rad_s: float) -> None:
        self._launch("move", self._controller.move_joints, [float(v) for v in q])

    def start_run(self, start: Sequence[float], end: Sequence[float], speed_rad_s: float) -> None:
        a, b = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
        for path in self._controller_config().paths:
            u, v = np.asarray(path.u), np.asarray(path.v)
            if np.max(np.abs(u - a)) < SAME_Q_RAD and np.max(np.abs(v - b)) < SAME_Q_RAD:
                direction = "UV"
            elif np.max(np.abs(v - a)) < SAME_Q_RAD and np.max(np.abs(u - b)) < SAME_Q_RAD:
                direction = "VU"
            else:
                continue
            self._launch("run", self._controller.run, path.id, direction, speed_rad_s=float(speed_rad_s))
            return
        raise InputError(f"no taught path runs from {_q(a)} to {_q(b)}; add a [[controller.path]] with these "
                         f"u and v", source=self.config.source, column="controller.path")

    def _controller_config(self):
        return self.config.controller

    def move_done(self) -> bool:
        if self._worker is None:
            return True
        if self._worker.is_alive():
            return False
        self._worker = None
        if self._worker_error is not None:
            error, self._worker_error = self._worker_error, None
            raise error
        return True

    def motion_reported(self) -> str | None:
        if self._worker is not None and self._worker.is_alive():
            return "a move is running"
        if self._controller.status().busy:
            return "the cell controller reports a motion (busy)"
        return None

    def world(self) -> LoadWorld | None:
        return self._world

    # ------------------------------------------------------------ sampling
    def begin_reading(self, marker: str) -> None:
        """Aim the tracker at ``marker`` even when it already is: every reading starts with its own
        aim (the session has every drive sample of the last window in by then), so a simulated cell
        draws each reading's noise once for the whole reading (sims/world.py) and no sample of one
        reading falls into the next; a real tracker just stays on the marker."""
        if self._tracker is None:
            return
        self._tracker.select(marker)
        self._selected = marker

    def _measure(self, markers: Sequence[str], duration_s: float) -> list[TrackerSample]:
        out: list[TrackerSample] = []
        if self._tracker is None:       # the tracker software measures (reads_tracker is False)
            time.sleep(duration_s)
            return out
        end = time.monotonic() + duration_s
        k = 0
        while True:
            m = markers[k % len(markers)]
            k += 1
            if self._selected != m:
                self._tracker.select(m)
                self._selected = m
            try:
                s = self._tracker.measure()
            except BeamBroken as exc:     # a gap: the procedure waits for the beam (Session.hold)
                now = time.monotonic_ns()
                self._blocked.append(SampleGap("tracker", now, now, 1, str(exc)))
                s = None
            if s is not None:
                if s.marker != m:
                    raise DeviceTimeout(f"tracker: measured marker {s.marker!r} while {m!r} was selected")
                out.append(s)
            left = end - time.monotonic()
            if left <= 0:
                return out
            time.sleep(min(self._tracker_period_s, left))

    def poll(self, markers: Sequence[str], duration_s: float) -> Samples:
        if not self._streams:
            raise RuntimeError("DriverCellIO.poll before start()")
        if markers:
            tracker = self._measure(list(markers), duration_s)
        else:
            tracker = []
            time.sleep(duration_s)
        drives: list[DriveSample] = []
        gaps: list[SampleGap] = _merge_blocked(self._blocked)
        self._blocked = []
        for d, stream in zip(self._drives, self._streams):
            batch = stream.read(timeout_s=self.config.drive(d.joint).timeout_s)
            drives.extend(batch.samples)
            for g in batch.gaps:
                gaps.append(SampleGap(g.device, g.start_ns, g.end_ns, g.missing, g.reason, d.joint))
        return Samples(tuple(drives), tuple(tracker), tuple(gaps))

    def close(self) -> None:
        streams, self._streams = self._streams, []
        first: BaseException | None = None
        for s in streams:
            try:
                s.close()
            except BaseException as exc:  # noqa: BLE001 - re-raised below
                first = first or exc
        if self._worker is not None:
            self._worker.join(timeout=self._controller_config().move_timeout_s)
        if first is not None:
            raise first


def _merge_blocked(blocked: list[SampleGap]) -> list[SampleGap]:
    """Consecutive blocked measurements of one reason as one gap."""
    out: list[SampleGap] = []
    for g in blocked:
        if out and out[-1].reason == g.reason:
            last = out[-1]
            out[-1] = SampleGap(last.device, last.start_ns, g.end_ns, last.missing + 1, last.reason)
        else:
            out.append(g)
    return out


def _q(q: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.4f}" for v in q) + "]"
