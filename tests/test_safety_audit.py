"""The second shop-floor safety audit: each reproducer of the audit, as a test that failed
before the fix (its docstring says what it reproduces). The simulated devices are real
protocol peers (CANopen on a virtual or loopback bus, Modbus TCP on 127.0.0.1); prompts are
answered on a real pseudo-terminal where a terminal is the point."""

from __future__ import annotations

import json
import os
import pathlib
import stat
import subprocess
import sys
import time
from dataclasses import replace

import pytest

from elastocal.acquisition.logreader import read_log
from elastocal.acquisition.procedures import run_calibration
from elastocal.acquisition.ui import AutoUI
from elastocal.drivers import open_controller
from elastocal.drivers.base import COMMAND_MOVE_JOINTS
from elastocal.drivers.config import parse_cell_config
from elastocal.errors import InputError
from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.sims.modbus_server import ModbusServerThread, SimModbusDrive
from elastocal.sims.serve import SimulatedCell, example_cell_config, to_loopback_can

#: Modbus function codes that change a device's data
WRITE_FUNCTIONS = {5, 6, 15, 16, 22, 23}
#: where the packaged simulated cell starts (its [sim] start_q)
START_Q = (0.0, 0.2, -0.4, 0.0, 0.5, 0.0)


def _plan(pose=START_Q, loads=(LoadSpec("L1", mass_kg=50.0),)) -> str:
    return plan_toml(poses=[pose], loads=loads, markers=("R1",), repeats=1, reading_s=0.05,
                     settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=20.0))


class _Watching(AutoUI):
    """Answers yes, and notes at every prompt whether the simulated robot moved."""

    def __init__(self, sim):
        super().__init__(quiet=True)
        self.sim = sim
        self.moving_at_prompt: list[bool] = []
        self.messages: list[str] = []

    def message(self, text):
        self.messages.append(text)

    def confirm(self, text):
        self.moving_at_prompt.append(self.sim.world.is_moving())
        return super().confirm(text)


# ------------------------------------------------------------------ 1: no prompt while the robot moves
def test_no_prompt_while_a_move_of_a_killed_run_goes_on(tmp_path):
    """Reproduces audit item 1: a calibrate killed during a move leaves the controller busy and the
    robot moving; the next calibrate showed "clear the cell" at once (q2 still moving). Now it waits
    for standstill (controller idle, joints still), says so, and only then asks."""
    config = example_cell_config(can_channel="audit-moving", move_speed_rad_s=0.15)
    target = (0.0, 0.65, -0.4, 0.0, 0.5, 0.0)            # 0.45 rad on q2 at 0.15 rad/s: 3 s of motion
    plan = parse_plan(_plan(pose=target))
    with SimulatedCell(config) as sim:
        # what the killed process left behind: a move request the controller accepted and still runs
        controller = open_controller(sim.config.controller)
        try:
            controller._request(COMMAND_MOVE_JOINTS, {"target": target}, controller.status().ack % 65535 + 1)
            deadline = time.monotonic() + 5
            while not sim.world.is_moving() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert sim.world.is_moving() and controller.status().busy
        finally:
            controller.close()
        ui = _Watching(sim)
        out = run_calibration(sim.config, plan, tmp_path / "b.mcap", yes=True, ui=ui, world=sim.world)
    assert out.status == "completed"
    assert ui.moving_at_prompt and not any(ui.moving_at_prompt), ui.moving_at_prompt
    assert any(m.startswith("waiting for the robot to stand still before the next prompt: the cell controller "
                            "reports a motion") for m in ui.messages), ui.messages
    events = read_log(tmp_path / "b.mcap").events
    first_prompt = next(i for i, e in enumerate(events) if e["kind"] == "prompt")
    waited = events[first_prompt - 1]
    assert waited["kind"] == "standstill" and waited["settled"] is True
    assert waited["duration_s"] > 1.0, waited            # the rest of the 3 s move, then 0.5 s of standstill


