"""The procedure engine on the virtual cell (SimCell physics on a virtual clock):
static identification from the log, abort and resume, settle timeouts,
friction runs and sweeps, the operator interface, plan files."""

import io
import json

import numpy as np
import pytest

from elastocal.acquisition.cellio import SampleGap, Samples, VirtualCellIO, VirtualTiming
from elastocal.acquisition.export import load_log
from elastocal.acquisition.logreader import read_log
from elastocal.formats.plan import (
    CheckSpec,
    FrictionSpec,
    LoadSpec,
    SettleSpec,
    SweepSpec,
    load_plan,
    parse_plan,
    plan_toml,
)
from elastocal.acquisition.procedures import run_procedures
from elastocal.acquisition.steps import build_steps
from elastocal.acquisition.ui import Aborted, AutoUI, TerminalUI, progress_line
from elastocal.errors import DeviceTimeout, InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import identify_static
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.static import random_poses
from elastocal.model.kinds import KinematicForm, TorqueSource

TIMING = VirtualTiming(drive_rate_hz=250.0, tracker_rate_hz=250.0)
LOADS = (LoadSpec("L1", mass_kg=60.0), LoadSpec("L2", mass_kg=110.0),
         LoadSpec("L3", force_n=(650.0, -300.0, -400.0), description="cable pull through the force gauge"))
SETTLE = SettleSpec(speed_rad_s=2e-3, spread_m=20e-6, window_s=0.15, timeout_s=20.0)
Q_A = (0.2, 0.3, -0.4, 0.3, 1.0, 0.2)
Q_B = (0.5, 0.55, -0.2, 0.6, 1.2, 0.5)


@pytest.fixture(scope="module")
def poses(robot):
    return random_poses(robot, 8, np.random.default_rng(11))


def static_plan(poses, **kw):
    return parse_plan(plan_toml(poses=poses, loads=LOADS, markers=("R1", "R2", "R3"), repeats=2, reading_s=0.04,
                                speed_rad_s=0.6, settle=SETTLE, **kw), source="plan.toml")


def virtual_io(robot, seed=5, timing=TIMING):
    return VirtualCellIO(SimCell(robot, CellTruth()), seed=seed, timing=timing)


class AbortAt(AutoUI):
    """Answers yes, then aborts at prompt number ``n`` (1-based)."""

    def __init__(self, n):
        super().__init__(quiet=True)
        self.n = n

    def confirm(self, text):
        super().confirm(text)
        if len(self.prompts) == self.n:
            raise Aborted(f"aborted by the operator at: {text}")
        return "yes"


def check_stiffness(fit):
    truth = np.array(CellTruth().stiffness)
    k = fit.values([f"k{j}" for j in range(1, 7)])
    err = np.abs(k - truth) / truth
    assert np.all(err[:3] < 0.02), err
    assert np.all(err[3:] < 0.05), err


def test_static_procedure_log_identifies_stiffness(robot, poses, tmp_path):
    plan = static_plan(poses)
    out = run_procedures(virtual_io(robot), plan, tmp_path / "log.mcap")
    assert out.status == "completed" and out.steps_done == out.steps_total == len(poses)
    contents = read_log(tmp_path / "log.mcap")
    assert contents.complete and not contents.truncated
    kinds = [e["kind"] for e in contents.events]
    assert kinds[0] == "procedure_start" and kinds[-1] == "procedure_end"
    assert contents.end_status == "completed"
    # every pose: settle before each hold, 2 repeats x 3 markers x (1 + 3 loads) readings
    assert kinds.count("reading") == len(poses) * 2 * 3 * 4
    assert kinds.count("settle") == len(poses) * 4
    assert all(e["settled"] for e in contents.events if e["kind"] == "settle")
    answers = [e for e in contents.events if e["kind"] == "answer"]
    assert answers and all(a["answer"] == "yes" and a["automatic"] for a in answers)
    loads = [e for e in contents.events if e["kind"] == "load" and e["load"] == "L2"]
    assert loads[0]["wrench"] == pytest.approx([0, 0, -110.0 * 9.81, 0, 0, 0])
    log_robot, static, runs = load_log(tmp_path / "log.mcap")
    assert runs is None and log_robot.name == robot.name
    assert len(static) == len(poses) * 4 * 2 * 3
    fit = identify_static(log_robot, static, torque=TorqueSource.CURRENT, form=KinematicForm.EXACT)
    check_stiffness(fit)


