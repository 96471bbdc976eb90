"""Guided calibration procedures: steps over a :class:`CellIO`, recorded to MCAP.

A procedure is a list of :class:`Step` built from the plan:

* ``static``: per pose, the unloaded reference then each load state; at each,
  wait until the cell settles (joint speeds about zero, tracker spread below a
  threshold over a window), then ``repeats`` readings of every marker;
* ``friction``: the same slow path forward (UV) and backward (VU), at each
  speed and load, recorded continuously;
* ``sweep``: joint 2 swept forward (+) and backward (-) for the compensator;
* ``check``: a few static poses under one load and one UV/VU pair.

Steps that need a person (hanging or removing a load, clearing the cell
before the first move) ask for confirmation first; an abort at any prompt
ends the procedure with a complete log. A step is the unit of resumption:
``resume_from`` copies the completed steps of an interrupted log and runs the
rest. Acquisition computes no physics: nominal load wrenches are the plan's
masses times the robot's gravity vector.
"""

from __future__ import annotations

import bisect
import math
import pathlib
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from elastocal.acquisition import logformat as lf
from elastocal.acquisition.cellio import CellIO, LoadWorld, Samples
from elastocal.acquisition.export import LogReader, read_log
from elastocal.acquisition.plan import UNLOADED, FrictionSpec, Plan, PoseSpec
from elastocal.acquisition.recorder import Recorder
from elastocal.acquisition.ui import Aborted, AutoUI, OperatorUI
from elastocal.errors import DeviceError, DeviceTimeout, InputError
from elastocal.textfiles import read_text_file

#: time a person is assumed to need for a load change, for the time-left estimate [s]
PERSON_S = 60.0
#: extra time allowed for a move beyond its nominal duration before giving up [s]
MOVE_MARGIN_S = 30.0
#: longest wait for late drive samples after a reading [s]
DRAIN_TIMEOUT_S = 5.0
#: how many more times a reading is taken when a drive lost every sample of its window (a stream gap)
READING_RETRIES = 3
#: how often progress is redrawn during a step [s]
PROGRESS_EVERY_S = 0.5


@dataclass(frozen=True)
class Step:
    """One resumable unit of a procedure."""

    id: str
    procedure: str
    label: str
    estimate_s: float
    needs_person: bool
    action: Callable[["Session"], None]


@dataclass(frozen=True)
class Outcome:
    """How a calibration session ended."""

    path: str
    status: str                 # "completed" or "aborted"
    steps_total: int
    steps_done: int             # done in this log, including the ones copied from resume_from
    steps_resumed: int          # copied from resume_from
    duration_s: float
    message: str = ""
    skipped: tuple[str, ...] = ()   # labels of the steps an unattended run left out (they need a person)


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
            ps.append(s.xyz)

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
            rec.tracker_sample(s.t_ns, s.marker, s.xyz, s.environment)
        for g in samples.gaps:
            self.event("gap", device=g.device, window_ns=[g.start_ns, g.end_ns], missing=g.missing, text=g.reason)
        self.detector.add(samples)
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
        while len(self._latest_drive_ns) < 6 or min(self._latest_drive_ns.values()) < t_ns:
            if (self.io.clock() - t0) * 1e-9 > timeout_s:
                late = [j for j in range(1, 7) if self._latest_drive_ns.get(j, -1) < t_ns]
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
        """Ask the operator (``load_id``: the prompt changes that load, whose name answers it too)."""
        self.event("prompt", text=text)
        try:
            answer = self.ui.confirm(text) if load_id is None else self.ui.confirm_load(text, load_id)
        except Aborted:
            self.event("answer", text=text, answer="abort", automatic=self.ui.automatic)
            raise
        self.event("answer", text=text, answer=answer, automatic=self.ui.automatic)

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
        markers = list(markers[:1])  # the tracker follows one reflector: watch the first
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
                t0 = self.io.clock()
                samples = self.poll([m], reading_s)
                t1 = self.io.clock()
                if not any(s.marker == m and t0 <= s.t_ns <= t1 for s in samples.tracker):
                    raise DeviceTimeout(f"the tracker gave no reading of marker {m} in {reading_s:g} s at "
                                        f"pose {pose.id}, load {load_id}")
                windows.append((r, m, t0, t1))
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
        self._wait_move(target, speed_rad_s, markers)
        self.event("run_end", run=run_id, direction=direction)


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def _fmt_q(q: Sequence[float]) -> str:
    return "[" + ", ".join(f"{v:.4f}" for v in q) + "]"


