"""Read an elastocal MCAP log back: robot, static table, run table (formats.md §2-3).

:class:`LogReader` walks the file with mcap's streaming reader and stops cleanly
where a killed recorder left it (a truncated record ends the walk; the complete
chunks before it are read). :func:`read_log` gathers the samples and procedure
events; :func:`load_log` turns them into the tables the identification uses;
:func:`export_log` writes them as files. Tables are built from raw samples by
fixed rules (docs/log-format.md), so identifying from the log and from the
exported tables gives the same result.

Only steps whose ``step_done`` event is in the log contribute rows: a pose
interrupted between its unloaded reference and its loads is left out whole.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import operator
import os
import pathlib
import struct
from dataclasses import dataclass
from typing import IO, Iterator

import numpy as np
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk

from elastocal.acquisition import logformat as lf
from elastocal.errors import InputError
from elastocal.identify.robot import Robot, parse_robot
from elastocal.identify.tables import (
    RunTable,
    StaticTable,
    run_table_from_arrays,
    static_table_from_arrays,
    write_run_table,
    write_static_table,
)


class _ExactReads:
    """File wrapper for StreamReader: a short read (the file ends inside a
    record) raises :class:`mcap.exceptions.EndOfFile` instead of returning a
    partial record, so a truncated log ends cleanly at its last whole record."""

    def __init__(self, raw: IO[bytes]) -> None:
        self._raw = raw
        self.offset = 0

    def read(self, n: int = -1) -> bytes:
        data = self._raw.read(n)
        if n is not None and n >= 0 and len(data) < n:
            raise EndOfFile()
        self.offset += len(data)
        return data


class _Position:
    """A complete file, read directly (no per-read check needed)."""

    def __init__(self, raw: IO[bytes]) -> None:
        self._raw = raw
        self.read = raw.read

    @property
    def offset(self) -> int:
        return self._raw.tell()


def _ends_with_magic(f: IO[bytes]) -> bool:
    from mcap.writer import MCAP0_MAGIC

    f.seek(0, 2)
    size = f.tell()
    if size < 2 * len(MCAP0_MAGIC):
        f.seek(0)
        return False
    f.seek(size - len(MCAP0_MAGIC))
    tail = f.read(len(MCAP0_MAGIC))
    f.seek(0)
    return tail == MCAP0_MAGIC


class LogReader:
    """Messages of a (possibly truncated) elastocal log, in file order.

    After iterating, ``complete`` tells whether the file ended with its MCAP
    footer and closing magic, and ``truncated`` whether it ended inside a
    record (a killed writer).
    """

    def __init__(self, path: str | pathlib.Path) -> None:
        self.path = pathlib.Path(path)
        self.complete = False
        self.truncated = False
        self.trailing_bytes = 0
        self.end_offset = 0
        self.topics: dict[int, str] = {}
        self.schemas: dict[int, str] = {}

    def _records(self) -> Iterator[object]:
        try:
            f = open(self.path, "rb")
        except OSError as exc:
            raise InputError(f"cannot read: {exc.strerror}", source=str(self.path)) from None
        with f:
            # a finished log ends with the MCAP magic: read it directly; otherwise
            # every read is checked so that a truncated record ends the walk
            stream = _ExactReads(f) if not _ends_with_magic(f) else _Position(f)
            reader = StreamReader(stream, emit_chunks=True, record_size_limit=1 << 30)  # type: ignore[arg-type]
            it = reader.records
            while True:
                try:
                    record = next(it)
                except StopIteration:  # the footer and the closing magic were read
                    self.complete = True
                    # bytes after the closing magic: garbage, or a second copy appended to the file
                    self.trailing_bytes = max(os.fstat(f.fileno()).st_size - stream.offset, 0)
                    return
                except EndOfFile:
                    if stream.offset == 0:
                        raise InputError("empty file; not an MCAP log", source=str(self.path)) from None
                    self.truncated = True
                    return
                except InvalidMagic:
                    if stream.offset <= 8:
                        raise InputError("not an MCAP file", source=str(self.path)) from None
                    raise InputError("the MCAP footer is not followed by the closing magic; corrupt file",
                                     source=str(self.path)) from None
                except (McapError, struct.error, UnicodeDecodeError) as exc:
                    raise InputError(f"corrupt MCAP record near byte {stream.offset}: {exc}",
                                     source=str(self.path)) from None
                self.end_offset = stream.offset
                yield record

    def _expand(self, record: object) -> list[Message]:
        """Messages of one top-level record; schemas and channels are remembered."""
        if isinstance(record, Chunk):
            try:
                inner = breakup_chunk(record, validate_crc=True)
            except CRCValidationError as exc:
                raise InputError(f"corrupt chunk before byte {self.end_offset}: {exc}", source=str(self.path)) from None
            except Exception as exc:  # zstandard raises its own error type on bad data
                raise InputError(f"cannot decompress chunk before byte {self.end_offset}: {exc}",
                                 source=str(self.path)) from None
            out = []
            for r in inner:
                if isinstance(r, Message):
                    out.append(r)
                else:
                    self._remember(r)
            return out
        if isinstance(record, Message):
            return [record]
        self._remember(record)
        return []

    def _remember(self, record: object) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record.name
        elif isinstance(record, Channel):
            self.topics[record.id] = record.topic

    def _topic(self, message: Message) -> str:
        return self._topic_of(message.channel_id)

    def raw_messages(self) -> Iterator[tuple[str, Message]]:
        """(topic, message) pairs with undecoded payloads."""
        for record in self._records():
            for m in self._expand(record):
                yield self._topic(m), m

    def batches(self) -> Iterator[list[tuple[str, int, dict]]]:
        """Decoded messages, one list per chunk: (topic, log_time_ns, payload).

        Each chunk's JSON payloads are decoded in one call; a payload that is
        not JSON raises :class:`InputError` naming its topic and time.
        """
        for record in self._records():
            msgs = self._expand(record)
            if not msgs:
                continue
            try:
                values = json.loads(b"[" + b",".join([m.data for m in msgs]) + b"]")
            except ValueError:
                values = [self._decode_one(m) for m in msgs]
            yield [(self._topic(m), m.log_time, v) for m, v in zip(msgs, values)]

    def _decode_one(self, m: Message) -> dict:
        try:
            value = json.loads(m.data)
        except ValueError as exc:
            raise InputError(f"message on {self._topic(m)} at log time {m.log_time} ns is not JSON: {exc}",
                             source=str(self.path)) from None
        return value

    def grouped(self) -> Iterator[dict[str, tuple[list[int], list]]]:
        """Decoded messages, one dict per chunk: topic -> (log times, payloads),
        each in file order. The fastest way through a log: one JSON decode per
        topic and chunk."""
        for record in self._records():
            msgs = self._expand(record)
            if not msgs:
                continue
            by_channel: dict[int, tuple[list[int], list[bytes]]] = {}
            for m in msgs:
                entry = by_channel.get(m.channel_id)
                if entry is None:
                    entry = by_channel[m.channel_id] = ([], [])
                entry[0].append(m.log_time)
                entry[1].append(m.data)
            out = {}
            for cid, (times, datas) in by_channel.items():
                topic = self._topic_of(cid)
                try:
                    values = json.loads(b"[" + b",".join(datas) + b"]")
                except ValueError:
                    values = [self._decode_data(topic, t, d) for t, d in zip(times, datas)]
                out[topic] = (times, values)
            yield out

    def _topic_of(self, channel_id: int) -> str:
        try:
            return self.topics[channel_id]
        except KeyError:
            raise InputError(f"message on channel {channel_id} before its channel record",
                             source=str(self.path)) from None

    def _decode_data(self, topic: str, log_time: int, data: bytes) -> dict:
        try:
            return json.loads(data)
        except ValueError as exc:
            raise InputError(f"message on {topic} at log time {log_time} ns is not JSON: {exc}",
                             source=str(self.path)) from None

    def messages(self) -> Iterator[tuple[str, int, dict]]:
        """Decoded messages one by one: (topic, log_time_ns, payload)."""
        for batch in self.batches():
            yield from batch


# ------------------------------------------------------------------ contents
@dataclass(frozen=True)
class Document:
    kind: str
    name: str
    text: str
    sha256: str
    path: str | None


@dataclass(frozen=True, eq=False)
class DriveSamples:
    """Samples of one drive, in time order."""

    t_ns: np.ndarray            # (n,) int64: session * SEGMENT_NS + acquisition time
    position_rad: np.ndarray    # (n,)
    velocity_rad_s: np.ndarray  # (n,) NaN when not given
    current_a: np.ndarray       # (n,) NaN when not given


@dataclass(frozen=True, eq=False)
class TrackerSamples:
    """Samples of one marker, in time order."""

    t_ns: np.ndarray  # (n,) int64: session * SEGMENT_NS + acquisition time
    xyz: np.ndarray   # (n, 3) m


@dataclass(frozen=True, eq=False)
class LogContents:
    """Everything in a log, gathered: documents, events and raw samples."""

    path: str
    complete: bool
    truncated: bool
    messages: int
    robot: Document | None
    cell: Document | None
    plan: Document | None
    sessions: tuple[dict, ...]
    events: tuple[dict, ...]       # each with "t_ns"
    drives: tuple[DriveSamples, ...]  # 6, joint 1..6
    markers: dict[str, TrackerSamples]
    trailing_bytes: int = 0        # bytes after the MCAP closing magic (ignored)

    @property
    def completed_steps(self) -> tuple[str, ...]:
        """Ids of the steps whose ``step_done`` event is in the log, in order."""
        return tuple(e["step_id"] for e in self.events if e["kind"] == "step_done")

    @property
    def started_steps(self) -> tuple[str, ...]:
        return tuple(e["step_id"] for e in self.events if e["kind"] == "step_start")

    @property
    def incomplete_steps(self) -> tuple[str, ...]:
        done = set(self.completed_steps)
        return tuple(dict.fromkeys(s for s in self.started_steps if s not in done))

    @property
    def end_status(self) -> str | None:
        """``completed``, ``aborted`` or ``failed`` from the last procedure_end, None if absent."""
        ends = [e for e in self.events if e["kind"] == "procedure_end"]
        return ends[-1].get("status") if ends else None


def _document(payload: dict, source: str) -> Document:
    try:
        doc = Document(kind=str(payload["kind"]), name=str(payload["name"]), text=str(payload["text"]),
                       sha256=str(payload["sha256"]), path=payload.get("path"))
    except KeyError as exc:
        raise InputError(f"configuration message lacks {exc.args[0]!r}", source=source) from None
    if hashlib.sha256(doc.text.encode()).hexdigest() != doc.sha256:
        raise InputError(f"the recorded {doc.kind} document does not match its sha256", source=source)
    return doc


def _check_messages(topic: str, times: list[int], values: list, source: str) -> None:
    """Documents, sessions and events follow their schema (logformat.SCHEMAS): one line naming
    the topic, the log time and the field, instead of a KeyError further on."""
    for t, v in zip(times, values):
        why = lf.message_error(topic, v)
        if why is not None:
            raise InputError(f"the message on {topic} at log time {t} ns is not a valid "
                             f"{lf.TOPIC_SCHEMAS[topic]}: {why}", source=source)
        if topic == lf.TOPIC_EVENT and "window_ns" in v and v["window_ns"][0] > v["window_ns"][1]:
            raise InputError(f"the {v['kind']} event at log time {t} ns has a window that ends before it starts",
                             source=source)


def read_log(path: str | pathlib.Path) -> LogContents:
    """Gather a log's documents, events and samples (tolerates a truncated file)."""
    reader = LogReader(path)
    source = str(reader.path)
    docs: dict[str, Document] = {}
    sessions: list[dict] = []
    events: list[dict] = []
    drive_parts: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(lf.N_JOINTS)]
    tracker_parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    drive_index = {t: j for j, t in enumerate(lf.DRIVE_TOPICS)}
    n_messages = 0
    get_drive = operator.itemgetter("position_rad", "velocity_rad_s", "current_a")
    get_xyz = operator.itemgetter("x", "y", "z")
    segment = 0
    for groups in reader.grouped():
        offset = segment * SEGMENT_NS
        resumes = 0
        for topic, (log_times, values) in groups.items():
            n_messages += len(log_times)
            times = _monotonic(log_times, values)
            if topic in lf.CHECKED_TOPICS:
                _check_messages(topic, log_times, values, source)
            j = drive_index.get(topic)
            if j is not None:
                try:
                    vals = np.array(list(map(get_drive, values)), dtype=float)
                except (KeyError, TypeError, ValueError):
                    raise InputError(f"a message on {topic} is not a drive sample", source=source) from None
                drive_parts[j].append((_keys(times, offset, source), vals))
            elif topic == lf.TOPIC_TRACKER:
                try:
                    markers = [v["marker"] for v in values]
                    xyz = np.array(list(map(get_xyz, values)), dtype=float)
                    if not all(isinstance(m, str) for m in markers):
                        raise TypeError("marker")
                except (KeyError, TypeError, ValueError):
                    raise InputError(f"a message on {topic} is not a tracker sample", source=source) from None
                t = _keys(times, offset, source)
                if len(set(markers)) == 1:
                    tracker_parts.setdefault(markers[0], []).append((t, xyz))
                else:
                    names = np.array(markers)
                    for m in dict.fromkeys(markers):
                        sel = names == m
                        tracker_parts.setdefault(m, []).append((t[sel], xyz[sel]))
            elif topic == lf.TOPIC_EVENT:
                events.extend({**v, "t_ns": t, "segment": segment} for t, v in zip(times, values))
                resumes += sum(1 for v in values if v.get("kind") == "resume")
            elif topic in (lf.TOPIC_ROBOT, lf.TOPIC_CELL, lf.TOPIC_PLAN):
                for v in values:
                    doc = _document(v, source)
                    docs.setdefault(doc.kind, doc)
            elif topic == lf.TOPIC_SESSION:
                for v in values:
                    if v.get("format") != lf.LOG_FORMAT:
                        raise InputError(f"log format {v.get('format')!r} is not {lf.LOG_FORMAT}", source=source)
                    sessions.append(v)
        segment += resumes
    if n_messages == 0 or not sessions:
        raise InputError("no elastocal session in the log (not an elastocal log, or killed before "
                         "its first message was written)", source=source)

    def _sorted(parts, width):
        if not parts:
            return np.zeros(0, dtype=np.int64), np.zeros((0, width))
        t = np.concatenate([p[0] for p in parts])
        vals = np.concatenate([p[1] for p in parts])
        if np.any(np.diff(t) < 0):
            order = np.argsort(t, kind="stable")
            t, vals = t[order], vals[order]
        return t, vals

    drives_out = []
    for parts in drive_parts:
        t, vals = _sorted(parts, 3)
        drives_out.append(DriveSamples(t, vals[:, 0], vals[:, 1], vals[:, 2]))
    markers_out = {}
    for m, parts in tracker_parts.items():
        t, vals = _sorted(parts, 3)
        markers_out[m] = TrackerSamples(t, vals)
    return LogContents(path=source, complete=reader.complete, truncated=reader.truncated, messages=n_messages,
                       robot=docs.get("robot"), cell=docs.get("cell"), plan=docs.get("plan"),
                       sessions=tuple(sessions), events=tuple(events), drives=tuple(drives_out),
                       markers=markers_out, trailing_bytes=reader.trailing_bytes)