def test_the_core_design_identified_from_its_log_meets_the_core_tolerances(robot, tmp_path):
    """The first experiment of the project (12 poses, unloaded + 3 loads, 3 markers, 3 repeats) run as
    a procedure and identified from the log: k1-k3 within 2 %, k4-k6 within 5 %,
    residual within 1.15x the noise floor."""
    poses12 = random_poses(robot, 12, np.random.default_rng(21))
    plan = parse_plan(plan_toml(poses=poses12, loads=LOADS, markers=("R1", "R2", "R3"), repeats=3,
                                reading_s=0.04, speed_rad_s=0.6, settle=SETTLE), source="plan.toml")
    out = run_procedures(virtual_io(robot, seed=8), plan, tmp_path / "core.mcap")
    assert out.status == "completed"
    _, static, _ = load_log(tmp_path / "core.mcap")
    assert len(static) == 12 * 4 * 3 * 3
    fit = identify_static(robot, static, torque=TorqueSource.CURRENT, form=KinematicForm.EXACT)
    check_stiffness(fit)
    assert fit.noise_floor is not None and fit.rms <= 1.15 * fit.noise_floor, (fit.rms, fit.noise_floor)


def test_abort_then_resume_gives_the_same_steps_once(robot, poses, tmp_path):
    plan = static_plan(poses[:4])
    first = tmp_path / "first.mcap"
    # prompt 1: clear the cell; each pose asks 4 (unload, L1, L2, L3): abort in pose 3
    out = run_procedures(virtual_io(robot), plan, first, ui=AbortAt(1 + 4 * 2 + 2))
    assert out.status == "aborted" and out.steps_done == 2
    old = read_log(first)
    assert old.complete and old.end_status == "aborted"
    assert old.completed_steps == ("static/P1", "static/P2") and old.incomplete_steps == ("static/P3",)
    assert [e["answer"] for e in old.events if e["kind"] == "answer"][-1] == "abort"
    _, partial, _ = load_log(first)
    assert sorted(set(partial.pose)) == ["P1", "P2"]  # the interrupted pose is left out whole

    second = tmp_path / "second.mcap"
    out2 = run_procedures(virtual_io(robot, seed=6), plan, second, resume_from=first)
    assert out2.status == "completed" and out2.steps_resumed == 2 and out2.steps_done == 4
    new = read_log(second)
    assert new.completed_steps == ("static/P1", "static/P2", "static/P3", "static/P4")
    assert new.sessions[0]["resumed_from"] == str(first)
    _, static, _ = load_log(second)
    # the copied poses are bit for bit the ones of the first log
    for p in ("P1", "P2"):
        a, b = partial.subset(partial.pose == p), static.subset(static.pose == p)
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.currents, b.currents)
        np.testing.assert_array_equal(a.t, b.t)
    assert sorted(set(static.pose)) == ["P1", "P2", "P3", "P4"]
    with pytest.raises(InputError, match="another plan"):
        run_procedures(virtual_io(robot), static_plan(poses[:3]), tmp_path / "third.mcap", resume_from=first)
    with pytest.raises(InputError, match="resume must name the interrupted log, out a new file") as refused:
        run_procedures(virtual_io(robot), plan, first, resume_from=first, overwrite=True)
    # the library names its arguments; a command line says them as its flags
    assert str(refused.value.on_command_line()).endswith("--resume must name the interrupted log, --out a new file")


def test_settle_timeout_is_a_recorded_device_error(robot, poses, tmp_path):
    strict = SettleSpec(speed_rad_s=2e-3, spread_m=1e-6, window_s=0.1, timeout_s=1.0)  # below the noise
    plan = parse_plan(plan_toml(poses=poses[:1], loads=LOADS[:1], markers=("R1",), settle=strict))
    with pytest.raises(DeviceTimeout, match="did not settle within 1 s"):
        run_procedures(virtual_io(robot), plan, tmp_path / "log.mcap")
    contents = read_log(tmp_path / "log.mcap")
    assert contents.complete and contents.end_status == "failed"
    fault = [e for e in contents.events if e["kind"] == "fault"]
    assert fault and fault[0]["error"] == "DeviceTimeout"
    settle = [e for e in contents.events if e["kind"] == "settle"][-1]
    assert settle["settled"] is False and settle["spread_m"] > 1e-6
    assert contents.completed_steps == ()


