"""The MCAP recorder: schemas once, JSON channels Foxglove opens, raw timestamps,
and logs that survive a kill at any moment (byte-level truncation, and a real
SIGKILL of a subprocess calibrating the simulated cell through the drivers)."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from elastocal.formats import logformat as lf
from elastocal.acquisition.export import load_log
from elastocal.acquisition.logreader import LogReader, read_log
from elastocal.acquisition.recorder import Recorder
from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot

ROBOT = bundled_robot()


class Clock:
    def __init__(self):
        self.t = 5_000_000_000

    def __call__(self):
        self.t += 1000
        return self.t


def small_log(path, *, samples=40, events=6):
    clock = Clock()
    with Recorder(path, clock=clock, chunk_size=4096) as rec:
        rec.document("robot", ROBOT.name, ROBOT.to_toml())
        rec.document("cell", "test cell", "[cell]\nname = 'test cell'\n")
        rec.document("plan", "p", "name = 'p'\n")
        for k in range(events):
            rec.event("step_start", step=k, step_id=f"s/{k}")
            for n in range(samples):
                t = 7_000_000_000 + (k * samples + n) * 1_000_000
                for j in range(1, 7):
                    rec.drive_sample(j, t, 0.1 * j, 0.0, 1.5 * j, 0x27)
                rec.tracker_sample(t, "R1", (1.0, 2.0 + n * 1e-6, 3.0))
            rec.event("step_done", step=k, step_id=f"s/{k}")
    return path


def test_schemas_registered_once_and_channels_are_json(tmp_path):
    path = small_log(tmp_path / "log.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert reader.get_header().profile == lf.PROFILE
        names = [s.name for s in summary.schemas.values()]
        assert sorted(names) == sorted(set(names))   # each schema once
        assert set(names) == {"elastocal.Session", "elastocal.Document", "elastocal.DriveSample",
                              "elastocal.TrackerSample", "elastocal.ProcedureEvent",
                              "foxglove.FrameTransforms", "foxglove.SceneUpdate", "foxglove.Log"}
        for s in summary.schemas.values():
            assert s.encoding == "jsonschema"
            doc = json.loads(s.data)
            assert doc["type"] == "object" and doc["title"] == s.name
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {lf.TOPIC_SESSION, lf.TOPIC_ROBOT, lf.TOPIC_CELL, lf.TOPIC_PLAN, lf.TOPIC_EVENT,
                               lf.TOPIC_TRACKER, *(lf.drive_topic(j) for j in range(1, 7)), *lf.FOXGLOVE_TOPIC_SCHEMAS}
        assert all(c.message_encoding == "json" for c in topics.values())
        counts = summary.statistics.channel_message_counts
        raw = sum(n for cid, n in counts.items() if summary.channels[cid].topic not in lf.FOXGLOVE_TOPIC_SCHEMAS)
        assert raw == 3 + 1 + 6 * 2 + 6 * 40 * 7
        # Foxglove's channels: one log line per event, measured frames every 100 ms of the 240 ms of samples
        fox = {summary.channels[cid].topic: n for cid, n in counts.items()
               if summary.channels[cid].topic in lf.FOXGLOVE_TOPIC_SCHEMAS}
        assert fox[lf.TOPIC_LOG] == 6 * 2 and fox[lf.TOPIC_FRAMES] == 3
        meta = list(reader.iter_metadata())
        assert meta[0].name == "elastocal" and meta[0].metadata["format"] == lf.LOG_FORMAT
        # every message decodes with the mcap reader and carries only fields its schema names
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            payload = json.loads(message.data)
            spec = json.loads(schema.data)
            assert set(spec["required"]) <= set(payload), (channel.topic, payload)
            assert set(payload) <= set(spec["properties"]), (channel.topic, payload)
    # the session, robot, cell and plan come first, in this order
    order = [m.channel_id for m in StreamReader(str(path)).records if isinstance(m, Message)][:4]
    assert [topics_by_id(path)[c] for c in order] == [lf.TOPIC_SESSION, lf.TOPIC_ROBOT, lf.TOPIC_CELL, lf.TOPIC_PLAN]


def topics_by_id(path):
    with open(path, "rb") as f:
        return {c.id: c.topic for c in make_reader(f).get_summary().channels.values()}


def test_samples_keep_their_acquisition_time_and_events_the_clock(tmp_path):
    path = small_log(tmp_path / "log.mcap", samples=3, events=1)
    contents = read_log(path)
    assert contents.drives[2].t_ns.tolist() == [7_000_000_000, 7_001_000_000, 7_002_000_000]
    assert contents.drives[2].current_a.tolist() == [4.5, 4.5, 4.5]
    assert contents.markers["R1"].xyz[1].tolist() == [1.0, 2.000001, 3.0]
    events = [(e["kind"], e["t_ns"]) for e in contents.events]
    assert events[0][0] == "step_start" and events[1][0] == "step_done"
    assert all(isinstance(t, int) for _, t in events) and events[1][1] > events[0][1]


def test_recorder_refuses_to_overwrite_and_rejects_unknown_topics(tmp_path):
    path = small_log(tmp_path / "log.mcap", samples=1, events=1)
    with pytest.raises(InputError, match="already exists"):
        Recorder(path)
    with Recorder(tmp_path / "other.mcap") as rec:
        with pytest.raises(InputError, match="unknown topic"):
            rec.copy("/camera", 1, 1, b"{}")
        with pytest.raises(ValueError):
            rec.drive_sample(65, 1, 0.0, 0.0, 0.0)     # beyond the log's joints


@pytest.mark.heavy
def test_a_log_cut_at_any_byte_reads_up_to_the_cut(tmp_path):
    full = small_log(tmp_path / "log.mcap", samples=20, events=5)
    data = full.read_bytes()
    reference = [(t, m.log_time, m.data) for t, m in LogReader(full).raw_messages()]
    first_ok = None
    previous = 0
    cut_path = tmp_path / "cut.mcap"
    for cut in list(range(0, len(data), 173)) + [len(data) - 1]:
        cut_path.write_bytes(data[:cut])
        try:
            contents = read_log(cut_path)
        except InputError as exc:
            # before the first chunk (session + documents) there is nothing to read
            assert first_ok is None, (cut, exc)
            continue
        first_ok = first_ok if first_ok is not None else cut
        reader = LogReader(cut_path)
        got = [(t, m.log_time, m.data) for t, m in reader.raw_messages()]
        assert got == reference[:len(got)]       # a prefix of the complete log, nothing garbled
        assert len(got) >= previous
        assert reader.truncated and not reader.complete
        previous = len(got)
        assert contents.messages == len(got)
    assert first_ok is not None and previous > 0.8 * len(reference)
    assert read_log(full).complete


RECORD_SCRIPT = textwrap.dedent("""
    import sys
    import numpy as np
    from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
    from elastocal.acquisition.procedures import run_calibration
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.serve import SimulatedCell, example_cell_config
    from elastocal.sims.static import random_poses

    robot = bundled_robot()
    poses = random_poses(robot, 30, np.random.default_rng(4))
    loads = (LoadSpec("L1", mass_kg=110.0), LoadSpec("L2", force_n=(650.0, -300.0, -400.0)))
    plan = parse_plan(plan_toml(poses=poses, loads=loads, markers=("R1", "R2"), repeats=2,
                                reading_s=0.04, settle=SettleSpec(window_s=0.1, timeout_s=10.0)))
    config = example_cell_config(can_channel="issue4-kill", move_speed_rad_s=2.0)
    with SimulatedCell(config) as sim:
        run_calibration(sim.config, plan, sys.argv[1], yes=True, world=sim.world)
""")


def test_killed_recorder_leaves_a_log_that_export_and_identify_read(tmp_path):
    log = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", RECORD_SCRIPT, str(log)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 90
        done = ()
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.5)
            if log.exists():
                try:
                    done = read_log(log).completed_steps
                except InputError:
                    continue   # nothing complete yet
                if len(done) >= 3:
                    break
        assert proc.poll() is None, proc.stderr.read().decode()
        assert len(done) >= 3
        time.sleep(1.3)  # somewhere inside the next pose
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=10)
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    contents = read_log(log)
    assert not contents.complete                  # no summary: the writer never finished
    assert contents.end_status is None
    assert len(contents.completed_steps) >= 3
    robot, static, runs = load_log(log)
    assert runs is None
    assert sorted(set(static.pose)) == sorted(p.split("/")[1] for p in contents.completed_steps)
    out = tmp_path / "export"
    assert main(["export", str(log), "--out", str(out)]) == 0
    assert (out / "static.csv").exists() and (out / "robot.toml").exists() and (out / "plan.toml").exists()
    assert main(["identify", str(log), "--json"]) == 0
