"""The procedure on a simulated cell's own time: one simulated clock for the procedure and the
simulated devices (``elastocal demo``; ``--realtime`` there serves the devices instead).

A simulated cell served through its protocols (``calibrate --sim``, ``demo --realtime``) answers
the real drivers over CAN, TCP and Modbus on this computer's wall clock: how many samples a
reading holds and when it was taken hang on how busy the computer is, so two runs of one seed
differ in their last digits and in whatever is fitted against time (a thermal drift). Here the
procedure and the simulated devices share one :class:`~elastocal.sims.world.SimClock`, in
lockstep as ``stream --sim``'s simulated controller is: the clock advances only when the
procedure waits (:meth:`LockstepCellIO.poll`), and each device is sampled at the instants of its
own grid in that time (each drive at its rate from the start of its stream, the tracker at its
rate on the reflector it aims at) from the simulated world, which computes the physics, the noise
and the hidden effects its own way (sims/world.py). The same seed gives the same samples at the
same times, the same log and the same numbers, and nothing waits for the wall clock. Real
devices stay on this computer's monotonic clock (:class:`~elastocal.acquisition.drivercell.DriverCellIO`).
"""

from __future__ import annotations

import pathlib
from typing import Sequence

from elastocal.acquisition.cellio import CellIO, LoadWorld, Samples
from elastocal.acquisition.drivercell import SimWorldLoads
from elastocal.drivers.samples import DriveSample, TrackerSample
from elastocal.errors import InputError

#: CiA 402 statusword "operation enabled", as a simulated drive reports it at work
OPERATION_ENABLED = 0x0237
#: a tracker's aim opens a reading one tick later: a sample taken at the aim's instant belongs to
#: the reading before it (its noise was drawn then), so no window holds samples of two readings
AIM_TICK_NS = 1_000


class LockstepCellIO(CellIO):
    """:class:`CellIO` over a :class:`~elastocal.sims.world.SimWorld` whose clock is ``clock``
    (the module docstring). ``config`` gives the drives' and the tracker's rates."""

    def __init__(self, robot, config, world, clock) -> None:
        if world.now_ns() != clock.now_ns():
            raise ValueError("the simulated world must run on the lockstep clock (SimWorld(..., clock_ns=clock.now_ns))")
        self.robot = robot
        self._world = world
        self._clock = clock
        self.clock = clock.now_ns
        self._drive_period_ns = [int(round(1e9 / config.drive(j).rate_hz)) for j in range(1, robot.n_joints + 1)]
        rate = config.tracker.rate_hz if config.tracker is not None else 100.0
        self._tracker_period_ns = int(round(1e9 / rate))
        self._next_drive_ns: list[int] | None = None
        self._next_tracker_ns = 0
        self._selected: str | None = None
        self._seq = 0

    def start(self) -> None:
        if self._next_drive_ns is None:
            now = self._clock.now_ns()
            self._next_drive_ns = [now + p for p in self._drive_period_ns]
            self._next_tracker_ns = now + self._tracker_period_ns

    # ------------------------------------------------------------ motion
    def start_move(self, q: Sequence[float], speed_rad_s: float) -> None:
        # the simulated controller moves joints at its own speed, as a real one does (DriverCellIO)
        self._world.move_to([float(v) for v in q])

    def start_run(self, start: Sequence[float], end: Sequence[float], speed_rad_s: float) -> None:
        self._world.run([float(v) for v in start], [float(v) for v in end], speed_rad_s=float(speed_rad_s))

    def move_done(self) -> bool:
        return not self._world.is_moving()

    def motion_reported(self) -> str | None:
        return "the simulated cell controller reports a motion" if self._world.is_moving() else None

    def world(self) -> LoadWorld | None:
        return SimWorldLoads(self._world)

    # ------------------------------------------------------------ sampling
    def begin_reading(self, marker: str) -> None:
        self._aim(marker)
        self._clock.advance_to(self._clock.now_ns() + AIM_TICK_NS)

    def _aim(self, marker: str) -> None:
        self._world.select_marker(marker)
        self._selected = marker

    def poll(self, markers: Sequence[str], duration_s: float) -> Samples:
        if self._next_drive_ns is None:
            raise RuntimeError("LockstepCellIO.poll before start()")
        end_ns = self._clock.now_ns() + max(int(round(duration_s * 1e9)), 1)
        self._clock.advance_to(end_ns)
        drives = self._drive_samples(end_ns)
        tracker: list[TrackerSample] = []
        markers = list(markers)
        k = 0
        while self._next_tracker_ns <= end_ns:
            t = self._next_tracker_ns
            self._next_tracker_ns += self._tracker_period_ns
            if not markers:
                continue
            m = markers[k % len(markers)]       # a laser tracker measures one reflector at a time
            k += 1
            if self._selected != m:
                self._aim(m)
            self._seq += 1
            p = self._world.read_tracker(m, t)
            tracker.append(TrackerSample(t_ns=t, seq=self._seq, device_time_s=self._world.t_s(t), marker=m,
                                         tracker_p_marker=(float(p[0]), float(p[1]), float(p[2]))))
        return Samples(tuple(drives), tuple(tracker))

    def _drive_samples(self, end_ns: int) -> list[DriveSample]:
        """Every drive's samples on its own grid up to ``end_ns``, in time order (one world sample
        per instant, shared by the drives that sample then)."""
        out: list[DriveSample] = []
        nxt = self._next_drive_ns
        while min(nxt) <= end_ns:
            t = min(nxt)
            s = self._world.sample(t)
            for j in range(self.robot.n_joints):
                if nxt[j] == t:
                    out.append(DriveSample(t_ns=t, joint=j + 1, position_rad=float(s.q[j]),
                                           current_a=float(s.currents_a[j]), velocity_rad_s=float(s.dq[j]),
                                           status=OPERATION_ENABLED))
                    nxt[j] += self._drive_period_ns[j]
        return out

    def close(self) -> None:
        self._next_drive_ns = None


def run_lockstep_calibration(cell_config, plan, out_path: str | pathlib.Path, *, world, clock, ui=None,
                             overwrite: bool = False):
    """The guided calibration of the simulated cell ``cell_config`` by ``plan`` on the cell's own
    simulated time (the module docstring): ``world`` the cell's simulated world running on ``clock``
    (a :class:`~elastocal.sims.world.SimClock`; the command that simulates the cell builds both),
    prompts answered automatically; the :class:`~elastocal.acquisition.procedures.Outcome`."""
    from elastocal.acquisition.procedures import log_robot_text, run_procedures

    if not cell_config.sim:
        raise InputError("runs on a simulated cell only (a [sim] section)", source=str(cell_config.source))
    robot = cell_config.load_robot()
    with LockstepCellIO(robot, cell_config, world, clock) as io:
        return run_procedures(io, plan, out_path, ui=ui, cell_text=cell_config.to_toml(),
                              cell_name=cell_config.name, cell_path=str(cell_config.source),
                              robot_text=log_robot_text(robot, cell_config.robot_path()), overwrite=overwrite)