def test_friction_runs_and_sweep_make_a_run_table(robot, tmp_path):
    marker_timing = VirtualTiming(drive_rate_hz=200.0, tracker_rate_hz=100.0)
    friction = (FrictionSpec("F1", start=Q_A, end=Q_B, speeds_rad_s=(0.1, 0.25), loads=("0", "L1"), marker="R1"),)
    sweep = SweepSpec(q=(0.0, 0.0, -0.3, 0.0, 0.8, 0.0), q2_from=-0.2, q2_to=0.6, speed_rad_s=0.2)
    text = plan_toml(poses=[], loads=LOADS[:1], markers=(), settle=SETTLE, friction=friction, sweep=sweep,
                     speed_rad_s=1.0)
    plan = parse_plan(text)
    assert plan.procedures == ("friction", "sweep")
    out = run_procedures(virtual_io(robot, timing=marker_timing), plan, tmp_path / "runs.mcap")
    assert out.status == "completed" and out.steps_total == 4 + 1
    _, static, runs = load_log(tmp_path / "runs.mcap")
    assert static is None
    ids = list(dict.fromkeys(runs.run))
    assert ids == ["F1-1-UV", "F1-1-VU", "F1-2-UV", "F1-2-VU", "F1-3-UV", "F1-3-VU", "F1-4-UV", "F1-4-VU",
                   "sweep-1+", "sweep-1-"]
    for r in ids:
        rows = runs.run == r
        q = runs.q[rows]
        t = runs.t[rows]
        assert np.all(np.diff(t) > 0)
        direction = runs.direction[rows][0]
        if r.startswith("F1"):
            span = (np.array(Q_B) - np.array(Q_A)) * (1 if direction == "UV" else -1)
            # the run goes from one end to the other, along the path
            assert np.allclose(q[-1] - q[0], span, atol=0.02)
            speed = 0.1 if r.split("-")[1] in ("1", "3") else 0.25
            moving = np.abs(runs.dq[rows][:, 0]) > 0
            assert np.max(np.abs(runs.dq[rows][moving])) == pytest.approx(speed, rel=0.05)
            assert runs.load[rows][0] == ("0" if r.split("-")[1] in ("1", "2") else "L1")
            # the followed marker is in the rows where the tracker measured (100 of 200 Hz)
            has = runs.marker[rows] == "R1"
            assert 0.3 < has.mean() < 0.7 and np.all(np.isfinite(runs.xyz[rows][has]))
        else:
            assert direction == ("+" if r.endswith("+") else "-")
            assert np.ptp(q[:, 1]) == pytest.approx(0.8, abs=0.02) and np.ptp(q[:, 0]) == 0.0
    # loaded runs carry the nominal weight
    assert np.allclose(runs.wrench[runs.load == "L1"][:, 2], -60.0 * 9.81)
    # friction shows: joint-1 current differs between UV and VU at the same place
    uv, vu = runs.run == "F1-1-UV", runs.run == "F1-1-VU"
    i_uv = np.interp(0.35, runs.q[uv][:, 0], runs.currents[uv][:, 0])
    i_vu = np.interp(0.35, runs.q[vu][::-1, 0], runs.currents[vu][::-1, 0])
    assert np.isfinite(i_uv) and np.isfinite(i_vu)


def test_check_procedure_is_short(robot, poses, tmp_path):
    friction = (FrictionSpec("F1", start=Q_A, end=Q_B, speeds_rad_s=(0.2, 0.3)),)
    text = plan_toml(poses=poses[:4], loads=LOADS, markers=("R1", "R2"), repeats=2, reading_s=0.04,
                     speed_rad_s=0.6, settle=SETTLE, friction=friction,
                     check=CheckSpec(poses=("P1", "P3"), load="L2", friction="F1"))
    plan = parse_plan(text)
    steps = build_steps(plan, ("check",))
    assert [s.id for s in steps] == ["check/P1", "check/P3", "check/F1"]
    out = run_procedures(virtual_io(robot), plan, tmp_path / "check.mcap", procedures=("check",))
    assert out.status == "completed"
    _, static, runs = load_log(tmp_path / "check.mcap")
    assert sorted(set(static.pose)) == ["P1", "P3"] and sorted(set(static.load)) == ["0", "L2"]
    assert list(dict.fromkeys(runs.run)) == ["check-F1-UV", "check-F1-VU"]