# ------------------------------------------------------------------ tables
#: samples of the k-th recording session of a log (a resumed log holds several,
#: possibly on clocks restarted by a reboot) are kept at k * SEGMENT_NS + t, so
#: reading windows only ever see samples of their own session
SEGMENT_NS = 10**17
MAX_SEGMENTS = 90


def _monotonic(log_times: list[int], values: list) -> list[int]:
    """Acquisition times on the monotonic clock: each message's ``monotonic_ns``, or its
    log time in logs written before log times became Unix time (docs/log-format.md)."""
    if not values or not isinstance(values[0], dict) or "monotonic_ns" not in values[0]:
        if not any(isinstance(v, dict) and "monotonic_ns" in v for v in values):
            return log_times
    return [v.get("monotonic_ns", t) if isinstance(v, dict) else t for t, v in zip(log_times, values)]


def _keys(times: list[int], offset: int, source: str) -> np.ndarray:
    t = np.array(times, dtype=np.int64)
    if len(t) and (t.max() >= SEGMENT_NS or t.min() < 0):
        raise InputError(f"sample times beyond {SEGMENT_NS} ns (3 years) of the log clock", source=source)
    if offset >= MAX_SEGMENTS * SEGMENT_NS:
        raise InputError(f"more than {MAX_SEGMENTS} resumed sessions in one log", source=source)
    return t + offset


