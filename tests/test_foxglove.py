"""Foxglove-ready logs: wall-clock log times with the monotonic stamp kept, the cell
in Foxglove's well-known schemas (validated against Foxglove's published JSON
Schemas), every message of a procedure log valid against its channel's schema,
and logs written before the change still read."""

import io
import json
import time

import jsonschema
import numpy as np
import pinocchio as pin
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from elastocal.formats import logformat as lf
from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.export import load_log
from elastocal.acquisition.logreader import read_log
from elastocal.formats.plan import FrictionSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_procedures
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import identify_static
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.static import random_poses

TIMING = VirtualTiming(drive_rate_hz=200.0, tracker_rate_hz=100.0)
LOADS = (LoadSpec("L1", mass_kg=80.0), LoadSpec("L2", force_n=(600.0, -300.0, -400.0)))
SETTLE = SettleSpec(speed_rad_s=2e-3, spread_m=20e-6, window_s=0.15, timeout_s=20.0)
FOXGLOVE = {name: json.loads((lf.FOXGLOVE_SCHEMA_DIR / f"{name.split('.')[1]}.json").read_text())
            for name in set(lf.FOXGLOVE_TOPIC_SCHEMAS.values())}


@pytest.fixture(scope="module")
def robot():
    return bundled_robot()


@pytest.fixture(scope="module")
def demo_log(robot, tmp_path_factory):
    """A demo-like log: static poses under two loads and a UV/VU friction pair, through
    the procedure engine and the recorder, on the virtual cell."""
    poses = random_poses(robot, 5, np.random.default_rng(3))
    friction = (FrictionSpec("F1", start=(0.2, 0.3, -0.4, 0.3, 1.0, 0.2), end=(0.5, 0.55, -0.2, 0.6, 1.2, 0.5),
                             speeds_rad_s=(0.25,), loads=("0",), marker="R1"),)
    plan = parse_plan(plan_toml(poses=poses, loads=LOADS, markers=("R1", "R2", "R3"), repeats=2, reading_s=0.04,
                                speed_rad_s=0.8, settle=SETTLE, friction=friction), source="plan.toml")
    path = tmp_path_factory.mktemp("fox") / "demo.mcap"
    before = time.time_ns()
    out = run_procedures(VirtualCellIO(SimCell(robot, CellTruth()), seed=4, timing=TIMING), plan, path)
    assert out.status == "completed"
    return path, before, time.time_ns()


def messages(path):
    with open(path, "rb") as f:
        yield from make_reader(f).iter_messages(log_time_order=False)


def test_every_message_is_valid_against_its_channel_schema(demo_log):
    path, _, _ = demo_log
    validators, seen = {}, {}
    for schema, channel, message in messages(path):
        assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
        v = validators.get(schema.id)
        if v is None:
            doc = json.loads(schema.data)
            jsonschema.Draft202012Validator.check_schema(doc)
            v = validators[schema.id] = jsonschema.Draft202012Validator(doc)
        v.validate(json.loads(message.data))
        seen[channel.topic] = seen.get(channel.topic, 0) + 1
    six_drives = {lf.drive_topic(j) for j in range(1, 7)}          # the HH-150's
    assert set(lf.FOXGLOVE_TOPIC_SCHEMAS) <= set(seen) and six_drives <= set(seen)
    assert seen[lf.TOPIC_LOG] == seen[lf.TOPIC_EVENT]      # every procedure event is a Log line