def test_standstill_that_never_comes_is_a_fault_with_a_resume_hint(tmp_path, capsys):
    """A robot that keeps moving (a drive reports a speed) is never prompted: after the stated
    time the procedure stops with NotAtRest, and the command says how to resume."""
    from elastocal.acquisition import session
    from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
    from elastocal.acquisition.procedures import run_procedures
    from elastocal.errors import NotAtRest
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.cell import CellTruth, SimCell

    class Creeping(VirtualCellIO):
        def poll(self, markers, duration_s):
            s = super().poll(markers, duration_s)
            return replace(s, drives=tuple(replace(d, velocity_rad_s=0.01) if d.joint == 2 else d
                                           for d in s.drives))

    io = Creeping(SimCell(bundled_robot(), CellTruth()), q0=START_Q,
                  timing=VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0))
    ui = _Watching.__new__(_Watching)
    AutoUI.__init__(ui, quiet=True)
    ui.messages, ui.moving_at_prompt, ui.sim = [], [], None
    ui.confirm = lambda text: pytest.fail(f"asked {text!r} while a joint moved")
    with pytest.raises(NotAtRest, match="did not stand still within 120 s"):
        run_procedures(io, parse_plan(_plan()), tmp_path / "c.mcap", ui=ui)
    assert ui.messages == [f"waiting for the robot to stand still before the next prompt: a joint moves at 0.01 "
                           f"rad/s (limit {session.STANDSTILL_SPEED_RAD_S:g}) (at most 120 s)"]
    contents = read_log(tmp_path / "c.mcap")
    kinds = [e["kind"] for e in contents.events]
    assert "prompt" not in kinds and kinds[-3:] == ["standstill", "fault", "procedure_end"], kinds
    assert contents.events[-2]["error"] == "NotAtRest" and contents.complete


# ------------------------------------------------------------------ 2: a person behind every answer
def _served_cell_file(tmp_path, sim, *, rig: str | None = None):
    config = replace(sim.config, sim={k: v for k, v in sim.config.sim.items() if k != "load_url"})
    if rig is not None:
        config = replace(config, sim={**config.sim, "load_url": rig})
    path = tmp_path / "cell.toml"
    path.write_text(config.to_toml())
    return path


def _cli(args, *, stdin: bytes | None = None, timeout=120):
    return subprocess.run([sys.executable, "-m", "elastocal", *map(str, args)], input=stdin,
                          capture_output=True, timeout=timeout)


@pytest.mark.slow
def test_piped_answers_never_answer_a_real_cells_prompts(tmp_path):
    """Reproduces audit item 2: `yes yes | elastocal calibrate --cell real.toml ...` ran unattended
    and logged the piped lines as a person's answers. Now a real cell's prompts are answered at a
    terminal only: one line, exit 2, no log, nothing written to the controller."""
    (tmp_path / "plan.toml").write_text(_plan())
    with SimulatedCell(to_loopback_can(example_cell_config(move_speed_rad_s=2.0))) as sim:
        cell = _served_cell_file(tmp_path, sim)                 # no load rig: a real cell as far as anyone knows
        out = _cli(["calibrate", "--cell", cell, "--plan", tmp_path / "plan.toml", "--out", tmp_path / "x.mcap"],
                   stdin=b"yes\n" * 50)
        (server,) = sim.modbus_servers.values()
        writes = [r for r in server.requests if r[1] in WRITE_FUNCTIONS]
    err = out.stderr.decode().strip().splitlines()
    assert out.returncode == 2 and len(err) == 1, out.stderr.decode()
    assert "the standard input is not a terminal" in err[0] and "run it in a terminal" in err[0]
    assert not (tmp_path / "x.mcap").exists() and writes == []


PTY_CHILD = r"""
import json
import os
import sys
from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.procedures import run_procedures
from elastocal.acquisition.ui import TerminalUI
from elastocal.formats.plan import parse_plan
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import CellTruth, SimCell

io = VirtualCellIO(SimCell(bundled_robot(), CellTruth()), q0=(0.0, 0.2, -0.4, 0.0, 0.5, 0.0),
                   timing=VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0))
out = run_procedures(io, parse_plan(open(sys.argv[1]).read()), sys.argv[2], ui=TerminalUI(sys.stderr))
print("STATUS", out.status, file=sys.stderr, flush=True)
"""


