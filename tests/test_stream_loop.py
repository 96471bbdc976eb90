"""The stream's loop on a scripted controller and an injected clock: the correction's physics, its
limits, the watchdog, lost and late messages, the log. No sockets and no wall clock: what the
loop recorded is what is checked.
"""

from __future__ import annotations

import json
from dataclasses import replace

import jsonschema
import numpy as np
import pytest

from elastocal.acquisition.recorder import Recorder
from elastocal.compensation.ik import yang_path
from elastocal.compensation.model import CompensationModel
from elastocal.compensation.trajectory import compensate_path
from elastocal.drivers.guidance import ControllerLost, ControllerRefused, ControllerState, GuidanceKind
from elastocal.formats import logformat as lf
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.guided import statics
from elastocal.stream.clock import ControllerTime
from elastocal.stream.correction import Limits, wrench_from_currents
from elastocal.stream.loop import LateCause, NotAtStart, StreamSettings, WatchdogFault, run_stream
from elastocal.stream.plan import build_plan
from elastocal.stream.recording import ARROW_GAIN, StreamLog
from elastocal.stream.sources import CurrentsSource, PathSource
from elastocal.model.kinds import KinematicForm

CYCLE_MS = 4
WRENCH = np.array([0.0, 0.0, 1500.0, 0.0, 0.0, 0.0])


class Clock:
    """An injected monotonic clock: every reading advances it by ``step_ns``."""

    def __init__(self, step_ns: int = 5_000) -> None:
        self.t = 0
        self.step_ns = step_ns

    def __call__(self) -> int:
        self.t += self.step_ns
        return self.t


class ScriptedController:
    """The guidance interface with states from a script: ``(controller_ms, delay_ns, q, currents, skipped)``;
    ``delay_ns`` is how long the message waited before the loop took it up."""

    kind = GuidanceKind.EGM
    name = "scripted controller"
    cycle_s = CYCLE_MS * 1e-3

    def __init__(self, clock: Clock, q_of, n_cycles: int, *, n_joints: int = 6, delays=None, gaps=(), ready=True,
                 currents=None, skipped=None) -> None:
        self.clock = clock
        self.n_joints = n_joints
        self.sent: list[np.ndarray] = []
        self.q_of = q_of
        self.cycles = [k for k in range(n_cycles) if k not in set(gaps)]
        self.delays = delays or {}
        self.ready = ready
        self.currents = currents
        self.skipped = skipped or {}
        self._i = 0

    def receive(self, timeout_s=None) -> ControllerState:
        if self._i >= len(self.cycles):
            raise ControllerLost("scripted controller: the script ended")
        k = self.cycles[self._i]
        self._i += 1
        self.clock.t = max(self.clock.t, k * CYCLE_MS * 1_000_000) + self.delays.get(k, 0)
        q = self.q_of(k)
        cur = None if self.currents is None else self.currents(k, self.sent[-1] if self.sent else q)
        return ControllerState(t_ns=self.clock.t - self.delays.get(k, 0), sequence=k + 1, q=q, currents_a=cur,
                               controller_time_ms=k * CYCLE_MS, ready=self.ready, skipped=self.skipped.get(k, 0))

    def send(self, q) -> None:
        self.sent.append(np.array(q, dtype=float))


class Events:
    def __init__(self) -> None:
        self.records, self.events = [], []

    def cycle(self, record) -> None:
        self.records.append(record)

    def event(self, kind, **fields) -> None:
        self.events.append((kind, fields))


@pytest.fixture(scope="module")
def model(robot):
    truth = CellTruth()
    return CompensationModel(robot=robot, stiffness=truth.stiffness, compensator=truth.compensator)


@pytest.fixture(scope="module")
def plan(model, robot):
    path = yang_path(robot, step_m=0.05)                 # 13 samples
    return build_plan(model, np.linspace(0.0, 0.2, len(path.q)), path.q)


def _run(plan, source, n_cycles, *, settings=StreamSettings(limits=Limits(1.0, 100.0)), **script):
    clock = Clock()
    ctrl = ScriptedController(clock, lambda k: plan.q[0], n_cycles, **script)
    sink = Events()
    try:
        result = run_stream(ctrl, source, plan, sink, settings=replace(settings, end_hold_s=0.0), clock_ns=clock)
    except Exception as exc:                                # noqa: BLE001 - the tests look at it
        return ctrl, sink, exc
    return ctrl, sink, result


