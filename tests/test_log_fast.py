"""The fast log replay reads what the streaming reader reads.

A finished log is read through mcap's summary, chunk by chunk, with only the topics
``read_log`` needs cut out of each chunk (acquisition/logreader.py). These tests hold it
to the streaming reader, which reads any log: the same messages chunk by chunk, the same
gathered contents to the bit, the same tables; and the files it must not take (truncated,
a second log appended, messages outside chunks, a corrupt chunk) go the streaming way or
fail with the same one-line error.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream
from mcap.writer import CompressionType, Writer

from elastocal.formats import logformat as lf
from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.export import load_log, tables_from_log
from elastocal.acquisition.logreader import LogReader, chunk_messages, read_log
from elastocal.formats.plan import FrictionSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_procedures
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.static import random_poses

ROBOT = bundled_robot()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A log of static poses and a friction pair recorded on the virtual cell (several chunks,
    Foxglove views included)."""
    poses = random_poses(ROBOT, 3, np.random.default_rng(4))
    plan = parse_plan(plan_toml(
        poses=poses, loads=(LoadSpec("L1", mass_kg=60.0),), markers=("R1", "R2"), repeats=2, reading_s=0.04,
        speed_rad_s=0.6, settle=SettleSpec(spread_m=20e-6, window_s=0.15),
        friction=(FrictionSpec("F1", start=(0.2, 0.3, -0.4, 0.3, 1.0, 0.2), end=(0.4, 0.5, -0.3, 0.5, 1.1, 0.4),
                               speeds_rad_s=(0.2,), marker="R2"),)))
    io = VirtualCellIO(SimCell(ROBOT, CellTruth()), seed=3,
                       timing=VirtualTiming(drive_rate_hz=250.0, tracker_rate_hz=250.0))
    log = tmp_path_factory.mktemp("fast") / "cal.mcap"
    assert run_procedures(io, plan, log).status == "completed"
    return log


def _streamed(path, monkeypatch):
    """read_log through the streaming reader only."""
    with monkeypatch.context() as m:
        m.setattr(LogReader, "_indexed_chunks", lambda self: None)
        return read_log(path)


def _same_contents(a, b) -> None:
    assert (a.complete, a.truncated, a.messages, a.trailing_bytes) == (b.complete, b.truncated, b.messages,
                                                                     b.trailing_bytes)
    assert (a.robot, a.cell, a.plan, a.sessions, a.events) == (b.robot, b.cell, b.plan, b.sessions, b.events)
    for da, db in zip(a.drives, b.drives, strict=True):
        for field in ("t_ns", "position_rad", "velocity_rad_s", "current_a"):
            np.testing.assert_array_equal(getattr(da, field), getattr(db, field))
    assert a.markers.keys() == b.markers.keys()
    for m in a.markers:
        np.testing.assert_array_equal(a.markers[m].t_ns, b.markers[m].t_ns)
        np.testing.assert_array_equal(a.markers[m].xyz, b.markers[m].xyz)


def test_chunk_messages_are_mcaps_own(recorded):
    chunks = 0
    with open(recorded, "rb") as f:
        for record in StreamReader(f, emit_chunks=True).records:
            if not isinstance(record, Chunk):
                continue
            chunks += 1
            theirs = [r for r in breakup_chunk(record, validate_crc=True) if isinstance(r, Message)]
            stream, length = get_chunk_data_stream(record, validate_crc=True)
            count, ours = chunk_messages(stream.read(length))
            assert count == len(theirs)
            for cid in {m.channel_id for m in theirs} | set(ours):
                expected = [(m.log_time, m.data) for m in theirs if m.channel_id == cid]
                assert list(zip(*ours[cid])) == expected
            wanted = {min(ours)}
            count_w, only = chunk_messages(stream_bytes := get_chunk_data_stream(record)[0].read(length), wanted)
            assert count_w == count and set(only) == wanted and only[min(ours)] == ours[min(ours)]
            assert len(stream_bytes) == length
    assert chunks > 3, "the fixture should span several chunks"