def test_answers_come_from_the_terminal_after_the_prompt_and_say_so_in_the_log(tmp_path, Terminal):
    """Prompts on a real pseudo-terminal (keys typed ahead are tests/test_safety.py's): the log
    records each answer's source (the terminal) and its delay after the prompt was shown."""
    (tmp_path / "plan.toml").write_text(_plan())
    log = tmp_path / "t.mcap"
    term = Terminal([sys.executable, "-c", PTY_CHILD, str(tmp_path / "plan.toml"), str(log)])
    try:
        at = 0
        answered = 0
        while True:
            try:
                shown = term.wait_for(">>> ", 60, at)
            except AssertionError:
                break
            end = term.wait_for("(a + Enter aborts): ", 30, shown)
            time.sleep(0.3)                                  # the operator reads the prompt
            answer = "L1" if "'L1'" in term.screen[shown:end] else "yes"
            term.type(answer + "\n")
            at = term.wait_for(answer + "\r\n", 30, end) + 1
            answered += 1
        term.wait_for("STATUS completed", 60)
    finally:
        term.close()
    events = read_log(log).events
    answers = [e for e in events if e["kind"] == "answer"]
    assert answered == len(answers) == 4, answers           # clear, unload at the start, hang L1, remove L1
    assert all(a["source"].startswith("terminal /dev/pts/") and a["automatic"] is False for a in answers), answers
    assert all(0.25 < a["delay_s"] < 30 for a in answers), [a["delay_s"] for a in answers]


def test_a_pipe_on_stdin_answers_nothing(tmp_path):
    """The library side of audit item 2: a TerminalUI whose standard input is a pipe aborts at the
    first prompt (nothing is answered from it), and the log says why."""
    plan = tmp_path / "plan.toml"
    plan.write_text(_plan())
    log = tmp_path / "p.mcap"
    out = subprocess.run([sys.executable, "-c", PTY_CHILD, str(plan), str(log)], input=b"yes\n" * 20,
                         capture_output=True, timeout=120)
    assert "STATUS aborted" in out.stderr.decode(), out.stderr.decode()
    answers = [e for e in read_log(log).events if e["kind"] == "answer"]
    assert [(a["answer"], a["source"]) for a in answers] == [("abort", "no terminal")]


# ------------------------------------------------------------------ 3, 5: writes only where declared
@pytest.mark.slow
def test_a_load_url_naming_another_modbus_device_is_refused_and_never_written(tmp_path):
    """Reproduces audit item 3: `[sim] load_url` naming any Modbus device on 127.0.0.1 made calibrate
    write registers 0-11 there at every load change (read-only ones included) and let --yes through.
    Now the rig is checked by its device identification first: one line, exit 2, nothing written."""
    from elastocal.sims.world import SimWorld
    from elastocal.sims.config import sim_config

    (tmp_path / "plan.toml").write_text(_plan())
    drive_cfg = parse_cell_config(
        '[cell]\nrobot = "hh150"\n[[drive]]\njoint = 1\nurl = "modbus+tcp://127.0.0.1:0?unit=1"\n'
        '[drive.registers]\ncurrent = { address = 0, type = "float32", unit = "A" }\n'
        'position = { address = 2, type = "float32", unit = "rad" }\n').drives[0]
    config = example_cell_config(move_speed_rad_s=2.0)
    world = SimWorld.from_config(config.load_robot(), sim_config(config))
    other = ModbusServerThread([SimModbusDrive(drive_cfg, world).device], tcp=("127.0.0.1", 0)).start()
    try:
        with SimulatedCell(to_loopback_can(config)) as sim:
            cell = _served_cell_file(tmp_path, sim, rig=f"modbus+tcp://127.0.0.1:{other.port}?unit=1")
            out = _cli(["calibrate", "--cell", cell, "--plan", tmp_path / "plan.toml", "--out",
                        tmp_path / "x.mcap", "--yes"])
            (server,) = sim.modbus_servers.values()
            controller_writes = [r for r in server.requests if r[1] in WRITE_FUNCTIONS]
    finally:
        other.close()
    err = out.stderr.decode().strip().splitlines()
    assert out.returncode == 2 and len(err) == 1, out.stderr.decode()
    assert "is not a simulated cell's load rig" in err[0] and "nothing was written" in err[0], err
    assert [r for r in other.requests if r[1] in WRITE_FUNCTIONS] == [] and controller_writes == []
    assert not (tmp_path / "x.mcap").exists()