def _key(event: dict, t_ns: int) -> int:
    return int(event["segment"]) * SEGMENT_NS + int(t_ns)


def _window(t_ns: np.ndarray, start: int, end: int) -> slice:
    return slice(int(np.searchsorted(t_ns, start, side="left")), int(np.searchsorted(t_ns, end, side="right")))


def _time_origin(contents: LogContents) -> int:
    """Origin of the ``t`` columns: the first ``procedure_start`` of the log (a
    resumed log keeps the one of the log it continues)."""
    for e in contents.events:
        if e["kind"] == "procedure_start":
            return int(e["t_ns"])
    return min(e["t_ns"] for e in contents.events) if contents.events else 0


def _wrench(value) -> list[float]:
    if value is None:
        return [float("nan")] * 6
    return [float(x) for x in value]


@dataclass(frozen=True)
class StaticReading:
    """One ``reading`` event of a completed static step and what the log holds for it."""

    pose: str
    load: str
    marker: str
    window: tuple[int, int]         # sample keys (session * SEGMENT_NS + monotonic ns)
    t_s: float                      # the window's middle, seconds from the log's time origin
    q: tuple[float, ...]            # commanded pose [rad]
    wrench: tuple[float, ...]       # nominal load [N, N·m], NaN when unknown
    currents: tuple[float, ...]     # mean current of each drive over the window [A], NaN without samples
    wall_s: tuple[float, float]     # the window on the UTC clock of its session (epoch seconds)