def test_a_finished_log_is_read_by_its_summary_and_equals_the_stream(recorded, monkeypatch):
    reader = LogReader(recorded)
    assert reader._indexed_chunks() is not None      # the fast way is taken for a finished log
    fast, streamed = read_log(recorded), _streamed(recorded, monkeypatch)
    assert fast.complete and not fast.truncated and fast.trailing_bytes == 0
    _same_contents(fast, streamed)
    robot_f, static_f, runs_f = tables_from_log(fast)
    robot_s, static_s, runs_s = tables_from_log(streamed)
    for a, b in ((static_f, static_s), (runs_f, runs_s)):
        for field in ("q", "currents", "xyz", "t", "wrench"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_only_the_topics_it_gathers_are_decoded(recorded, tmp_path):
    """A payload that is not JSON on a Foxglove view (not gathered) does not stop the replay;
    on a drive topic it is the one-line error it always was."""
    for topic, fails in ((lf.TOPIC_FRAMES, False), (lf.drive_topic(2), True)):
        path = tmp_path / f"{topic.strip('/').replace('/', '_')}.mcap"
        _copy_with_bad_payload(recorded, path, topic)
        if fails:
            with pytest.raises(InputError, match=f"{topic} at log time .* is not JSON"):
                read_log(path)
        else:
            assert read_log(path).messages == read_log(recorded).messages


def _copy_with_bad_payload(src, dst, topic: str) -> None:
    """``src`` written again with the first payload on ``topic`` replaced by a non-JSON one."""
    reader = LogReader(src)
    with open(dst, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema("json", "jsonschema", b"{}")
        channel_ids, spoiled = {}, False
        for record_topic, m in reader.raw_messages():
            if m.channel_id not in channel_ids:
                channel_ids[m.channel_id] = w.register_channel(record_topic, "json", sid)
            data = m.data
            if record_topic == topic and not spoiled:
                data, spoiled = b"{not json", True
            w.add_message(channel_ids[m.channel_id], m.log_time, data, m.publish_time)
        w.finish()
    assert spoiled


def test_files_the_summary_cannot_vouch_for_are_streamed(recorded, tmp_path, monkeypatch):
    data = recorded.read_bytes()
    whole = read_log(recorded)
    # truncated: no closing magic
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    assert LogReader(cut)._indexed_chunks() is None
    got = read_log(cut)
    assert got.truncated and not got.complete and got.messages < whole.messages
    # a second copy appended: the summary at the end is not this file's
    twice = tmp_path / "twice.mcap"
    twice.write_bytes(data + data)
    assert LogReader(twice)._indexed_chunks() is None
    got = read_log(twice)
    assert got.trailing_bytes == len(data) and got.messages == whole.messages
    _same_contents(got, _streamed(twice, monkeypatch))


def test_messages_outside_chunks_are_streamed(tmp_path):
    """A log written without chunks has no chunk index: read as a stream, every message."""
    path = tmp_path / "unchunked.mcap"
    with open(path, "wb") as f:
        w = Writer(f, use_chunking=False)
        w.start()
        sid = w.register_schema("elastocal.Session", "jsonschema", b"{}")
        cid = w.register_channel(lf.TOPIC_SESSION, "json", sid)
        w.add_message(cid, 5, json.dumps({"format": lf.LOG_FORMAT, "software": "0", "started_utc": "x",
                                          "monotonic_ns": 5, "unix_ns": 5, "log_clock": "unix",
                                          "resumed_from": None}).encode(), 5)
        w.finish()
    assert LogReader(path)._indexed_chunks() is None
    got = read_log(path)
    assert got.complete and got.messages == 1 and len(got.sessions) == 1
    with pytest.raises(InputError, match="no robot description"):
        load_log(path)


def test_a_corrupt_chunk_is_the_same_one_line_error(recorded, tmp_path):
    data = bytearray(recorded.read_bytes())
    reader = LogReader(recorded)
    chunks = reader._indexed_chunks()
    ci = chunks[len(chunks) // 2]
    start = ci.chunk_start_offset + ci.chunk_length - 40      # inside the compressed records
    data[start:start + 16] = bytes(16)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    assert LogReader(bad)._indexed_chunks() is not None       # the summary is intact
    with pytest.raises(InputError, match=f"(corrupt|cannot decompress) chunk before byte {ci.chunk_start_offset + ci.chunk_length}"):
        read_log(bad)