def test_foxglove_channels_use_foxglove_schemas_by_their_well_known_names(demo_log):
    path, _, _ = demo_log
    checked = set()
    validators = {name: jsonschema.Draft202012Validator(doc) for name, doc in FOXGLOVE.items()}
    for doc in FOXGLOVE.values():
        jsonschema.Draft202012Validator.check_schema(doc)
    for schema, channel, message in messages(path):
        if channel.topic not in lf.FOXGLOVE_TOPIC_SCHEMAS:
            continue
        name = lf.FOXGLOVE_TOPIC_SCHEMAS[channel.topic]
        assert schema.name == name and json.loads(schema.data) == FOXGLOVE[name]
        assert FOXGLOVE[name]["title"] == name and "foxglove-sdk" in FOXGLOVE[name]["$comment"]
        validators[name].validate(json.loads(message.data))
        checked.add(channel.topic)
    assert checked == set(lf.FOXGLOVE_TOPIC_SCHEMAS)
    assert (lf.FOXGLOVE_SCHEMA_DIR / "LICENSE").read_text().startswith("MIT License")


def test_log_times_are_unix_ns_and_samples_keep_their_monotonic_stamp(demo_log):
    path, before, after = demo_log
    contents = read_log(path)
    session = contents.sessions[0]
    offset = session["unix_ns"] - session["monotonic_ns"]
    assert before <= session["unix_ns"] <= after        # the log opened during this run, on the wall clock
    drive_times = []
    for schema, channel, message in messages(path):
        # the virtual cell's clock runs faster than real time: within its minutes of this run's start
        assert session["unix_ns"] <= message.log_time <= session["unix_ns"] + 600 * 10**9, channel.topic
        payload = json.loads(message.data)
        if channel.topic in lf.DRIVE_TOPICS or channel.topic in (lf.TOPIC_TRACKER, lf.TOPIC_EVENT):
            assert message.log_time == payload["monotonic_ns"] + offset
        if channel.topic == "/drive/2":
            drive_times.append(payload["monotonic_ns"])
    # the reader keeps the monotonic stamps: reading windows and samples on one clock
    assert contents.drives[1].t_ns.tolist() == sorted(drive_times)
    assert all(e["t_ns"] == e["monotonic_ns"] for e in contents.events)


def _chain(transforms):
    """Compose a FrameTransforms message base -> joint6."""
    out = pin.SE3.Identity()
    for tf in transforms:
        r, t = tf["rotation"], tf["translation"]
        quat = pin.Quaternion(r["w"], r["x"], r["y"], r["z"])
        out = out * pin.SE3(quat.matrix(), np.array([t["x"], t["y"], t["z"]]))
    return out


def test_measured_frames_put_the_markers_where_the_model_does(demo_log, robot):
    """The composed joint frames and the scene's marker spheres give the model's marker
    positions at the drives' measured joint values (within the drive-to-grid time step)."""
    path, _, _ = demo_log
    contents = read_log(path)
    scene = frames = None
    checked = 0
    for _, channel, message in messages(path):
        payload = json.loads(message.data)
        if channel.topic == lf.TOPIC_ROBOT_SCENE and scene is None:
            scene = payload
        if channel.topic != lf.TOPIC_FRAMES or not payload["transforms"][0]["child_frame_id"].startswith("measured"):
            continue
        frames = payload["transforms"]
        assert [f["child_frame_id"] for f in frames] == [f"measured/joint{i}" for i in range(1, 7)]
        assert frames[0]["parent_frame_id"] == "base"
        t_mono = message.log_time - (contents.sessions[0]["unix_ns"] - contents.sessions[0]["monotonic_ns"])
        q = np.array([d.position_rad[np.searchsorted(d.t_ns, t_mono, side="right") - 1] for d in contents.drives])
        tool = next(e for e in scene["entities"] if e["id"] == "measured/tool")
        flange = _chain(frames)
        spheres = [s["pose"]["position"] for s in tool["spheres"]]
        got = np.array([flange.act(np.array([p["x"], p["y"], p["z"]])) for p in spheres])
        want = robot.positions(robot.theta(q), ["load_point", *robot.marker_names])
        np.testing.assert_allclose(got, want, atol=1e-9)
        checked += 1
    assert checked > 20