def static_readings(contents: LogContents) -> list[StaticReading]:
    """The ``reading`` events of the log's completed static steps, in log order (the rows
    :func:`static_table_from_log` makes, without the tracker's positions)."""
    done = set(contents.completed_steps)
    origin = _time_origin(contents)
    out = []
    for e in contents.events:
        if e["kind"] != "reading" or e.get("step_id") not in done:
            continue
        start, end = (_key(e, v) for v in e["window_ns"])
        cur = []
        for d in contents.drives:
            dsl = _window(d.t_ns, start, end)
            cur.append(float(np.mean(d.current_a[dsl])) if dsl.stop > dsl.start else float("nan"))
        session = contents.sessions[min(int(e["segment"]), len(contents.sessions) - 1)]
        wall0 = _utc_seconds(session["started_utc"], contents.path) - int(session["monotonic_ns"]) * 1e-9
        out.append(StaticReading(
            pose=str(e["pose"]), load=str(e["load"]), marker=str(e["marker"]), window=(start, end),
            t_s=((start + end) // 2 - e["segment"] * SEGMENT_NS - origin) * 1e-9,
            q=tuple(float(v) for v in e["q"]), wrench=tuple(_wrench(e.get("wrench"))), currents=tuple(cur),
            wall_s=tuple(wall0 + int(v) * 1e-9 for v in e["window_ns"])))
    return out


def _utc_seconds(text: str, source: str) -> float:
    try:
        dt = datetime.datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"session start {text!r} is not an ISO 8601 time", source=source) from None
    return (dt if dt.tzinfo else dt.replace(tzinfo=datetime.timezone.utc)).timestamp()