def _where(where: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in where.items()) or "here"


# ------------------------------------------------------------------ steps
def _move_s(a: Sequence[float] | None, b: Sequence[float], speed: float) -> float:
    if a is None:
        return 5.0
    return float(np.max(np.abs(np.asarray(b) - np.asarray(a)))) / speed


def build_steps(plan: Plan, procedures: Sequence[str], *, person_s: float = PERSON_S) -> list[Step]:
    """The steps of ``procedures`` (names of plan sections), in order, with
    their time estimates (robot time plus ``person_s`` per load change)."""
    steps: list[Step] = []
    settle_s = plan.settle.window_s + 0.5
    last_q: list[Sequence[float] | None] = [None]

    def static_step(proc: str, pose: PoseSpec, loads: Sequence[str]) -> Step:
        st = plan.static
        markers = st.markers
        est = (_move_s(last_q[0], pose.q, st.speed_rad_s) + (1 + len(loads)) * (settle_s + st.repeats * st.reading_s)
               + (len(loads) + 1) * person_s)
        last_q[0] = pose.q

        def action(s: Session) -> None:
            s.ensure_load(UNLOADED)
            s.move(pose.q, st.speed_rad_s, markers[:1])
            s.event("pose", pose=pose.id, q=list(pose.q))
            for load_id in (UNLOADED, *loads):
                s.ensure_load(load_id)
                s.settle(markers, pose=pose.id, load=load_id)
                s.hold(pose, load_id, markers, st.repeats, st.reading_s)

        return Step(id=f"{proc}/{pose.id}", procedure=proc, label=f"{proc} pose {pose.id}", estimate_s=est,
                    needs_person=True, action=action)

    def pair_step(proc: str, f: FrictionSpec, speed: float, load_id: str, step_id: str, run_prefix: str) -> Step:
        move_speed = plan.static.speed_rad_s if plan.static else max(f.speeds_rad_s) * 4
        est = (_move_s(last_q[0], f.start, move_speed) + 2 * _move_s(f.start, f.end, speed) + 3 * settle_s
               + (person_s if load_id != UNLOADED else 0.0))
        last_q[0] = f.start
        markers = [f.marker] if f.marker else []

        def action(s: Session) -> None:
            s.ensure_load(load_id)
            s.move(f.start, move_speed, markers)
            s.settle(markers, run=run_prefix)
            s.run(f"{run_prefix}-UV", "UV", f.start, f.end, speed, load_id, f.marker)
            s.settle(markers, run=run_prefix)
            s.run(f"{run_prefix}-VU", "VU", f.end, f.start, speed, load_id, f.marker)

        return Step(id=step_id, procedure=proc, label=f"{proc} {f.id} at {speed:g} rad/s, load {load_id}",
                    estimate_s=est, needs_person=load_id != UNLOADED, action=action)

    for proc in procedures:
        if proc == "static":
            for pose in plan.static.poses:
                steps.append(static_step(proc, pose, pose.loads))
        elif proc == "friction":
            for f in plan.friction:
                k = 0
                for load_id in f.loads:
                    for speed in f.speeds_rad_s:
                        for _ in range(f.repeats):
                            k += 1
                            steps.append(pair_step(proc, f, speed, load_id, f"friction/{f.id}/{k}",
                                                   f"{f.id}-{k}"))
        elif proc == "sweep":
            w = plan.sweep
            q_from = list(w.q)
            q_from[1] = w.q2_from
            q_to = list(w.q)
            q_to[1] = w.q2_to
            move_speed = plan.static.speed_rad_s if plan.static else w.speed_rad_s * 4
            for r in range(1, w.repeats + 1):
                est = (_move_s(last_q[0], q_from, move_speed) + 2 * _move_s(q_from, q_to, w.speed_rad_s)
                       + 2 * settle_s + (person_s if w.load != UNLOADED else 0.0))
                last_q[0] = q_from
                markers = [w.marker] if w.marker else []

                def action(s: Session, r=r, q_from=tuple(q_from), q_to=tuple(q_to), markers=markers,
                           move_speed=move_speed) -> None:
                    s.ensure_load(w.load)
                    s.move(q_from, move_speed, markers)
                    s.settle(markers, run=f"sweep-{r}")
                    s.run(f"sweep-{r}+", "+", q_from, q_to, w.speed_rad_s, w.load, w.marker, joint=2)
                    s.settle(markers, run=f"sweep-{r}")
                    s.run(f"sweep-{r}-", "-", q_to, q_from, w.speed_rad_s, w.load, w.marker, joint=2)

                steps.append(Step(id=f"sweep/{r}", procedure="sweep", label=f"joint-2 sweep {r}/{w.repeats}",
                                  estimate_s=est, needs_person=w.load != UNLOADED, action=action))
        elif proc == "check":
            c = plan.check
            for pid in c.poses:
                steps.append(static_step("check", plan.pose(pid), (c.load,)))
            if c.friction is not None:
                f = next(x for x in plan.friction if x.id == c.friction)
                steps.append(pair_step("check", f, f.speeds_rad_s[0], f.loads[0], f"check/{f.id}",
                                       f"check-{f.id}"))
        else:
            raise InputError(f"unknown procedure {proc!r}", source=plan.source, column="procedures")
    ids = [s.id for s in steps]
    if len(set(ids)) != len(ids):
        raise InputError("the procedures repeat a step; list each procedure once", source=plan.source,
                         column="procedures")
    return steps


