"""A calibration session: the cell, the recorder and the operator of one run of the
procedures, and what a step can do with them (move, wait until the cell settles, read,
record). The steps are built in :mod:`elastocal.acquisition.steps`, run by
:mod:`elastocal.acquisition.procedures`."""

from __future__ import annotations

import bisect
import math
import time
from typing import Sequence

import numpy as np

from elastocal.acquisition.cellio import CellIO, LoadWorld, Samples
from elastocal.formats.plan import UNLOADED, Plan, PoseSpec
from elastocal.acquisition.recorder import Recorder
from elastocal.acquisition.steps import Step
from elastocal.acquisition.ui import Aborted, OperatorUI
from elastocal.errors import BeamBroken, DeviceTimeout, NotAtRest


#: extra time allowed for a move beyond its nominal duration before giving up [s]
MOVE_MARGIN_S = 30.0


#: longest wait for late drive samples after a reading [s]
DRAIN_TIMEOUT_S = 5.0


#: how many more times a reading is taken when a drive lost every sample of its window (a stream gap)
READING_RETRIES = 3
#: a reading's window is held open until every drive has a sample in it, up to this many times its length
WINDOW_EXTEND = 20


#: how often progress is redrawn during a step [s]
PROGRESS_EVERY_S = 0.5


#: how long a reading waits for the tracker's beam to come back (a person or a cable in the line of
#: sight) before the procedure stops with BeamBroken [s]; the readings are then taken again, settled
BEAM_WAIT_S = 30.0


#: standstill before a prompt: the controller reports no motion and every joint is slower than
#: STANDSTILL_SPEED_RAD_S (its reported speed and its position span over the window) for STANDSTILL_S
STANDSTILL_SPEED_RAD_S = 2e-3
STANDSTILL_S = 0.5
#: the longest wait for standstill before a prompt; then the procedure stops with a NotAtRest fault [s]
STANDSTILL_TIMEOUT_S = 120.0


# ------------------------------------------------------------------ settle
class SettleDetector:
    """Rest detection over a sliding window of raw samples.

    Settled when, over the last ``window_s`` since :meth:`reset`, every joint
    is slower than ``speed_rad_s`` and the spread (standard deviation) of every
    coordinate of every watched marker is below ``spread_m`` (at least 3
    samples of each marker; a standard deviation, unlike max - min, does not
    grow with the tracker's rate). A joint's speed over the window is the larger of its largest
    reported speed and its position span divided by the window (so drives that
    report no velocity are judged by their positions).
    """

    def __init__(self, speed_rad_s: float, spread_m: float, window_s: float) -> None:
        self.speed_rad_s = speed_rad_s
        self.spread_m = spread_m
        self.window_ns = int(window_s * 1e9)
        self.reset(0)

    def reset(self, t_ns: int) -> None:
        self._since_ns = t_ns
        self._drive_t: list[int] = []
        self._drive_v: list[float] = []
        self._drive_j: list[int] = []
        self._drive_p: list[float] = []
        self._tracker: dict[str, tuple[list[int], list[tuple[float, float, float]]]] = {}

    def add(self, samples: Samples) -> None:
        for d in samples.drives:
            self._drive_t.append(d.t_ns)
            self._drive_v.append(abs(d.velocity_rad_s) if d.velocity_rad_s is not None else 0.0)
            self._drive_j.append(d.joint)
            self._drive_p.append(d.position_rad)
        for s in samples.tracker:
            ts, ps = self._tracker.setdefault(s.marker, ([], []))
            ts.append(s.t_ns)
            ps.append(s.tracker_p_marker)

    def _trim(self, now_ns: int) -> None:
        cut = now_ns - self.window_ns
        if self._drive_t and min(self._drive_t) < cut:  # samples of several drives interleave
            keep = [i for i, t in enumerate(self._drive_t) if t >= cut]
            self._drive_t = [self._drive_t[i] for i in keep]
            self._drive_v = [self._drive_v[i] for i in keep]
            self._drive_j = [self._drive_j[i] for i in keep]
            self._drive_p = [self._drive_p[i] for i in keep]
        for m, (ts, ps) in list(self._tracker.items()):
            if ts and min(ts) < cut:
                keep = [i for i, t in enumerate(ts) if t >= cut]
                self._tracker[m] = ([ts[i] for i in keep], [ps[i] for i in keep])

    def status(self, now_ns: int, markers: Sequence[str]) -> tuple[bool, float | None, float | None]:
        """(settled, max joint speed, max marker spread) over the window."""
        self._trim(now_ns)
        speed = None
        if self._drive_v:
            joints = np.asarray(self._drive_j)
            pos = np.asarray(self._drive_p)
            span = max(float(np.ptp(pos[joints == j])) for j in set(self._drive_j))
            speed = max(max(self._drive_v), span / (self.window_ns * 1e-9))
        spread = None
        enough = True
        for m in markers:
            ts, ps = self._tracker.get(m, ([], []))
            if len(ps) < 3:
                enough = False
                continue
            arr = np.asarray(ps)
            s = float(np.max(arr.std(axis=0)))
            spread = s if spread is None else max(spread, s)
        covered = now_ns - self._since_ns >= self.window_ns
        ok = (covered and enough and speed is not None and not math.isnan(speed) and speed < self.speed_rad_s
              and (not markers or (spread is not None and spread < self.spread_m)))
        return ok, speed, spread