def static_table_from_log(contents: LogContents, robot: Robot | None = None) -> StaticTable | None:
    """The static deflection table of the log's completed static steps, or None.

    One row per ``reading`` event: the mean tracker position of its marker and
    the mean current of each drive over the reading's window; ``t`` is the
    window's middle in seconds from the log's first event; ``q`` and the wrench
    are the commanded pose and the nominal load the event names.
    """
    readings = static_readings(contents)
    if not readings:
        return None
    pose, load, t, q, wrench, currents, marker, xyz = [], [], [], [], [], [], [], []
    for r in readings:
        start, end = r.window
        samples = contents.markers.get(r.marker)
        sl = _window(samples.t_ns, start, end) if samples is not None else slice(0, 0)
        if samples is None or sl.stop <= sl.start:
            raise InputError(f"reading of marker {r.marker} at pose {r.pose} load {r.load} has no tracker sample "
                             f"in its window", source=contents.path)
        xyz.append(samples.xyz[sl].mean(axis=0))
        currents.append(list(r.currents))
        pose.append(r.pose)
        load.append(r.load)
        t.append(r.t_s)
        q.append(list(r.q))
        wrench.append(list(r.wrench))
        marker.append(r.marker)
    try:
        return static_table_from_arrays(pose=pose, load=load, t=t, q=q, wrench=wrench, currents=currents,
                                        marker=marker, xyz=xyz, source=contents.path, robot=robot)
    except InputError as exc:
        raise InputError(f"the log's static readings do not make a deflection table: {_exported_at(exc, 'static')}",
                         source=contents.path) from None