def test_terminal_ui_prompts_progress_and_abort():
    answers = iter(["L2\n", "yes\n", "\n", "what?\n", "yes\n", "a\n"])
    out = io.StringIO()
    ui = TerminalUI(out, read_line=lambda: next(answers))
    assert ui.confirm_load("hang load L2, 66 kg, on the load point", "L2") == "yes"   # the load's name
    assert ui.confirm("clear the cell") == "yes"
    assert ui.confirm("remove load L2") == "yes"   # a bare Enter or an unknown answer is asked again
    with pytest.raises(Aborted, match="remove every load"):
        ui.confirm("remove every load")
    text = out.getvalue()
    assert ">>> hang load L2, 66 kg, on the load point; type 'yes' or 'L2' and Enter (a + Enter aborts): " in text
    assert text.count("answer 'yes' to go on, or 'a' to abort") == 2

    def eof():
        raise EOFError

    with pytest.raises(Aborted):
        TerminalUI(io.StringIO(), read_line=eof).confirm("hang load L1")
    line = progress_line(3, 12, "static pose P4", 83.0, 190.0, width=12)
    assert line == "[###---------] 3/12  static pose P4  1:23 elapsed, ~3:10 left"
    ui.progress(3, 12, "static pose P4", 83.0, 190.0)
    ui.progress(3, 12, "static pose P4", 84.0, 189.0)  # not a terminal: one line per step
    assert out.getvalue().count("3/12") == 1


def test_progress_and_time_left_shown_during_a_procedure(robot, poses, tmp_path):
    out = io.StringIO()
    plan = static_plan(poses[:2])
    run_procedures(virtual_io(robot), plan, tmp_path / "log.mcap", ui=AutoUI(out))
    text = out.getvalue()
    assert "0/2  static pose P1" in text and "1/2  static pose P2" in text
    assert "2/2  static pose P2 done" in text and "left" in text
    assert (">>> remove load L1, then hang load L2, 110 kg, on the load point; step out of the cell: yes "
            "(answered automatically)") in text


def test_plan_file_errors_name_file_and_key(tmp_path):
    good = plan_toml(poses=[Q_A], loads=LOADS[:1], markers=("R1",))
    assert parse_plan(good).static.poses[0].q == Q_A
    cases = [
        (good.replace('id = "L1"', 'id = "0"'), "load[1].id"),
        (good.replace("q = [\n    0.2,", "q = [\n    20.0,"), "degrees"),
        (good.replace('markers = [\n    "R1",\n]', 'markers = "R1"'), "static.markers"),
        (good + '\n[check]\nposes = ["P9"]\nload = "L1"\n', "unknown pose 'P9'"),
        (good.replace("mass_kg = 60.0", "mass_kg = 60.0, force_n = [1.0, 2.0, 3.0]"), "either mass_kg"),
        (good.replace("repeats = 3", "repeats = 0"), "static.repeats"),
        (good + "\n[speling]\n", "unknown key"),
        ("name = [", "not valid TOML"),
    ]
    for text, expected in cases:
        assert text != good
        with pytest.raises(InputError, match=expected.replace("[", r"\[").replace("]", r"\]")) as exc:
            parse_plan(text, source="plan.toml")
        assert str(exc.value).startswith("plan.toml")
    path = tmp_path / "plan.toml"
    path.write_text(good.replace('markers = [\n    "R1",', 'markers = [\n    "R9",'))
    with pytest.raises(InputError, match="unknown marker 'R9'"):
        load_plan(path).validate_for(bundled_robot())
    with pytest.raises(InputError, match="cannot read"):
        load_plan(tmp_path / "missing.toml")


def test_plan_toml_roundtrip(poses):
    """plan_toml writes what parse_plan reads, loads and settle included."""
    plan = static_plan(poses[:2])
    assert [p.id for p in plan.static.poses] == ["P1", "P2"]
    assert plan.static.poses[1].loads == ("L1", "L2", "L3")
    assert plan.loads[2].wrench((0, 0, -9.81)) == (650.0, -300.0, -400.0, 0.0, 0.0, 0.0)
    assert plan.settle == SETTLE
    assert json.dumps(plan.static.poses[0].q)  # plain floats
    own = parse_plan(plan_toml(poses=poses[:2], loads=LOADS, markers=("R1",), pose_loads={"P2": ("L3", "L1")}))
    assert own.static.poses[0].loads == ("L1", "L2", "L3") and own.static.poses[1].loads == ("L3", "L1")