def test_every_modbus_write_needs_a_register_declared_writable():
    """The one write path of the drivers refuses a register the map does not declare writable,
    before anything is sent; the load rig writes its wrench only through it."""
    from elastocal.drivers.load_rig import WRENCH, open_load_rig
    from elastocal.sims.load_rig import SimLoadRig, rig_identity
    from elastocal.sims.world import SimWorld
    from elastocal.sims.config import sim_config

    config = example_cell_config()
    world = SimWorld.from_config(config.load_robot(), sim_config(config))
    rig = SimLoadRig(world)
    server = ModbusServerThread([rig.device], tcp=("127.0.0.1", 0), identity=rig_identity()).start()
    try:
        with open_load_rig(f"modbus+tcp://127.0.0.1:{server.port}?unit=1") as loads:
            with pytest.raises(InputError, match="not declared writable"):
                loads.link.write_spec(replace(WRENCH, access="read"), [0.0] * 6, unit=1)
            assert [r for r in server.requests if r[1] in WRITE_FUNCTIONS] == []
            loads.hang((0.0, 0.0, -500.0, 0.0, 0.0, 0.0))
            loads.hang(None)
        assert rig.hung == [(0.0, 0.0, -500.0, 0.0, 0.0, 0.0), None]
        assert [r[1:] for r in server.requests if r[1] in WRITE_FUNCTIONS] == [(16, 0, 12), (16, 0, 12)]
    finally:
        server.close()


OVERLAP = """
[cell]
robot = "hh150"
[[drive]]
joint = 1
url = "modbus+tcp://10.0.0.5:502?unit=1"
[drive.registers]
current  = { address = 0, type = "float32", unit = "A" }
position = { address = 2, type = "float32", unit = "rad" }
[controller]
url = "modbus+tcp://10.0.0.5:502?unit=UNIT"
[controller.registers]
command  = { address = 0, type = "uint16", access = "write" }
sequence = { address = 100, type = "uint16", access = "write" }
ack      = { address = 101, type = "uint16" }
status   = { address = 102, type = "uint16" }
"""


def test_devices_sharing_a_modbus_unit_must_not_share_registers():
    """Reproduces audit item 5: a drive and the controller on one Modbus endpoint and unit with
    overlapping registers were accepted (the controller's command aliased the drive's current).
    Refused at config load, naming both; another unit, or another protocol's endpoint, is checked too."""
    with pytest.raises(InputError) as info:
        parse_cell_config(OVERLAP.replace("UNIT", "1"), source="cell.toml")
    assert str(info.value) == ("cell.toml: controller's register command and drive J1's register current are both "
                               "holding register 0 of unit 1 on modbus+tcp://10.0.0.5:502?unit=1: one device's value "
                               "would be read or written as the other's")
    assert parse_cell_config(OVERLAP.replace("UNIT", "2"), source="cell.toml").controller is not None
    tracker = OVERLAP.replace("UNIT", "2") + '[tracker]\nurl = "tracker+tcp://10.0.0.5:502"\nmarkers = ["R1"]\n'
    with pytest.raises(InputError, match="are on one endpoint but speak different protocols"):
        parse_cell_config(tracker, source="cell.toml")
    # a served cell's load rig shares no register with the cell's devices either
    from elastocal.sims.config import sim_config

    rig = parse_cell_config(OVERLAP.replace("10.0.0.5", "127.0.0.1").replace("UNIT", "2")
                            + '[sim]\nload_url = "modbus+tcp://127.0.0.1:502?unit=1"\n', source="cell.toml")
    with pytest.raises(InputError, match="load rig's register wrench and drive J1's register current"):
        sim_config(rig)