def _exported_at(exc: InputError, table: str) -> str:
    """An error of a table built from a log, with where it is in the exported CSV."""
    where = [f"line {exc.row}"] if exc.row is not None else []
    where += [f"column {exc.column}"] if exc.column else []
    return f"{exc.detail} ({', '.join(where)} of the exported {table}.csv)" if where else exc.detail


def run_table_from_log(contents: LogContents, robot: Robot | None = None) -> RunTable | None:
    """The run table of the log's completed runs (friction runs, sweeps), or None.

    One row per sample of drive 1 between ``run_start`` and ``run_end``; the
    other drives contribute their sample nearest in time, the followed marker
    its nearest tracker sample when it lies within half a drive period.
    """
    done = set(contents.completed_steps)
    starts = {}
    runs = []
    for e in contents.events:
        if e["kind"] == "run_start":
            starts[e["run"]] = e
        elif e["kind"] == "run_end" and e["run"] in starts and e.get("step_id") in done:
            runs.append((starts.pop(e["run"]), e))
    if not runs:
        return None
    origin = _time_origin(contents)
    cols: dict[str, list] = {k: [] for k in ("run", "direction", "load", "t", "q", "dq", "i", "w", "marker", "xyz")}
    ref = contents.drives[0]
    for start, end in runs:
        sl = _window(ref.t_ns, _key(start, start["t_ns"]), _key(end, end["t_ns"]))
        t_rows = ref.t_ns[sl]
        n = len(t_rows)
        if n == 0:
            raise InputError(f"run {start['run']} has no drive samples", source=contents.path)
        q = np.empty((n, 6))
        dq = np.empty((n, 6))
        cur = np.empty((n, 6))
        for j, d in enumerate(contents.drives):
            if len(d.t_ns) == 0:
                raise InputError(f"run {start['run']}: drive {j + 1} has no samples", source=contents.path)
            idx = _nearest(d.t_ns, t_rows)
            q[:, j] = d.position_rad[idx]
            dq[:, j] = d.velocity_rad_s[idx]
            cur[:, j] = d.current_a[idx]
        mname = start.get("marker") or ""
        xyz = np.full((n, 3), np.nan)
        marker = np.full(n, "", dtype=object)
        if mname and mname in contents.markers and n > 1:
            tr = contents.markers[mname]
            period = float(np.median(np.diff(t_rows)))
            idx = _nearest(tr.t_ns, t_rows)
            ok = np.abs(tr.t_ns[idx] - t_rows) <= 0.5 * period
            xyz[ok] = tr.xyz[idx[ok]]
            marker[ok] = mname
        cols["run"] += [str(start["run"])] * n
        cols["direction"] += [str(start["direction"])] * n
        cols["load"] += [str(start.get("load", "0"))] * n
        cols["t"].append((t_rows - start["segment"] * SEGMENT_NS - origin) * 1e-9)
        cols["q"].append(q)
        cols["dq"].append(dq)
        cols["i"].append(cur)
        cols["w"].append(np.tile(_wrench(start.get("wrench")), (n, 1)))
        cols["marker"] += list(marker)
        cols["xyz"].append(xyz)
    try:
        return run_table_from_arrays(run=cols["run"], direction=cols["direction"], load=cols["load"],
                                     t=np.concatenate(cols["t"]), q=np.concatenate(cols["q"]),
                                     dq=np.concatenate(cols["dq"]), currents=np.concatenate(cols["i"]),
                                     wrench=np.concatenate(cols["w"]), marker=cols["marker"],
                                     xyz=np.concatenate(cols["xyz"]), source=contents.path, robot=robot)
    except InputError as exc:
        raise InputError(f"the log's runs do not make a run table: {_exported_at(exc, 'runs')}",
                         source=contents.path) from None