# ------------------------------------------------------------------ running
def _copy_completed(old_path: str | pathlib.Path, rec: Recorder, last_done_event: int) -> None:
    """Copy the messages of an interrupted log up to its last ``step_done``."""
    events_seen = -1
    for topic, m in LogReader(old_path).raw_messages():
        if topic in (lf.TOPIC_SESSION, lf.TOPIC_ROBOT, lf.TOPIC_CELL, lf.TOPIC_PLAN):
            continue
        rec.copy(topic, m.log_time, m.publish_time, m.data)
        if topic == lf.TOPIC_EVENT:
            events_seen += 1
            if events_seen == last_done_event:
                break
    rec.flush()


def _procedures(plan: Plan, procedures: Sequence[str] | None) -> tuple[str, ...]:
    procs = tuple(procedures) if procedures else plan.procedures
    for p in procs:
        if p not in plan.procedures and not (p == "check" and plan.check is not None):
            raise InputError(f"procedure {p!r} is not in the plan", source=plan.source, column="procedures")
    return procs


def _check_out(out_path: str | pathlib.Path, overwrite: bool, resume_from) -> None:
    out = pathlib.Path(out_path)
    if out.exists() and not overwrite:
        raise InputError("already exists; choose another --out, or --force to overwrite it", source=str(out))
    if resume_from is not None:
        if not pathlib.Path(resume_from).is_file():
            raise InputError("cannot read: no such log", source=str(resume_from))
        if pathlib.Path(resume_from).resolve() == out.resolve():
            raise InputError("--resume must name the interrupted log, --out a new file", source=str(out))