# ------------------------------------------------------------------ session
class Session:
    """The running procedure: the cell, the recorder, the operator and the state
    they share (current load, current step)."""

    def __init__(self, io: CellIO, rec: Recorder, ui: OperatorUI, plan: Plan, steps: Sequence[Step],
                 world: LoadWorld | None) -> None:
        self.io = io
        self.rec = rec
        self.ui = ui
        self.plan = plan
        self.robot = io.robot
        self.steps = list(steps)
        self.world = world
        self.load_state: str | None = None      # None: unknown (start, resume)
        self.step_index = -1
        self.step: Step | None = None
        self.detector = SettleDetector(plan.settle.speed_rad_s, plan.settle.spread_m, plan.settle.window_s)
        self.standstill = SettleDetector(STANDSTILL_SPEED_RAD_S, math.inf, STANDSTILL_S)
        self.standstill.reset(io.clock())
        self.n_joints = self.robot.n_joints
        self.started_ns = io.clock()
        self._step_started_ns = self.started_ns
        self._spent_s = 0.0         # time of the steps done in this session
        self._estimated_done_s = 0.0
        self._remaining_s = sum(s.estimate_s for s in steps)
        self._done = 0
        self._last_progress_ns = 0
        self._last_label = "starting"
        self._latest_drive_ns: dict[int, int] = {}
        self._drive_times: dict[int, list[int]] = {}     # sample times per joint since the hold began

    # ------------------------------------------------------------ recording
    def event(self, kind: str, **fields) -> int:
        if self.step is not None:
            fields.setdefault("step", self.step_index)
            fields.setdefault("step_id", self.step.id)
        return self.rec.event(kind, **fields)

    def poll(self, markers: Sequence[str], duration_s: float) -> Samples:
        samples = self.io.poll(markers, duration_s)
        rec = self.rec
        for d in samples.drives:
            rec.drive_sample(d.joint, d.t_ns, d.position_rad, d.velocity_rad_s, d.current_a, d.status)
        for s in samples.tracker:
            rec.tracker_sample(s.t_ns, s.marker, s.tracker_p_marker, s.environment)
        for g in samples.gaps:
            self.event("gap", device=g.device, window_ns=[g.start_ns, g.end_ns], missing=g.missing, text=g.reason)
        self.detector.add(samples)
        self.standstill.add(samples)
        for d in samples.drives:
            if d.t_ns > self._latest_drive_ns.get(d.joint, -1):
                self._latest_drive_ns[d.joint] = d.t_ns
            self._drive_times.setdefault(d.joint, []).append(d.t_ns)
        for g in samples.gaps:  # samples a drive reported lost will not come
            if g.joint is not None and g.end_ns > self._latest_drive_ns.get(g.joint, -1):
                self._latest_drive_ns[g.joint] = g.end_ns
        now = self.io.clock()
        if now - self._last_progress_ns >= PROGRESS_EVERY_S * 1e9:
            self.show_progress(now)
        return samples

    def drain(self, t_ns: int, timeout_s: float = DRAIN_TIMEOUT_S) -> None:
        """Poll until every drive has delivered (or reported lost) its samples up
        to ``t_ns`` (drive samples may arrive a little after they were acquired),
        so a reading's window is complete in the log before its step ends. A
        silent drive raises from its own stream first; this limit is a backstop."""
        t0 = self.io.clock()
        joints = range(1, self.n_joints + 1)
        while len(self._latest_drive_ns) < self.n_joints or min(self._latest_drive_ns.values()) < t_ns:
            if (self.io.clock() - t0) * 1e-9 > timeout_s:
                late = [j for j in joints if self._latest_drive_ns.get(j, -1) < t_ns]
                raise DeviceTimeout(f"drive(s) {', '.join(f'J{j}' for j in late)} sent no sample for "
                                    f"{timeout_s:g} s")
            self.poll([], 0.005)

    # ------------------------------------------------------------ progress
    def show_progress(self, now_ns: int | None = None) -> None:
        now_ns = self.io.clock() if now_ns is None else now_ns
        self._last_progress_ns = now_ns
        elapsed = (now_ns - self.started_ns) * 1e-9
        ratio = self._spent_s / self._estimated_done_s if self._estimated_done_s > 0 else 1.0
        in_step = (now_ns - self._step_started_ns) * 1e-9 if self.step is not None else 0.0
        left = max(0.0, self._remaining_s * ratio - in_step)
        label = self.step.label if self.step is not None else self._last_label
        self.ui.progress(self._done, len(self.steps), label, elapsed, left)

    def begin_step(self, index: int, step: Step) -> None:
        self.step_index, self.step = index, step
        self._last_label = f"{step.label} done"
        self._step_started_ns = self.io.clock()
        self.event("step_start", procedure=step.procedure, steps=len(self.steps))
        self.show_progress()

    def end_step(self) -> None:
        step = self.step
        self.event("step_done", procedure=step.procedure)
        now = self.io.clock()
        self._spent_s += (now - self._step_started_ns) * 1e-9
        self._estimated_done_s += step.estimate_s
        self._remaining_s -= step.estimate_s
        self._done += 1
        self.step = None
        self.show_progress(now)

    @property
    def done(self) -> int:
        """Steps done in this log (run now or copied from the resumed one)."""
        return self._done

    def skip_step(self, step: Step, duration_s: float | None = None) -> None:
        """A step already done in the log being resumed; ``duration_s``, how long it
        took there, corrects the time-left estimate as the steps done here do."""
        self._remaining_s -= step.estimate_s
        self._done += 1
        if duration_s is not None and duration_s > 0:
            self._spent_s += duration_s
            self._estimated_done_s += step.estimate_s

    # ------------------------------------------------------------ operator
    def confirm(self, text: str, load_id: str | None = None) -> None:
        """Ask the operator (``load_id``: the prompt changes that load, whose name answers it too),
        once the robot stands still (:meth:`wait_standstill`). The answer is logged with who gave
        it (``source``) and how long after the prompt was shown (``delay_s``)."""
        self.wait_standstill(text)
        self.event("prompt", text=text)
        source = self.ui.answer_source
        shown = time.monotonic()        # a person's delay is wall-clock time, whatever clock the cell keeps
        try:
            answer = self.ui.confirm(text) if load_id is None else self.ui.confirm_load(text, load_id)
        except Aborted:
            self.event("answer", text=text, answer="abort", automatic=self.ui.automatic, source=source,
                       delay_s=time.monotonic() - shown)
            raise
        self.event("answer", text=text, answer=answer, automatic=self.ui.automatic, source=source,
                   delay_s=time.monotonic() - shown)

    def wait_standstill(self, before: str) -> None:
        """Wait until the controller reports no motion and every joint has been slower than
        :data:`STANDSTILL_SPEED_RAD_S` for :data:`STANDSTILL_S`; say why to the operator when it
        takes longer than one window; :class:`~elastocal.errors.NotAtRest` after
        :data:`STANDSTILL_TIMEOUT_S`."""
        t0 = self.io.clock()
        told = False
        while True:
            busy = self.io.motion_reported()
            now = self.io.clock()
            if busy:
                self.standstill.reset(now)      # the window counts from when the controller is idle
            ok, speed, _ = self.standstill.status(now, ())
            waited = (now - t0) * 1e-9
            if ok and not busy:
                self.event("standstill", settled=True, duration_s=waited, max_speed_rad_s=speed)
                return
            why = busy or (f"a joint moves at {speed:.3g} rad/s (limit {STANDSTILL_SPEED_RAD_S:g})"
                           if speed is not None and speed >= STANDSTILL_SPEED_RAD_S else "checking the drives")
            if waited > STANDSTILL_TIMEOUT_S:
                self.event("standstill", settled=False, duration_s=waited, max_speed_rad_s=speed, text=why)
                raise NotAtRest(f"the robot did not stand still within {STANDSTILL_TIMEOUT_S:g} s ({why}); "
                                f"nothing was asked ({before!r}); make sure the cell is at rest")
            if not told and (busy or waited >= STANDSTILL_S):
                told = True
                self.ui.message(f"waiting for the robot to stand still before the next prompt: {why} "
                                f"(at most {STANDSTILL_TIMEOUT_S:g} s)")
            self.poll([], 0.02)

    def wrench(self, load_id: str) -> tuple[float, ...]:
        spec = self.plan.load(load_id)
        return (0.0,) * 6 if spec is None else spec.wrench(self.robot.gravity)

    def ensure_load(self, load_id: str) -> None:
        """Ask the operator to put the cell in load state ``load_id`` (and hang it in
        a simulated world); nothing when it is already there."""
        if self.load_state == load_id:
            return
        spec = self.plan.load(load_id)
        named = load_id           # the load the prompt is about: its name answers it
        if spec is None:
            text = ("remove every load from the load point" if self.load_state is None
                    else f"remove load {self.load_state} from the load point")
            named = None if self.load_state is None else self.load_state
        else:
            text = spec.instruction()
            if self.load_state not in (None, UNLOADED):
                text = f"remove load {self.load_state}, then {text}"
        self.confirm(text + "; step out of the cell", load_id=named)
        wrench = self.wrench(load_id)
        if self.world is not None:
            self.world.hang(None if load_id == UNLOADED else wrench)
        self.load_state = load_id
        self.detector.reset(self.io.clock())
        self.event("load", load=load_id, wrench=list(wrench), mass_kg=None if spec is None else spec.mass_kg)

    # ------------------------------------------------------------ motion
    def move(self, q: Sequence[float], speed_rad_s: float, markers: Sequence[str] = ()) -> None:
        """Move to ``q`` and wait for the controller to report the move done."""
        self.io.start_move(q, speed_rad_s)
        self.detector.reset(self.io.clock())
        self.standstill.reset(self.io.clock())
        self._wait_move(q, speed_rad_s, markers)

    def _wait_move(self, q: Sequence[float], speed_rad_s: float, markers: Sequence[str]) -> None:
        limit_s = self._move_estimate(speed_rad_s, q) + MOVE_MARGIN_S
        t0 = self.io.clock()
        while not self.io.move_done():
            self.poll(markers, 0.02)
            if (self.io.clock() - t0) * 1e-9 > limit_s:
                raise DeviceTimeout(f"the cell controller did not finish the move to {_fmt_q(q)} "
                                    f"within {limit_s:.0f} s")
        self.detector.reset(self.io.clock())

    def _move_estimate(self, speed_rad_s: float, q: Sequence[float]) -> float:
        # the controller's position is not known here; the longest possible move bounds it
        span = float(np.max(self.robot.upper - self.robot.lower))
        return span / speed_rad_s

    def settle(self, markers: Sequence[str], **where) -> None:
        """Wait until the cell is at rest (``plan.settle``); DeviceTimeout otherwise."""
        spec = self.plan.settle
        # the tracker follows one reflector: watch the first (none when its own software reads it)
        markers = list(markers[:1]) if self.io.reads_tracker else []
        t0 = self.io.clock()
        step_s = min(0.05, spec.window_s / 4)
        while True:
            self.poll(markers, step_s)
            now = self.io.clock()
            ok, speed, spread = self.detector.status(now, markers)
            waited = (now - t0) * 1e-9
            if ok:
                self.event("settle", settled=True, duration_s=waited, max_speed_rad_s=speed, spread_m=spread,
                           **where)
                return
            if waited > spec.timeout_s:
                self.event("settle", settled=False, duration_s=waited, max_speed_rad_s=speed, spread_m=spread,
                           **where)
                raise DeviceTimeout(
                    f"the cell did not settle within {spec.timeout_s:g} s ({_where(where)}): joint speed "
                    f"{_fmt(speed)} rad/s (limit {spec.speed_rad_s:g}), marker spread {_fmt(spread)} m "
                    f"(limit {spec.spread_m:g})")

    def hold(self, pose: PoseSpec, load_id: str, markers: Sequence[str], repeats: int, reading_s: float) -> None:
        """``repeats`` readings of every marker at rest, one marker after the other;
        one ``reading`` event per marker and repeat with its window on the log clock.

        A reading counts only when every drive has a sample in its window: the
        drives deliver their cycles a little late, so the windows are judged
        once the hold's samples are in (and logged), and a reading whose window
        a drive's stream gap swallowed is taken again (:data:`READING_RETRIES`).
        The reading events follow, before the hold ends."""
        wrench = list(self.wrench(load_id))
        self.event("hold_start", pose=pose.id, load=load_id, q=list(pose.q), wrench=wrench)
        self._drive_times = {}
        order = [(r, m) for r in range(1, repeats + 1) for m in markers]
        todo = list(order)
        good: dict[tuple[int, str], tuple[int, int]] = {}
        for _ in range(1 + READING_RETRIES):
            windows = []
            for r, m in todo:  # a laser tracker measures one reflector at a time
                if windows:     # the last window's drive samples in before the next reading starts (begin_reading)
                    self.drain(windows[-1][3])
                windows.append((r, m, *self._reading_window(pose, load_id, m, reading_s)))
            self.drain(windows[-1][3])
            todo = []
            for r, m, t0, t1 in windows:
                if all(self._has_sample(j, t0, t1) for j in self._latest_drive_ns):
                    good[(r, m)] = (t0, t1)
                else:
                    todo.append((r, m))
            if not todo:
                break
        else:
            raise DeviceTimeout(f"the drives lost every sample of {len(todo)} reading window(s) in "
                                f"{1 + READING_RETRIES} tries at pose {pose.id}, load {load_id}")
        for r, m in order:
            t0, t1 = good[(r, m)]
            self.event("reading", pose=pose.id, load=load_id, marker=m, repeat=r, q=list(pose.q),
                       wrench=wrench, window_ns=[t0, t1])
        self.event("hold_end", pose=pose.id, load=load_id)

    def _reading_window(self, pose: PoseSpec, load_id: str, marker: str, reading_s: float) -> tuple[int, int]:
        """One reading of ``marker``: ``(t0, t1)`` of a window with tracker samples of it. A window
        without any (the beam was broken: the gaps are logged) is read again once the beam is back
        and the cell has settled again, for at most :data:`BEAM_WAIT_S`; then :class:`BeamBroken`."""
        first_miss = None
        while True:
            self.io.begin_reading(marker)
            t0 = self.io.clock()
            samples = self.poll([marker], reading_s)
            t1 = self.io.clock()
            if not self.io.reads_tracker or any(s.marker == marker and t0 <= s.t_ns <= t1 for s in samples.tracker):
                if first_miss is None:
                    return t0, self._complete_window(marker, t0, t1, reading_s)
                # the beam is back: whoever broke it may have touched the cell; settle, then read again
                self.event("beam_back", marker=marker, duration_s=(t1 - first_miss) * 1e-9, pose=pose.id,
                           load=load_id)
                self.settle([marker], pose=pose.id, load=load_id)
                first_miss = None
                continue
            if first_miss is None:
                first_miss = t0
                self.ui.message(f"the tracker does not see marker {marker} (beam broken?): waiting up to "
                                f"{BEAM_WAIT_S:g} s for it")
            if (t1 - first_miss) * 1e-9 > BEAM_WAIT_S:
                raise BeamBroken(f"the tracker gave no reading of marker {marker} for {BEAM_WAIT_S:g} s at pose "
                                 f"{pose.id}, load {load_id} (beam broken or no target); clear the line of "
                                 "sight, then resume")

    def _complete_window(self, marker: str, t0: int, t1: int, reading_s: float) -> int:
        """The end of a reading's window, held open until every drive has a sample in it: a busy host
        can delay a drive's cycles past a short window, and a window is then longer rather than
        taken again (a new aim would be a new reading, with its own simulated noise, so the same
        seed would not give the same numbers). At most :data:`WINDOW_EXTEND` windows long; a drive
        still without a sample then is left to :meth:`hold`'s retries."""
        if not self._latest_drive_ns:          # a cell without drives in this session
            return t1
        self.drain(t1)
        limit = t0 + int(WINDOW_EXTEND * max(reading_s, 0.01) * 1e9)
        while not all(self._has_sample(j, t0, t1) for j in self._latest_drive_ns) and t1 < limit:
            self.poll([marker], max(reading_s, 0.01) / 4)
            t1 = self.io.clock()
            self.drain(t1)
        return t1

    def _has_sample(self, joint: int, t0: int, t1: int) -> bool:
        times = self._drive_times.get(joint, [])
        i = bisect.bisect_left(times, t0)
        return i < len(times) and times[i] <= t1

    def run(self, run_id: str, direction: str, start: Sequence[float], target: Sequence[float],
            speed_rad_s: float, load_id: str, marker: str | None, joint: int | None = None) -> None:
        """One continuously recorded pass from ``start`` (where the robot stands)
        to ``target`` at ``speed_rad_s``."""
        markers = [marker] if marker else []
        self.event("run_start", run=run_id, direction=direction, load=load_id, wrench=list(self.wrench(load_id)),
                   speed_rad_s=speed_rad_s, marker=marker, joint=joint, q=list(target))
        self.io.start_run(start, target, speed_rad_s)
        self.standstill.reset(self.io.clock())
        self._wait_move(target, speed_rad_s, markers)
        self.event("run_end", run=run_id, direction=direction)


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def _fmt_q(q: Sequence[float]) -> str:
    return "[" + ", ".join(f"{v:.4f}" for v in q) + "]"


def _where(where: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in where.items()) or "here"