def _nearest(t_sorted: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Index of the sample of ``t_sorted`` nearest to each query time."""
    right = np.searchsorted(t_sorted, t_query, side="left").clip(0, len(t_sorted) - 1)
    left = (right - 1).clip(0, len(t_sorted) - 1)
    pick_left = np.abs(t_query - t_sorted[left]) <= np.abs(t_sorted[right] - t_query)
    return np.where(pick_left, left, right)


def robot_from_log(contents: LogContents) -> Robot:
    if contents.robot is None:
        raise InputError("the log holds no robot description", source=contents.path)
    return parse_robot(contents.robot.text, source=f"{contents.path} ({lf.TOPIC_ROBOT})")


def load_log(path: str | pathlib.Path) -> tuple[Robot, StaticTable | None, RunTable | None]:
    """Robot, static table and run table of a log (each table None when the log has none)."""
    return tables_from_log(read_log(path))


def tables_from_log(contents: LogContents) -> tuple[Robot, StaticTable | None, RunTable | None]:
    """Robot, static table and run table of a log already read."""
    robot = robot_from_log(contents)
    return robot, static_table_from_log(contents, robot), run_table_from_log(contents, robot)


@dataclass(frozen=True)
class ExportResult:
    files: tuple[str, ...]
    static_rows: int
    run_rows: int
    complete: bool
    truncated: bool
    incomplete_steps: tuple[str, ...]


def export_files(contents: LogContents) -> dict[str, str | StaticTable | RunTable | None]:
    """What an export of a log writes: file name -> its text or table (None:
    the log has none, e.g. no static experiment)."""
    robot, static, runs = tables_from_log(contents)
    return {"robot.toml": contents.robot.text,
            "cell.toml": None if contents.cell is None else contents.cell.text,
            "plan.toml": None if contents.plan is None else contents.plan.text,
            "static.csv": static, "runs.csv": runs}


def write_export_file(path: str | pathlib.Path, what: str | StaticTable | RunTable) -> None:
    """One file of :func:`export_files` at ``path``."""
    if isinstance(what, StaticTable):
        write_static_table(path, what)
    elif isinstance(what, RunTable):
        write_run_table(path, what)
    else:
        pathlib.Path(path).write_text(what, encoding="utf-8")


def export_log(path: str | pathlib.Path, out_dir: str | pathlib.Path) -> ExportResult:
    """Write ``robot.toml``, ``static.csv`` and/or ``runs.csv`` (and the recorded
    ``cell.toml`` and ``plan.toml``) of a log into ``out_dir``."""
    contents = read_log(path)
    writes = export_files(contents)
    out = pathlib.Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create: {exc.strerror}", source=str(out)) from None
    files = []
    for name, what in writes.items():
        if what is not None:
            write_export_file(out / name, what)
            files.append(str(out / name))
    return ExportResult(files=tuple(files), static_rows=_rows(writes["static.csv"]),
                        run_rows=_rows(writes["runs.csv"]), complete=contents.complete,
                        truncated=contents.truncated, incomplete_steps=contents.incomplete_steps)


def _rows(table) -> int:
    return 0 if table is None else len(table)


# ------------------------------------------------------------------ tables -> log
class _SetClock:
    """A clock the writer of a synthetic log sets before each event."""

    def __init__(self, t_ns: int) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


#: log time of the first event of a log written from tables [ns]
SYNTHETIC_ORIGIN_NS = 1_000_000_000_000
#: spacing of rows that have no usable time [ns]
SYNTHETIC_SLOT_NS = 10_000_000


def _row_times(t: np.ndarray, start_ns: int) -> np.ndarray:
    """Log times of table rows: their own ``t`` when finite, >= 0 and strictly
    increasing, else one slot per row."""
    if len(t) and np.all(np.isfinite(t)) and t[0] >= 0 and np.all(np.diff(t) > 0):
        times = start_ns + np.round(t * 1e9).astype(np.int64)
        if len(times) < 2 or np.all(np.diff(times) > 1_000):
            return times
    return start_ns + SYNTHETIC_SLOT_NS * (1 + np.arange(len(t), dtype=np.int64))


def _opt(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def write_log_from_tables(path: str | pathlib.Path, robot: Robot, *, static: StaticTable | None = None,
                          runs: RunTable | None = None, overwrite: bool = True) -> None:
    """Write a log whose export gives back ``static`` and ``runs`` (datasets made
    without devices, e.g. ``elastocal sim``): one reading window per static row
    holding exactly that row's tracker sample and currents, one drive sample per
    run row. ``q``, currents, wrenches and positions come back bit for bit; ``t``
    comes back to the nanosecond when the table's times are increasing, else as
    10 ms slots; runs that overlap in time are moved after one another.
    """
    from elastocal.acquisition.recorder import Recorder

    clock = _SetClock(SYNTHETIC_ORIGIN_NS)
    with Recorder(path, overwrite=overwrite, clock=clock) as rec:
        rec.document("robot", robot.name, robot.to_toml())
        rec.event("procedure_start", procedure="from-tables")
        now = SYNTHETIC_ORIGIN_NS - 1_000_000  # step events may precede the origin
        if static is not None and len(static):
            times = _row_times(static.t, SYNTHETIC_ORIGIN_NS)
            order = {p: i for i, p in enumerate(dict.fromkeys(static.pose))}
            for p in order:
                rows = np.flatnonzero(static.pose == p)
                step_id = f"static/{p}"
                clock.t_ns = int(times[rows[0]]) - 2_000
                rec.event("step_start", procedure="static", step_id=step_id)
                for r in rows:
                    t = int(times[r])
                    for j in range(6):
                        rec.drive_sample(j + 1, t, float(static.q[r, j]), 0.0, _opt(static.currents[r, j]))
                    rec.tracker_sample(t, str(static.marker[r]), static.xyz[r])
                    clock.t_ns = t + 500
                    w = static.wrench[r]
                    rec.event("reading", step_id=step_id, pose=str(p), load=str(static.load[r]),
                              marker=str(static.marker[r]), q=[float(v) for v in static.q[r]],
                              wrench=None if not np.all(np.isfinite(w)) else [float(v) for v in w],
                              window_ns=[t - 500, t + 500])
                clock.t_ns = int(times[rows[-1]]) + 1_000
                rec.event("step_done", procedure="static", step_id=step_id)
            now = int(times.max()) + 1_000_000_000
        if runs is not None and len(runs):
            for run_id in dict.fromkeys(runs.run):
                rows = np.flatnonzero(runs.run == run_id)
                for name, col in (("load", runs.load), ("wrench", runs.wrench)):
                    vals = col[rows]
                    same = np.all(vals == vals[0]) if vals.dtype.kind in "US" else \
                        np.allclose(vals, vals[0], equal_nan=True, rtol=0, atol=0)
                    if not same:
                        raise InputError(f"run {run_id}: the {name} changes within the run; a log run has one",
                                         source=runs.source)
                t = runs.t[rows]
                rel = _row_times(t - t[0], 0) if np.all(np.isfinite(t)) else _row_times(t, 0)
                start = now if not np.isfinite(t[0]) else max(now, SYNTHETIC_ORIGIN_NS + int(round(t[0] * 1e9)) - 2_000)
                times = start + 2_000 + rel - rel[0]
                step_id = f"runs/{run_id}"
                clock.t_ns = start
                rec.event("step_start", procedure="runs", step_id=step_id)
                clock.t_ns = start + 1_000
                w = runs.wrench[rows[0]]
                markers = sorted({m for m in runs.marker[rows] if m})
                if len(markers) > 1:
                    raise InputError(f"run {run_id} follows several markers ({', '.join(markers)}); a log run "
                                     f"follows one", source=runs.source)
                rec.event("run_start", step_id=step_id, run=str(run_id), direction=str(runs.direction[rows[0]]),
                          load=str(runs.load[rows[0]]), marker=markers[0] if markers else None,
                          wrench=None if not np.all(np.isfinite(w)) else [float(v) for v in w])
                for r, tn in zip(rows, times):
                    tn = int(tn)
                    for j in range(6):
                        rec.drive_sample(j + 1, tn, float(runs.q[r, j]), _opt(runs.dq[r, j]),
                                         _opt(runs.currents[r, j]))
                    if runs.marker[r]:
                        rec.tracker_sample(tn, str(runs.marker[r]), runs.xyz[r])
                clock.t_ns = int(times[-1]) + 1_000
                rec.event("run_end", step_id=step_id, run=str(run_id), direction=str(runs.direction[rows[0]]))
                rec.event("step_done", procedure="runs", step_id=step_id)
                now = clock.t_ns + 1_000_000_000
        clock.t_ns = now
        rec.event("procedure_end", status="completed")