def run_procedures(io: CellIO, plan: Plan, out_path: str | pathlib.Path, *, ui: OperatorUI | None = None,
                   procedures: Sequence[str] | None = None, resume_from: str | pathlib.Path | None = None,
                   cell_text: str = "", cell_name: str = "cell", cell_path: str | None = None,
                   robot_text: str | None = None, overwrite: bool = False,
                   recorder_options: dict | None = None, unattended: bool = False) -> Outcome:
    """Run the plan's procedures on ``io`` and record everything to ``out_path``.

    Returns the :class:`Outcome` (completed or aborted by the operator); a
    device failure is recorded as a ``fault`` event and raised, with the
    failed :class:`Outcome` (log path, steps done) as its ``outcome``
    attribute. ``resume_from``
    names an interrupted log of the same plan and robot: its completed steps
    are copied into the new log and skipped.

    ``unattended``: no person is at the cell (a scheduled check). The steps that
    need one (hanging or removing a load) are left out and listed in the
    outcome's ``skipped``; the cell is taken as unloaded, as every procedure
    leaves it, and nothing is asked. Refused when no step remains.
    """
    ui = ui if ui is not None else AutoUI(quiet=True)
    robot = io.robot
    plan.validate_for(robot)
    procs = _procedures(plan, procedures)
    steps = build_steps(plan, procs, person_s=0.0 if ui.automatic else PERSON_S)
    skipped: tuple[str, ...] = ()
    if unattended:
        skipped = tuple(s.label for s in steps if s.needs_person)
        steps = [s for s in steps if not s.needs_person]
        if not steps:
            raise InputError(f"no step of {', '.join(procs)} runs without a person at the cell (each hangs a "
                             "load): nothing to do unattended", source=plan.source)
    robot_text = robot_text if robot_text is not None else robot.to_toml()
    out_path = pathlib.Path(out_path)
    done_before: set[str] = set()
    took_s: dict[str, float] = {}      # how long each step of the resumed log took
    last_done_event = -1
    _check_out(out_path, overwrite, resume_from)
    if resume_from is not None:
        old = read_log(resume_from)
        if old.plan is None or old.plan.sha256 != plan.sha256:
            raise InputError("the log was recorded with another plan; resume with the same plan.toml",
                             source=str(resume_from))
        if old.robot is None or old.robot.text != robot_text:
            raise InputError("the log was recorded with another robot description", source=str(resume_from))
        done_before = set(old.completed_steps) & {s.id for s in steps}
        started_at: dict[str, int] = {}
        for i, e in enumerate(old.events):
            if e["kind"] == "step_start":
                started_at[e.get("step_id")] = e["t_ns"]
            if e["kind"] == "step_done":
                last_done_event = i
                if e.get("step_id") in started_at:
                    took_s[e["step_id"]] = (e["t_ns"] - started_at[e["step_id"]]) * 1e-9
    started = time.monotonic()
    world = io.world()
    with Recorder(out_path, overwrite=overwrite, clock=io.clock,
                  resumed_from=None if resume_from is None else str(resume_from),
                  **(recorder_options or {})) as rec:
        rec.document("robot", robot.name, robot_text)
        rec.document("cell", cell_name, cell_text, cell_path)
        rec.document("plan", plan.name, plan.text, plan.source)
        if resume_from is not None and last_done_event >= 0:
            _copy_completed(resume_from, rec, last_done_event)
            rec.event("resume", text=str(resume_from), completed_steps=sorted(done_before))
        io.start()
        session = Session(io, rec, ui, plan, steps, world)
        session.event("procedure_start", procedure=",".join(procs), steps=len(steps))
        remaining = [s for s in steps if s.id not in done_before]
        if unattended:
            session.load_state = UNLOADED
            session.event("unattended", text="no person at the cell: the cell is taken as unloaded; skipped "
                                             + ("; ".join(skipped) or "nothing"))
        try:
            if remaining and not unattended:
                session.confirm(f"the robot will run {len(remaining)} step(s) of {', '.join(procs)}; "
                                f"clear the cell")
            for index, step in enumerate(steps):
                if step.id in done_before:
                    session.skip_step(step, took_s.get(step.id))
                    continue
                session.begin_step(index, step)
                step.action(session)
                session.end_step()
            if session.load_state not in (None, UNLOADED):
                # the last load comes off, confirmed by a person, before the robot moves again
                session.ensure_load(UNLOADED)
        except Aborted as exc:
            session.step = None
            session.event("procedure_end", status="aborted", text=str(exc))
            ui.close()
            return Outcome(str(out_path), "aborted", len(steps), session.done, len(done_before),
                           time.monotonic() - started, str(exc))
        except KeyboardInterrupt:
            session.step = None
            session.event("procedure_end", status="aborted", text="interrupted (Ctrl-C)")
            ui.close()
            return Outcome(str(out_path), "aborted", len(steps), session.done, len(done_before),
                           time.monotonic() - started, "interrupted (Ctrl-C)")
        except DeviceError as exc:
            session.event("fault", error=type(exc).__name__, text=str(exc))
            session.step = None
            session.event("procedure_end", status="failed", text=str(exc))
            ui.close()
            # where the log is and how far it got, for the resume hint (the error stays the device's)
            exc.outcome = Outcome(str(out_path), "failed", len(steps), session.done, len(done_before),
                                  time.monotonic() - started, f"{type(exc).__name__}: {exc}")
            raise
        session.event("procedure_end", status="completed")
        ui.close()
    return Outcome(str(out_path), "completed", len(steps), session.done, len(done_before),
                   time.monotonic() - started, skipped=skipped)