# ------------------------------------------------------------------ 4: outputs replace regular files only
def test_force_never_replaces_a_fifo_a_device_or_a_link(tmp_path, capsys):
    """Reproduces audit item 4: `--out X --force` replaced a FIFO or a device node with a plain file
    (as root it broke /dev/null), and calibrate --out followed a symbolic link and overwrote its
    target. Now only regular files are replaced; links, FIFOs and devices are refused, nothing written."""
    from elastocal.cli import main

    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    assert main(["sim", "static", "--out", str(tmp_path / "data"), "--poses", "4", "--loads", "1", "--repeats",
                 "1"]) == 0
    capsys.readouterr()
    robot, static = tmp_path / "data" / "robot.toml", tmp_path / "data" / "static.csv"
    for out, why in ((fifo, "is not a regular file"), (link, "is a symbolic link"),
                     (pathlib.Path(os.devnull), "is not a regular file")):
        rc = main(["identify", "--robot", str(robot), "--static", str(static), "--out", str(out), "--force"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and why in err[0], err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and stat.S_ISCHR(os.stat(os.devnull).st_mode)
    assert link.is_symlink() and target.read_text() == "keep me"
    # the log of a procedure: never through a link, even with --force
    from elastocal.acquisition.recorder import Recorder

    log_link = tmp_path / "cal.mcap"
    log_link.symlink_to(target)
    with pytest.raises(InputError, match="is not a regular file"):
        Recorder(log_link, overwrite=True).__enter__()
    assert target.read_text() == "keep me"


def test_demo_writes_only_into_a_folder_of_its_own(tmp_path, capsys):
    """Reproduces audit item 4 (demo): `demo --out DIR` overwrote a cal.json or cell.toml of the
    user's in DIR. Now a folder with anything but the demo's own files is refused before anything runs."""
    from elastocal.cli import main

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "cal.json").write_text('{"mine": true}')
    rc = main(["demo", "--out", str(mine)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "holds files the demo did not make" in err[0], err
    assert [p.name for p in mine.iterdir()] == ["cal.json"] and (mine / "cal.json").read_text() == '{"mine": true}'


def test_an_empty_out_is_bad_input_not_a_silent_success(tmp_path, capsys):
    """Audit item 7: `identify --out ""` exited 0 and wrote nothing."""
    from elastocal.cli import main

    assert main(["sim", "static", "--out", str(tmp_path), "--poses", "4", "--loads", "1", "--repeats", "1"]) == 0
    capsys.readouterr()
    rc = main(["identify", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "static.csv"),
               "--out", ""])
    assert rc == 2 and capsys.readouterr().err.strip() == "elastocal identify: --out: is empty; give a value"


# ------------------------------------------------------------------ 6: a killed log
KILLED_CHILD = r"""
import sys, time
from elastocal.acquisition.recorder import Recorder
from elastocal.formats.robot_toml import bundled_robot

robot = bundled_robot()
with Recorder(sys.argv[1]) as rec:
    rec.document("robot", robot.name, robot.to_toml())
    rec.event("procedure_start", procedure="static", steps=1)
    rec.event("step_start", step_id="static/P1", procedure="static", step=0)
    n = 0
    while True:
        t = time.monotonic_ns()
        for j in range(1, 7):
            rec.drive_sample(j, t, 0.1 * j, 0.0, 1.0, 0x0237)
        n += 1
        if n % 10 == 0:
            print(t, flush=True)           # handed to the recorder up to here
        time.sleep(0.001)
"""


def test_a_killed_log_is_repaired_into_a_file_mcaps_reader_opens(tmp_path):
    """Reproduces audit item 6: a killed log opened only with elastocal's reader (mcap's make_reader
    failed without a footer) and 0.1-0.5 s of samples were lost per kill. Now `elastocal repair` writes
    a copy with its summary that mcap's reader opens, and the recorder flushes every 50 ms: a kill
    loses at most 50 ms (and one sample period) of what was handed to it."""
    import signal

    from mcap.reader import make_reader

    from elastocal.acquisition.recorder import FLUSH_INTERVAL_S
    from elastocal.formats.logformat import drive_topic

    log = tmp_path / "killed.mcap"
    child = subprocess.Popen([sys.executable, "-c", KILLED_CHILD, str(log)], stdout=subprocess.PIPE, text=True)
    try:
        seen = [int(child.stdout.readline()) for _ in range(100)]     # about a second of 1 kHz samples
        child.send_signal(signal.SIGKILL)
    finally:
        child.wait(30)
    with open(log, "rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())                         # what the audit found
    out = _cli(["repair", log, "--json"])
    assert out.returncode == 0, out.stderr.decode()
    summary = json.loads(out.stdout)
    copy = tmp_path / "killed.repaired.mcap"
    assert summary["out"] == str(copy) and not summary["was_complete"] and summary["ended"] is None
    assert summary["incomplete_steps"] == ["static/P1"]
    with open(copy, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        drive_t = [m.monotonic_ns for _, _, m in _decoded(reader.iter_messages(topics=[drive_topic(1)]))]
    assert abs(6 * len(drive_t) - summary["drive_samples"]) < 6     # a flush may fall between two joints
    lost_s = (seen[-1] - max(drive_t)) * 1e-9
    assert lost_s <= FLUSH_INTERVAL_S + 0.002, lost_s
    # the copy is an elastocal log like any other
    assert read_log(copy).complete and _cli(["repair", log]).returncode == 2          # exists: refused


class _Msg:
    def __init__(self, data):
        self.monotonic_ns = json.loads(data)["monotonic_ns"]


def _decoded(items):
    for schema, channel, message in items:
        yield schema, channel, _Msg(message.data)


# ------------------------------------------------------------------ 8: faults that pass
def test_a_beam_break_of_seconds_is_waited_out_and_logged(tmp_path, monkeypatch):
    """Reproduces audit item 8: a 3 s beam break ended the procedure (the tracker's DeviceFault).
    Now the measurements it cost are logged as gaps, the reading waits for the beam (at most
    BEAM_WAIT_S), the cell settles again and the reading is taken: the run completes."""
    from elastocal.acquisition.session import BEAM_WAIT_S, Session

    config = example_cell_config(can_channel="audit-beam", move_speed_rad_s=2.0)
    plan = parse_plan(_plan())
    with SimulatedCell(config) as sim:
        original = Session.event
        broken = []

        def event(self, kind, **fields):
            if kind == "hold_start" and fields.get("load") == "L1" and not broken:
                sim.tracker.break_beam(3.0)          # someone walks through the beam as the readings begin
                broken.append(time.monotonic())
            return original(self, kind, **fields)

        monkeypatch.setattr(Session, "event", event)
        ui = _Watching(sim)
        out = run_calibration(sim.config, plan, tmp_path / "beam.mcap", yes=True, ui=ui, world=sim.world)
    assert out.status == "completed" and broken
    events = read_log(tmp_path / "beam.mcap").events
    gaps = [e for e in events if e["kind"] == "gap" and e["device"] == "tracker"]
    assert gaps and all("beam broken" in g["text"] for g in gaps)
    back = [e for e in events if e["kind"] == "beam_back"]
    assert len(back) == 1 and 2.0 < back[0]["duration_s"] < BEAM_WAIT_S, back
    i = events.index(back[0])
    after = [e["kind"] for e in events[i + 1:] if e["kind"] != "gap"]
    assert after[:2] == ["settle", "reading"], after                     # settled again, then read
    assert next(e for e in events[i + 1:] if e["kind"] == "settle")["settled"] is True
    assert any("does not see marker R1" in m for m in ui.messages)
    readings = [e for e in events if e["kind"] == "reading" and e["load"] == "L1"]
    assert len(readings) == 1 and readings[0]["window_ns"][0] > back[0]["monotonic_ns"] - 10**9


# ------------------------------------------------------------------ 7: wrong answers to bad input
def test_check_refuses_an_invalid_sim_section(tmp_path, capsys):
    """Audit item 7: `check` exited 0 with an invalid [sim] section (it was never read)."""
    from elastocal.cli import main

    assert main(["sim", "static", "--out", str(tmp_path), "--poses", "6", "--loads", "2", "--repeats", "2"]) == 0
    assert main(["identify", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "static.csv"),
                 "--out", str(tmp_path / "cal.json")]) == 0
    capsys.readouterr()
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nrobot = "hh150"\n[sim]\nmove_speed_rad_s = -1.0\n')
    rc = main(["check", "--cell", str(cell), "--calibration", str(tmp_path / "cal.json"), "--static",
               str(tmp_path / "static.csv"), "--no-record"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"elastocal check: {cell}, column sim.move_speed_rad_s: must be > 0, got -1.0"], err


def test_export_refuses_a_log_that_lost_a_drives_messages(tmp_path, capsys):
    """Audit item 7: `export` of a log missing one drive's messages exited 0 with a blank column."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from elastocal.cli import main
    from elastocal.formats.logformat import drive_topic

    assert main(["sim", "static", "--out", str(tmp_path), "--poses", "4", "--loads", "1", "--repeats", "1"]) == 0
    capsys.readouterr()
    cut = tmp_path / "cut.mcap"
    with open(tmp_path / "log.mcap", "rb") as f, open(cut, "wb") as g:      # the same log without drive 3
        reader = make_reader(f)
        writer = Writer(g)
        header = reader.get_header()
        writer.start(profile=header.profile, library=header.library)
        ids: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if channel.topic == drive_topic(3):
                continue
            if channel.id not in ids:
                sid = writer.register_schema(schema.name, schema.encoding, schema.data) if schema else 0
                ids[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, sid)
            writer.add_message(ids[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()
    rc = main(["export", str(cut), "--out", str(tmp_path / "tables")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "drive(s) J3 have no sample in the window" in err[0], err
    assert not (tmp_path / "tables").exists()


def test_a_bad_can_channel_is_bad_input_everywhere(tmp_path):
    """Audit item 7: a bad CAN channel was exit 1 (a device error) and `sim serve` printed a
    traceback for it. Now it is one line naming the URL and the channel, exit 2."""
    text = example_cell_config().to_toml().replace("canopen://virtual/elastocal-sim", "canopen://udp_loopback/nonsense")
    cell = tmp_path / "cell.toml"
    cell.write_text(text)
    for args in (["devices", "--cell", cell, "--duration", "0.2"], ["sim", "serve", "--cell", cell, "--duration", "1"]):
        out = _cli(args, timeout=120)
        err = out.stderr.decode().strip().splitlines()
        assert out.returncode == 2 and len(err) == 1, out.stderr.decode()
        assert "cannot open CAN interface 'udp_loopback', channel 'nonsense'" in err[0] and "Traceback" not in err[0]


def test_errors_of_a_file_a_key_names_name_the_key(tmp_path, capsys):
    """Audit item 7: errors about the file a cell.toml key points to (robot, plan, history) named
    that file alone, not the key that named it."""
    from elastocal.cli import main

    base = example_cell_config().to_toml()
    plan = tmp_path / "plan.toml"
    plan.write_text(_plan())
    cases = [
        (base.replace('robot = "hh150"', 'robot = "missing/robot.toml"'),
         ["calibrate", "--plan", str(plan), "--out", str(tmp_path / "x.mcap"), "--sim", "--yes"], "cell.robot",
         "missing/robot.toml: cannot read"),
        (base.replace('robot = "hh150"', 'robot = "hh150"\nplan = "nope.toml"'),
         ["calibrate", "--out", str(tmp_path / "x.mcap"), "--sim", "--yes"], "cell.plan", "nope.toml: cannot read"),
        (base.replace('robot = "hh150"', 'robot = "hh150"\nhistory = "none/h.sqlite"'),
         ["check", "--sim", "--yes"], "cell.history", "none/h.sqlite: no history yet"),
        (base.replace('robot = "hh150"', 'robot = "hh150"\nhistory = "none/h.sqlite"'), ["history"], "cell.history",
         "none/h.sqlite: no history yet"),
    ]
    for text, args, key, what in cases:
        cell = tmp_path / "cell.toml"
        cell.write_text(text)
        rc = main([args[0], "--cell", str(cell), *args[1:]])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith(f"elastocal {args[0]}: {cell}, column {key}: "), err
        assert what in err[0], err
    assert not (tmp_path / "x.mcap").exists()


def test_a_corrupt_emscon_packet_is_said_in_the_trackers_words():
    """Audit item 7: an emScon corrupt packet leaked "'NoneType' object has no attribute 'unpack'"."""
    from elastocal.drivers.emscon_packets import HEADER, decode
    from elastocal.errors import ProtocolError

    for kind in (0, 3, 10):
        with pytest.raises(ProtocolError) as info:
            decode(HEADER.pack(16, kind) + bytes(range(8)), answers=True)
        assert "NoneType" not in str(info.value) and "is not one CESAPI can decode" in str(info.value)


def test_a_dropped_load_rig_connection_is_retried_and_named(tmp_path):
    """Audit item 7: a dropped load-rig connection was not retried, and its message did not say
    "load rig". Now it reconnects (the device policy's retries); when the rig is gone for good the
    error names it."""
    from elastocal.drivers.load_rig import open_load_rig
    from elastocal.errors import DeviceDisconnected
    from elastocal.sims.config import sim_config
    from elastocal.sims.load_rig import SimLoadRig, rig_identity
    from elastocal.sims.world import SimWorld

    config = example_cell_config()
    world = SimWorld.from_config(config.load_robot(), sim_config(config))
    rig = SimLoadRig(world)
    server = ModbusServerThread([rig.device], tcp=("127.0.0.1", 0), identity=rig_identity()).start()
    try:
        loads = open_load_rig(f"modbus+tcp://127.0.0.1:{server.port}?unit=1")
        server.drop_connections()
        time.sleep(0.2)
        loads.hang((0.0, 0.0, -300.0, 0.0, 0.0, 0.0))          # reconnected and written
        assert rig.hung == [(0.0, 0.0, -300.0, 0.0, 0.0, 0.0)]
    finally:
        server.close()
    with pytest.raises(DeviceDisconnected, match=r"^load rig modbus\+tcp://127\.0\.0\.1:\d+\?unit=1: .*after 3 attempts"):
        loads.hang(None)
    loads.close()