def test_resume_after_a_kill_continues_a_truncated_log(robot, poses, tmp_path):
    plan = static_plan(poses[:3])
    full = tmp_path / "full.mcap"
    run_procedures(virtual_io(robot), plan, full)
    data = full.read_bytes()
    killed = tmp_path / "killed.mcap"
    killed.write_bytes(data[: int(len(data) * 0.55)])   # what a kill in pose P2 or P3 leaves
    old = read_log(killed)
    assert not old.complete and old.truncated and old.end_status is None
    done = old.completed_steps
    assert 1 <= len(done) <= 2
    resumed = tmp_path / "resumed.mcap"
    # a rebooted clock: the new session's times lie before the old one's
    timing = VirtualTiming(drive_rate_hz=250.0, tracker_rate_hz=250.0, start_ns=500_000_000)
    out = run_procedures(virtual_io(robot, seed=7, timing=timing), plan, resumed, resume_from=killed)
    assert out.status == "completed" and out.steps_resumed == len(done)
    _, before, _ = load_log(killed)
    _, after, _ = load_log(resumed)
    assert sorted(set(after.pose)) == ["P1", "P2", "P3"]
    for p in set(before.pose):
        np.testing.assert_array_equal(before.subset(before.pose == p).xyz, after.subset(after.pose == p).xyz)
    check_stiffness(identify_static(robot, after, torque=TorqueSource.CURRENT, form=KinematicForm.EXACT))


class LosesJoint2InReadings(VirtualCellIO):
    """Joint 2's stream loses every sample of the first ``n`` polls of a reading window (a gap),
    the polls that hold a window open for a drive's sample and wait for late ones included."""

    def __init__(self, *args, n: int, reading_s: float, **kw):
        super().__init__(*args, **kw)
        self.n, self.reading_s, self.lost = n, reading_s, []

    def poll(self, markers, duration_s):
        samples = super().poll(markers, duration_s)
        reading = ((markers and duration_s in (self.reading_s, self.reading_s / 4))
                   or (not markers and duration_s == 0.005))
        if not (reading and len(self.lost) < self.n):
            return samples
        gone = [d for d in samples.drives if d.joint == 2]
        if not gone:
            return samples
        self.lost.append((gone[0].t_ns, gone[-1].t_ns))
        gap = SampleGap("drive J2", gone[0].t_ns, gone[-1].t_ns, len(gone), "no TPDO in the SYNC cycle", 2)
        return Samples(tuple(d for d in samples.drives if d.joint != 2), samples.tracker, samples.gaps + (gap,))


def test_a_reading_whose_window_a_drive_gap_swallowed_is_held_open_for_the_drive(robot, poses, tmp_path):
    """A gap over a reading's window keeps the window open until the drive's samples come (a busy
    host's late cycles), so no reading is taken again and none lacks a drive's current."""
    plan = static_plan(poses[:2])
    io = LosesJoint2InReadings(SimCell(robot, CellTruth()), seed=5, timing=TIMING, n=2, reading_s=0.04)
    out = run_procedures(io, plan, tmp_path / "log.mcap")
    assert out.status == "completed" and len(io.lost) == 2
    contents = read_log(tmp_path / "log.mcap")
    readings = [e for e in contents.events if e["kind"] == "reading"]
    assert len(readings) == 2 * 4 * 2 * 3                    # every reading once, none of the lost windows
    assert not any(r["window_ns"] == list(w) for r in readings for w in io.lost)
    assert sum(e["kind"] == "gap" for e in contents.events) == 2
    _, static, _ = load_log(tmp_path / "log.mcap")
    assert np.all(np.isfinite(static.currents))            # every row has every drive's current


def test_a_drive_that_loses_every_try_of_a_reading_ends_the_procedure(robot, poses, tmp_path):
    plan = static_plan(poses[:1])
    io = LosesJoint2InReadings(SimCell(robot, CellTruth()), seed=5, timing=TIMING, n=10**6, reading_s=0.04)
    with pytest.raises(DeviceTimeout, match=r"lost every sample of 6 reading window\(s\) in 4 tries at pose P1"):
        run_procedures(io, plan, tmp_path / "log.mcap")
    contents = read_log(tmp_path / "log.mcap")                 # the log up to the fault is readable
    assert contents.complete and contents.end_status == "failed"
    assert [e["error"] for e in contents.events if e["kind"] == "fault"] == ["DeviceTimeout"]
    # every try of every window held open to its limit, its gaps recorded
    assert sum(e["kind"] == "gap" for e in contents.events) == len(io.lost) > 4 * 6