def test_tracker_readings_and_commanded_frames_are_published(demo_log, robot):
    path, _, _ = demo_log
    readings, commanded, levels = {}, 0, set()
    for _, channel, message in messages(path):
        payload = json.loads(message.data)
        if channel.topic == lf.TOPIC_TRACKER_SCENE:
            e = payload["entities"][0]
            readings[e["id"]] = e["spheres"][0]["pose"]["position"]
            assert e["frame_id"] == "base"
        elif channel.topic == lf.TOPIC_FRAMES and payload["transforms"][0]["child_frame_id"] == "commanded/joint1":
            commanded += 1
        elif channel.topic == lf.TOPIC_LOG:
            levels.add(payload["level"])
            assert payload["message"].split()[0].rstrip(":") in lf.SCHEMAS["elastocal.ProcedureEvent"]["properties"]["kind"]["enum"]
    assert set(readings) == {"tracker/R1", "tracker/R2", "tracker/R3"}
    assert commanded >= 5 * 2           # each pose and its hold
    assert levels == {2}                # a clean run: information only


def _old_style_copy(src, dst):
    """The log as elastocal wrote it before log times became Unix time: monotonic log
    times, no monotonic_ns fields, no Foxglove channels, no unix_ns in the session."""
    out = io.BytesIO()
    w = Writer(out)
    w.start(profile=lf.PROFILE, library="elastocal/0.1.0")
    schema_ids, channel_ids = {}, {}
    offset = None
    for schema, channel, message in messages(src):
        if channel.topic in lf.FOXGLOVE_TOPIC_SCHEMAS:
            continue
        if schema.name not in schema_ids:
            old = json.loads(schema.data)
            old["properties"].pop("monotonic_ns", None) if schema.name != "elastocal.Session" else None
            schema_ids[schema.name] = w.register_schema(schema.name, "jsonschema", json.dumps(old).encode())
        if channel.topic not in channel_ids:
            channel_ids[channel.topic] = w.register_channel(channel.topic, "json", schema_ids[schema.name])
        payload = json.loads(message.data)
        if channel.topic == lf.TOPIC_SESSION:
            offset = payload.pop("unix_ns") - payload["monotonic_ns"]
            payload.pop("log_clock")
        payload.pop("monotonic_ns", None) if channel.topic != lf.TOPIC_SESSION else None
        t = message.log_time - offset
        w.add_message(channel_ids[channel.topic], t, json.dumps(payload).encode(), t)
    w.finish()
    dst.write_bytes(out.getvalue())


def test_an_old_style_log_with_monotonic_log_times_still_reads(demo_log, robot, tmp_path):
    path, _, _ = demo_log
    old = tmp_path / "old.mcap"
    _old_style_copy(path, old)
    assert all("monotonic_ns" not in json.loads(m.data) or c.topic == lf.TOPIC_SESSION for _, c, m in messages(old))
    _, static_new, runs_new = load_log(path)
    _, static_old, runs_old = load_log(old)
    np.testing.assert_array_equal(static_old.xyz, static_new.xyz)
    np.testing.assert_array_equal(static_old.currents, static_new.currents)
    np.testing.assert_array_equal(static_old.t, static_new.t)
    np.testing.assert_array_equal(runs_old.q, runs_new.q)
    fit = identify_static(robot, static_old)
    np.testing.assert_allclose(fit.beta, identify_static(robot, static_new).beta)


def test_the_layout_in_docs_shows_the_log_s_channels(demo_log):
    import pathlib

    layout = json.loads((pathlib.Path(__file__).parents[1] / "docs" / "foxglove-layout.json").read_text())
    path, _, _ = demo_log
    topics = {c.topic for _, c, _ in messages(path)}
    panels = layout["configById"]
    assert set(panels["3D!cell"]["topics"]) <= topics and panels["3D!cell"]["followTf"] == "base"
    assert panels["RosOut!events"]["topicToRender"] == lf.TOPIC_LOG
    assert all(p["value"].split(".")[0] in topics for p in panels["Plot!currents"]["paths"])