def test_the_correction_puts_the_loaded_robot_on_the_unloaded_plan(plan, model, robot):
    """The simulator's own statics (not the model's code) at the sent joints under the wrench
    put the load point where the unloaded plan does; and the correction is the offline exact one."""
    ctrl, sink, result = _run(plan, PathSource(plan, WRENCH), 51)
    assert result.cycles == 51 and result.late == 0
    cell = SimCell(robot, CellTruth())
    on_sample = {round(float(t) * 1e3) for t in plan.t}
    for r in sink.records[::3]:
        loaded = statics(cell, r.q_sent, WRENCH).load_point
        unloaded = statics(cell, r.q_planned, None).load_point
        # exact at the path's samples (the fixed points' 1e-13 rad times 2 m, and rounding); between them
        # the correction is interpolated linearly: an error of second order in the 50 mm sample spacing
        tol = 1e-8 if round(r.t_path_s * 1e3) in on_sample else 1e-6
        assert np.linalg.norm(loaded - unloaded) < tol
    offline = compensate_path(model, plan.q, WRENCH, form=KinematicForm.EXACT, reference="unloaded")
    at_samples = {round(r.t_path_s, 9): r for r in sink.records}
    for i, t in enumerate(plan.t):
        r = at_samples.get(round(float(t), 9))
        if r is not None:
            assert np.max(np.abs(r.q_sent - offline.q_command[i])) < 1e-10


def test_corrections_keep_their_size_and_rate_limits(plan):
    limits = Limits(max_rad=np.radians(0.01), max_rate_rad_s=np.radians(0.2))
    ctrl, sink, result = _run(plan, PathSource(plan, WRENCH), 60, settings=StreamSettings(limits=limits))
    corr = np.array([r.correction for r in sink.records])
    assert np.max(np.abs(corr)) <= limits.max_rad + 1e-15
    steps = np.abs(np.diff(np.vstack([np.zeros(6), corr]), axis=0))
    assert np.max(steps) <= limits.max_rate_rad_s * CYCLE_MS * 1e-3 + 1e-15
    assert sink.records[0].limited and result.limited > 0
    wanted = np.array([r.wanted for r in sink.records])
    assert np.max(np.abs(wanted)) > limits.max_rad            # the model asked for more than was sent


class Flaky:
    """A path source that has no fresh wrench on the cycles ``stale``."""

    def __init__(self, plan, stale) -> None:
        self.inner = PathSource(plan, WRENCH)
        self.stale = set(stale)
        self.calls = 0

    def read(self, state, i, w, now):
        k = self.calls
        self.calls += 1
        return None if k in self.stale else self.inner.read(state, i, w, now)


def test_late_cycles_hold_the_last_correction_and_three_in_a_row_stop_the_stream(plan):
    ctrl, sink, exc = _run(plan, Flaky(plan, {5, 6, 10, 11, 12}), 40)
    assert isinstance(exc, WatchdogFault) and exc.cause is LateCause.FORCE
    recs = sink.records
    assert [r.cycle for r in recs if r.late] == [5, 6, 10, 11, 12] and recs[-1].cycle == 12
    for k in (5, 6, 10, 11, 12):                             # held: the correction of the cycle before
        assert np.array_equal(recs[k].correction, recs[k - 1].correction)
        assert np.allclose(recs[k].q_sent, recs[k].q_planned + recs[k - 1].correction)


def test_a_message_taken_up_too_late_is_answered_with_the_held_correction(plan):
    ctrl, sink, result = _run(plan, PathSource(plan, WRENCH), 60, delays={7: 4_000_000})
    late = [r for r in sink.records if r.late]
    assert [r.cycle for r in late] == [7] and late[0].late is LateCause.SCHEDULE
    assert result.late == 1


def test_lost_and_skipped_controller_messages_are_counted(plan):
    ctrl, sink, result = _run(plan, PathSource(plan, WRENCH), 60, gaps=(10, 11), skipped={20: 2})
    assert result.lost == 2
    gaps = [f for kind, f in sink.events if kind == "gap"]
    assert [g["missing"] for g in gaps] == [2, 2]
    assert result.late == 2                                    # the two skipped ones were never answered
    # the path time follows the controller's clock across the gap
    assert [r.t_path_s for r in sink.records if r.lost_before] == [pytest.approx(0.048)]


def test_the_stream_refuses_a_robot_away_from_the_start_or_not_ready(plan):
    clock = Clock()
    away = ScriptedController(clock, lambda k: plan.q[0] + np.array([0, 0.01, 0, 0, 0, 0]), 5)
    with pytest.raises(NotAtStart, match="q2"):
        run_stream(away, PathSource(plan, WRENCH), plan, Events(), clock_ns=clock)
    assert away.sent == []
    off = ScriptedController(clock, lambda k: plan.q[0], 5, ready=False)
    with pytest.raises(ControllerRefused):
        run_stream(off, PathSource(plan, WRENCH), plan, Events(), clock_ns=clock)
    assert off.sent == []


def test_the_wrench_from_currents_is_the_process_wrench(plan, robot):
    """Currents of the simulated robot (its own statics) at the compensated command under the
    wrench give back that wrench through (J^T)^+."""
    cell = SimCell(robot, CellTruth())
    w = np.array([150.0, -90.0, 1200.0, 5.0, -8.0, 3.0])
    i = 5
    q_c = plan.q[i] + plan.gain[i] @ w
    currents = statics(cell, q_c, w).gear_torque / robot.torque_constants
    assert np.allclose(wrench_from_currents(plan, i, 0.0, currents), w, rtol=0, atol=1e-6 * 1200)


