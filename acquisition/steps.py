"""The steps of the calibration procedures, built from the plan (static, friction, sweep,
check; see :mod:`elastocal.acquisition.procedures`). A step is the unit of resumption;
its action runs on a :class:`~elastocal.acquisition.session.Session`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from elastocal.formats.plan import UNLOADED, FrictionSpec, Plan, PoseSpec
from elastocal.errors import InputError

if TYPE_CHECKING:  # the session runs the steps; the steps only name it
    from elastocal.acquisition.session import Session


#: time a person is assumed to need for a load change, for the time-left estimate [s]
PERSON_S = 60.0


@dataclass(frozen=True)
class Step:
    """One resumable unit of a procedure."""

    id: str
    procedure: str
    label: str
    estimate_s: float
    needs_person: bool
    action: Callable[["Session"], None]
    #: what an unattended run of this step leaves out (the part that needs a person), "" for nothing
    leaves_out: str = ""


# ------------------------------------------------------------------ steps
def _move_s(a: Sequence[float] | None, b: Sequence[float], speed: float) -> float:
    if a is None:
        return 5.0
    return float(np.max(np.abs(np.asarray(b) - np.asarray(a)))) / speed


def _sweep_steps(plan: Plan, last_q: list, settle_s: float, person_s: float) -> list[Step]:
    """The sweep's steps, of joint 2 or the plan's [sweep] joint (``last_q[0]``: where the robot
    stands before them, updated)."""
    steps: list[Step] = []
    w = plan.sweep
    q_from, q_to = (list(q) for q in w.ends())
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
            s.run(f"sweep-{r}+", "+", q_from, q_to, w.speed_rad_s, w.load, w.marker, joint=w.joint)
            s.settle(markers, run=f"sweep-{r}")
            s.run(f"sweep-{r}-", "-", q_to, q_from, w.speed_rad_s, w.load, w.marker, joint=w.joint)

        steps.append(Step(id=f"sweep/{r}", procedure="sweep", label=f"joint-{w.joint} sweep {r}/{w.repeats}",
                          estimate_s=est, needs_person=w.load != UNLOADED, action=action))
    return steps


def _unloaded_step(plan: Plan, proc: str, pose: PoseSpec, loads: Sequence[str], last_q: list,
                   settle_s: float) -> Step:
    """A check pose read unloaded only, what the robot can do with nobody at the cell
    (``last_q[0]``: where the robot stands before it, updated)."""
    st = plan.static
    markers = st.markers
    est = _move_s(last_q[0], pose.q, st.speed_rad_s) + settle_s + st.repeats * st.reading_s
    last_q[0] = pose.q

    def action(s: Session) -> None:
        s.move(pose.q, st.speed_rad_s, markers[:1])
        s.event("pose", pose=pose.id, q=list(pose.q))
        s.settle(markers, pose=pose.id, load=UNLOADED)
        s.hold(pose, UNLOADED, markers, st.repeats, st.reading_s)

    return Step(id=f"{proc}/{pose.id}/unloaded", procedure=proc, label=f"{proc} pose {pose.id} unloaded",
                estimate_s=est, needs_person=False, action=action,
                leaves_out=f"{proc} pose {pose.id} under load {', '.join(loads)}")


def build_steps(plan: Plan, procedures: Sequence[str], *, person_s: float = PERSON_S,
                unattended: bool = False) -> list[Step]:
    """The steps of ``procedures`` (names of plan sections), in order, with
    their time estimates (robot time plus ``person_s`` per load change).
    ``unattended``: nobody at the cell, so a check pose reads its markers unloaded
    only (what the robot can do alone); the loads it leaves out are the step's ``leaves_out``."""
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
            steps += _sweep_steps(plan, last_q, settle_s, person_s)
        elif proc == "check":
            c = plan.check
            for pid in c.poses:
                steps.append(_unloaded_step(plan, "check", plan.pose(pid), (c.load,), last_q, settle_s)
                             if unattended else static_step("check", plan.pose(pid), (c.load,)))
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