def _robot_text(robot, robot_path) -> str:
    """The robot description the log keeps: the file as written (comments kept),
    or, for a robot whose URDF is a separate file, the description with the
    URDF inline, so that the log stands alone."""
    if robot.urdf is not None and robot.urdf.path:
        return robot.to_toml()
    return read_text_file(robot_path)


def run_calibration(cell_config, plan: Plan, out_path: str | pathlib.Path, *, yes: bool = True,
                    ui: OperatorUI | None = None, world=None, simulate: bool = False,
                    procedures: Sequence[str] | None = None, resume_from: str | pathlib.Path | None = None,
                    overwrite: bool = False, unattended: bool = False) -> Outcome:
    """The guided calibration of the cell ``cell_config`` (a
    :class:`elastocal.drivers.config.CellConfig`) by ``plan``, recorded to ``out_path``.

    The devices are opened from the config (``elastocal.drivers.open_cell``).
    ``simulate=True`` first serves the cell's simulated devices in this process
    (``elastocal.sims.serve.SimulatedCell``, from the config's ``[sim]``) and
    hangs the loads in its world; ``world`` gives that world directly when the
    caller already serves the devices. ``yes`` answers every prompt
    automatically (``ui`` defaults to a silent :class:`AutoUI`; otherwise a
    :class:`TerminalUI`) and is refused for a real cell, where a person must
    confirm each load change.
    """
    import contextlib

    from elastocal.acquisition.drivercell import DriverCellIO
    from elastocal.acquisition.ui import TerminalUI
    from elastocal.drivers import open_cell

    if ui is None:
        ui = AutoUI(quiet=True) if yes else TerminalUI()
    robot_path = cell_config.robot_path()
    robot = cell_config.load_robot()
    plan.validate_for(robot)
    _procedures(plan, procedures)
    _check_out(out_path, overwrite, resume_from)
    with contextlib.ExitStack() as stack:
        config = cell_config
        if simulate:
            from elastocal.sims.serve import SimulatedCell

            sim = stack.enter_context(SimulatedCell(cell_config))
            config, world = sim.config, sim.world
        elif world is None:     # a cell `sim serve` serves: its load rig hangs the loads the operator confirms
            from elastocal.sims.load_rig import served_loads

            rig = served_loads(cell_config)
            if rig is not None:
                world = stack.enter_context(rig)
        if yes and world is None:
            raise InputError("--yes answers the prompts of a simulated cell only; a person confirms every load "
                             "change on a real cell", source="--yes")
        devices = stack.enter_context(open_cell(config))
        io = stack.enter_context(DriverCellIO(robot, config, drives=list(devices.drives.values()),
                                              tracker=devices.tracker, controller=devices.controller,
                                              world=world))
        return run_procedures(io, plan, out_path, ui=ui, procedures=procedures, resume_from=resume_from,
                              cell_text=cell_config.to_toml(), cell_name=cell_config.name,
                              cell_path=str(cell_config.source),
                              robot_text=_robot_text(robot, robot_path), overwrite=overwrite,
                              unattended=unattended)