def test_the_current_source_filters_and_needs_currents(plan, robot):
    cell = SimCell(robot, CellTruth())

    def currents(k, q):            # the process force sets in at cycle 10
        return statics(cell, q, WRENCH if k >= 10 else None).gear_torque / robot.torque_constants

    source = CurrentsSource(plan, filter_s=0.02, cycle_s=CYCLE_MS * 1e-3)
    ctrl, sink, result = _run(plan, source, 60, currents=currents)
    fz = np.array([r.wrench[2] for r in sink.records])
    # settled on the process force; the currents are the robot's one cycle before, on a path this test
    # runs at 250 mm/s: that cycle's motion changes the joints' torques by about half a percent
    assert abs(fz[-1] - 1500.0) < 0.01 * 1500.0
    # a first-order low-pass: 1 - exp(-5 cycles / 5 cycles) of the step after five cycles
    assert abs(fz[9]) < 0.01 * 1500.0
    assert fz[14] == pytest.approx(1500.0 * (1.0 - np.exp(-1.0)), rel=0.02)
    ctrl, sink, exc = _run(plan, CurrentsSource(plan, filter_s=0.0, cycle_s=0.004), 5)
    assert "MACur" in str(exc)


def test_every_cycle_goes_to_the_log_with_the_correction_arrow(plan, tmp_path):
    from mcap.reader import make_reader

    out = tmp_path / "stream.mcap"
    clock = Clock()
    ctrl = ScriptedController(clock, lambda k: plan.q[0], 60)
    with Recorder(out, clock=lambda: clock.t) as rec, StreamLog(rec, plan, "path") as sink:
        result = run_stream(ctrl, PathSource(plan, WRENCH), plan, sink,
                            settings=StreamSettings(limits=Limits(1.0, 100.0), end_hold_s=0.0), clock_ns=clock)
    cycles, scenes = [], []
    with open(out, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.topic == lf.TOPIC_STREAM_CYCLE:
                cycles.append(json.loads(message.data))
            elif channel.topic == lf.TOPIC_STREAM_SCENE:
                scenes.append(json.loads(message.data))
    assert len(cycles) == result.cycles
    validator = jsonschema.Draft202012Validator(lf.SCHEMAS["elastocal.StreamCycle"])
    for c in cycles:
        validator.validate(c)
    foxglove = json.loads(lf.schema_bytes("foxglove.SceneUpdate"))
    for s in scenes:
        jsonschema.validate(s, foxglove)
    assert scenes[0]["entities"][0]["lines"][0]["points"][0]["x"] == pytest.approx(plan.load_point[0][0])
    # the first arrow is drawn at the first cycle: the load point's displacement by its correction
    arrow = scenes[1]["entities"][0]["arrows"][0]
    moved = plan.position_jacobian[0] @ np.asarray(cycles[0]["correction_rad"])
    assert arrow["shaft_length"] + arrow["head_length"] == pytest.approx(np.linalg.norm(moved) * ARROW_GAIN,
                                                                         rel=1e-9)
    o = arrow["pose"]["orientation"]
    import pinocchio as pin

    x_axis = pin.Quaternion(o["w"], o["x"], o["y"], o["z"]).matrix()[:, 0]
    assert np.allclose(x_axis, moved / np.linalg.norm(moved), atol=1e-9)


def test_on_the_controller_s_time_a_slow_computer_is_not_late_but_an_injected_delay_is(plan):
    """Through :class:`ControllerTime` the loop judges on the controller's clock: every message
    here waits 10 ms on this computer's (injected) clock before the loop takes it up, which the
    wall-clock judgement calls late, the controller's time does not; the compute time is still
    measured (on ``measure_ns``). A message the controller itself sent late is still late."""
    slow = {k: 10_000_000 for k in range(60)}
    _, sink, exc = _run(plan, PathSource(plan, WRENCH), 60, delays=slow)
    assert isinstance(exc, WatchdogFault) and exc.cause is LateCause.SCHEDULE

    clock, wall = Clock(), Clock(step_ns=7_000)
    ctrl = ControllerTime(ScriptedController(clock, lambda k: plan.q[0], 60, delays=slow, gaps=(30,)))
    sink = Events()
    result = run_stream(ctrl, PathSource(plan, WRENCH), plan, sink, clock_ns=ctrl.clock_ns, measure_ns=wall,
                        settings=StreamSettings(limits=Limits(1.0, 100.0), end_hold_s=0.0))
    assert result.late == 0 and result.lost == 1
    assert [r.t_ns - sink.records[0].t_ns for r in sink.records[:3]] == [0, 4_000_000, 8_000_000]
    assert all(r.compute_ns == 7_000 and r.response_ns == 7_000 for r in sink.records)
    assert sink.records[30].period_ns == 8_000_000             # across the lost message
