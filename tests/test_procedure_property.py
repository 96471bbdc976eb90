"""A property of the procedure's state machine (hypothesis): whatever sequence of device faults,
kills and operator inputs, no prompt is shown while the robot moves, no load changes without a
person's "yes" to it, and the log reads back.

The cell is :class:`~elastocal.acquisition.cellio.VirtualCellIO` (SimCell physics on a virtual
clock) wrapped in :class:`Scripted`, which plays the drawn script: a device error at a poll, a
controller that reports motion for a while, a joint that creeps, or a kill (the log is then what
a SIGKILL leaves: the bytes on disk at that moment). The checks use the wrapper's own record of
what it delivered, not the procedure's."""

from __future__ import annotations

import shutil
from dataclasses import replace

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.logreader import read_log
from elastocal.acquisition.procedures import run_procedures
from elastocal.acquisition.session import STANDSTILL_S, STANDSTILL_SPEED_RAD_S
from elastocal.acquisition.ui import Aborted, AutoUI
from elastocal.errors import DeviceFault, DeviceTimeout, ProtocolError
from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import CellTruth, SimCell

ROBOT = bundled_robot()
CELL = SimCell(ROBOT, CellTruth())
PLAN = parse_plan(plan_toml(poses=[(0.1, 0.3, -0.4, 0.2, 1.0, 0.1), (0.3, 0.4, -0.3, 0.1, 0.9, 0.2)],
                            loads=(LoadSpec("L1", mass_kg=60.0),), markers=("R1",), repeats=1, reading_s=0.04,
                            speed_rad_s=0.8,
                            settle=SettleSpec(speed_rad_s=2e-3, spread_m=20e-6, window_s=0.15, timeout_s=20.0)),
                  source="plan.toml")
ERRORS = {"timeout": DeviceTimeout, "fault": DeviceFault, "garbled": ProtocolError}


class Killed(BaseException):
    """The process dies here (SIGKILL): nothing after it runs, not even the recorder's close."""


class Scripted(VirtualCellIO):
    """VirtualCellIO playing a script of (poll index, what) events."""

    def __init__(self, script, log_path, kill_copy):
        super().__init__(CELL, q0=(0.0, 0.2, -0.4, 0.0, 0.5, 0.0), seed=3,
                         timing=VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0))
        self.script = dict(script)
        self.polls = 0
        self.busy_until = -1            # poll index up to which the controller reports motion
        self.creep_until = -1           # ... up to which joint 3 creeps at 0.01 rad/s
        self.delivered: list[tuple[int, float]] = []     # (t_ns, max |velocity|) per delivered cycle
        self.log_path, self.kill_copy = log_path, kill_copy

    def poll(self, markers, duration_s):
        self.polls += 1
        what = self.script.get(self.polls)
        if what == "kill":
            shutil.copyfile(self.log_path, self.kill_copy)       # what the disk holds at the kill
            raise Killed()
        if what in ERRORS:
            raise ERRORS[what](f"scripted {what} at poll {self.polls}")
        if what == "busy":
            self.busy_until = self.polls + 30
        if what == "creep":
            self.creep_until = self.polls + 30
        s = super().poll(markers, duration_s)
        if self.polls <= self.creep_until:
            s = replace(s, drives=tuple(replace(d, velocity_rad_s=0.01) if d.joint == 3 else d for d in s.drives))
        for d in s.drives:
            if d.joint == 1:
                self.delivered.append((d.t_ns, 0.0))
            self.delivered[-1] = (self.delivered[-1][0], max(self.delivered[-1][1], abs(d.velocity_rad_s or 0.0)))
        return s

    def motion_reported(self):
        if self.polls <= self.busy_until:
            return "the cell controller reports a motion (busy)"
        return super().motion_reported()

    def moving_now(self) -> bool:
        """Did anything report motion within the standstill window before now?"""
        if not self.move_done() or self.polls <= self.busy_until:
            return True
        since = self._t_ns - int(STANDSTILL_S * 1e9)
        recent = [v for t, v in self.delivered if t >= since]
        return not recent or max(recent) >= STANDSTILL_SPEED_RAD_S


class Operator(AutoUI):
    """Answers from the drawn inputs; checks at every prompt that nothing moves."""

    def __init__(self, io, inputs):
        super().__init__(quiet=True)
        self.io, self.inputs = io, list(inputs)
        self.moving_at_prompt = []

    def message(self, text):
        pass

    def confirm(self, text):
        self.moving_at_prompt.append(self.io.moving_now())
        answer = self.inputs.pop(0) if self.inputs else "yes"
        if answer == "abort":
            raise Aborted(f"aborted by the operator at: {text}")
        if answer == "ctrl-c":
            raise KeyboardInterrupt
        return super().confirm(text)


SCRIPT = st.lists(st.tuples(st.integers(1, 400), st.sampled_from(["timeout", "fault", "garbled", "busy", "creep",
                                                                  "kill", "busy", "creep"])),
                  max_size=5, unique_by=lambda x: x[0])
INPUTS = st.lists(st.sampled_from(["yes", "yes", "yes", "abort", "ctrl-c"]), max_size=8)


@pytest.mark.slow
@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(script=SCRIPT, inputs=INPUTS)
def test_no_prompt_in_motion_no_unconfirmed_load_and_a_readable_log(tmp_path_factory, script, inputs):
    tmp = tmp_path_factory.mktemp("prop")
    log, killed_copy = tmp / "log.mcap", tmp / "killed.mcap"
    io = Scripted(script, log, killed_copy)
    ui = Operator(io, inputs)
    killed = False
    try:
        out = run_procedures(io, PLAN, log, ui=ui)
        assert out.status in ("completed", "aborted")
    except Killed:
        killed = True
    except (DeviceTimeout, DeviceFault, ProtocolError) as exc:
        assert exc.outcome.status == "failed"
    assert not any(ui.moving_at_prompt), ui.moving_at_prompt
    contents = read_log(killed_copy if killed else log)        # readable, whatever happened
    assert contents.complete is not killed          # a kill leaves no summary; every other end writes it
    events = contents.events
    if not killed:
        assert events[-1]["kind"] == "procedure_end"
    # every load change follows a person's "yes" to its prompt, with nothing asked in between
    last_answer = None
    for e in events:
        if e["kind"] == "prompt":
            last_answer = None
        elif e["kind"] == "answer":
            last_answer = e
        elif e["kind"] == "load":
            assert last_answer is not None and last_answer["answer"] == "yes", events
            last_answer = None
    # a prompt is asked only after the standstill wait said the robot stood still
    for i, e in enumerate(events):
        if e["kind"] == "prompt":
            before = [x for x in events[:i] if x["kind"] in ("standstill", "prompt", "step_start", "pose")]
            assert before and before[-1]["kind"] == "standstill" and before[-1]["settled"] is True
