"""Read an elastocal MCAP log back: its documents, samples and procedure events.

:class:`LogReader` walks the file with mcap's streaming reader and stops cleanly
where a killed recorder left it (a truncated record ends the walk; the complete
chunks before it are read). :func:`read_log` gathers the samples and procedure
events into :class:`LogContents`; :mod:`elastocal.acquisition.export` turns them
into tables (docs/log-format.md).

A finished log (closing magic, summary, every message in an indexed chunk) is read
faster: mcap's summary gives the chunks, which are read in file order without the
message-index records the streaming reader parses entry by entry (one per message),
and only the messages of the topics wanted are cut out of each decompressed chunk
(:mod:`elastocal.acquisition.logchunks`) and JSON-decoded, one decode per topic and chunk
(benchmarks/bench_log.py measures it against mcap's own readers on the same file).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import operator
import os
import pathlib
import struct
from dataclasses import dataclass
from typing import IO, Collection, Iterator

import numpy as np
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, breakup_chunk

from elastocal.formats import logformat as lf
from elastocal.acquisition.logchunks import chunk_messages, ends_with_magic, indexed_chunks, read_chunk
from elastocal.errors import InputError

#: samples of the k-th recording session of a log (a resumed log holds several,
#: possibly on clocks restarted by a reboot) are kept at k * SEGMENT_NS + t, so
#: reading windows only ever see samples of their own session
SEGMENT_NS = 10**17
MAX_SEGMENTS = 90
#: the topics :func:`read_log` gathers; the Foxglove views (docs/log-format.md) are for viewers
READ_TOPICS = frozenset({*lf.DRIVE_TOPICS, lf.TOPIC_TRACKER, lf.TOPIC_EVENT, lf.TOPIC_ROBOT, lf.TOPIC_CELL,
                         lf.TOPIC_PLAN, lf.TOPIC_SESSION})

class _ExactReads:
    """File wrapper for StreamReader: a short read (the file ends inside a
    record) raises :class:`mcap.exceptions.EndOfFile` instead of returning a
    partial record, so a truncated log ends cleanly at its last whole record."""

    def __init__(self, raw: IO[bytes]) -> None:
        self._raw = raw
        self.offset = 0
        self._size = os.fstat(raw.fileno()).st_size

    def read(self, n: int = -1) -> bytes:
        if n is not None and n > self._size - self.offset:   # never allocate what the file cannot hold
            raise EndOfFile()
        data = self._raw.read(n)
        if n is not None and n >= 0 and len(data) < n:
            raise EndOfFile()
        self.offset += len(data)
        return data


class _Position:
    """A complete file, read directly; a length field that claims more than the file
    holds (a corrupt record) is refused before anything is allocated for it."""

    def __init__(self, raw: IO[bytes]) -> None:
        self._raw = raw
        self._size = os.fstat(raw.fileno()).st_size

    def read(self, n: int = -1) -> bytes:
        if n is not None and n > self._size - self._raw.tell():
            raise McapError(f"a length of {n} bytes, more than the rest of the file holds")
        return self._raw.read(n)

    @property
    def offset(self) -> int:
        return self._raw.tell()


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
            stream = _ExactReads(f) if not ends_with_magic(f) else _Position(f)
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

    def _open_chunk(self, record: Chunk) -> list:
        try:
            return breakup_chunk(record, validate_crc=True)
        except CRCValidationError as exc:
            raise InputError(f"corrupt chunk before byte {self.end_offset}: {exc}", source=str(self.path)) from None
        except Exception as exc:  # zstandard raises its own error type on bad data
            raise InputError(f"cannot decompress chunk before byte {self.end_offset}: {exc}",
                             source=str(self.path)) from None

    def records(self) -> Iterator[object]:
        """Every whole record of the file in order, chunks opened (header, schemas, channels,
        messages, metadata, ...; the summary's index records too when the file is complete)."""
        for record in self._records():
            if isinstance(record, Chunk):
                yield from self._open_chunk(record)
            else:
                yield record

    def _expand(self, record: object) -> list[Message]:
        """Messages of one top-level record; schemas and channels are remembered."""
        if isinstance(record, Chunk):
            inner = self._open_chunk(record)
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

    def grouped(self, topics: Collection[str] | None = None) -> Iterator[tuple[int, dict[str, tuple[list[int], list]]]]:
        """Decoded messages, one item per chunk: (messages in it, {topic -> (log
        times, payloads)}), each topic's in file order; only ``topics`` are decoded
        (all when None). The fastest way through a log: one JSON decode per topic
        and chunk, and a finished log read by its summary (module docstring)."""
        chunks = self._indexed_chunks()
        source = self._streamed_groups() if chunks is None else self._summary_groups(chunks, topics)
        for count, by_channel in source:
            out = {}
            for cid, (times, datas) in by_channel.items():
                topic = self._topic_of(cid)
                if topics is not None and topic not in topics:
                    continue
                try:
                    values = json.loads(b"[" + b",".join(datas) + b"]")
                except ValueError:
                    values = [self._decode_data(topic, t, d) for t, d in zip(times, datas)]
                out[topic] = (times, values)
            yield count, out

    def _streamed_groups(self) -> Iterator[tuple[int, dict[int, tuple[list[int], list[bytes]]]]]:
        """Every record through mcap's streaming reader (any log, a truncated one too)."""
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
            yield len(msgs), by_channel

    def _indexed_chunks(self) -> list | None:
        """The chunk indexes of a finished log read by its summary (logchunks.indexed_chunks), its
        channels and schemas remembered; None: the streaming reader reads the file."""
        found = indexed_chunks(self.path)
        if found is None:
            return None
        chunks, summary = found
        self.topics.update({cid: ch.topic for cid, ch in summary.channels.items()})
        self.schemas.update({sid: sc.name for sid, sc in summary.schemas.items()})
        return chunks

    def _summary_groups(self, chunks: list, topics: Collection[str] | None
                        ) -> Iterator[tuple[int, dict[int, tuple[list[int], list[bytes]]]]]:
        """The chunks of :meth:`_indexed_chunks`, each read at its offset, checked against
        its CRC, and cut into the messages of ``topics``."""
        wanted = None if topics is None else {cid for cid, t in self.topics.items() if t in topics}
        with open(self.path, "rb") as f:
            for ci in chunks:
                self.end_offset = ci.chunk_start_offset + ci.chunk_length
                try:
                    data = read_chunk(f, ci)
                except CRCValidationError as exc:
                    raise InputError(f"corrupt chunk before byte {self.end_offset}: {exc}",
                                     source=str(self.path)) from None
                except Exception as exc:  # zstandard raises its own error type on bad data
                    raise InputError(f"cannot decompress chunk before byte {self.end_offset}: {exc}",
                                     source=str(self.path)) from None
                try:
                    yield chunk_messages(data, wanted)
                except (McapError, struct.error) as exc:
                    raise InputError(f"corrupt chunk before byte {self.end_offset}: {exc}",
                                     source=str(self.path)) from None
        self.complete = True

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
    drives: tuple[DriveSamples, ...]  # one per joint, 1..N
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


def _described_joints(robot_text: str) -> int:
    """How many ``[[joint]]`` tables a recorded robot.toml has (0 when it does not read)."""
    import tomllib

    try:
        joints = tomllib.loads(robot_text).get("joint", [])
    except tomllib.TOMLDecodeError:
        return 0
    return len(joints) if isinstance(joints, list) else 0


def _add_tracker_samples(tracker_parts: dict[str, list], values: list[dict], t: np.ndarray, source: str) -> None:
    """One group of tracker messages (times ``t``) added to each marker's parts."""
    try:
        markers = [v["marker"] for v in values]
        xyz = np.array(list(map(operator.itemgetter("x", "y", "z"), values)), dtype=float)
        if not all(isinstance(m, str) for m in markers):
            raise TypeError("marker")
    except (KeyError, TypeError, ValueError):
        raise InputError(f"a message on {lf.TOPIC_TRACKER} is not a tracker sample", source=source) from None
    if len(set(markers)) == 1:
        tracker_parts.setdefault(markers[0], []).append((t, xyz))
    else:
        names = np.array(markers)
        for m in dict.fromkeys(markers):
            sel = names == m
            tracker_parts.setdefault(m, []).append((t[sel], xyz[sel]))


def _sorted(parts: list[tuple[np.ndarray, np.ndarray]], width: int) -> tuple[np.ndarray, np.ndarray]:
    """The parts' times and values joined, in time order."""
    if not parts:
        return np.zeros(0, dtype=np.int64), np.zeros((0, width))
    t = np.concatenate([p[0] for p in parts])
    vals = np.concatenate([p[1] for p in parts])
    if np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        t, vals = t[order], vals[order]
    return t, vals


def read_log(path: str | pathlib.Path) -> LogContents:
    """Gather a log's documents, events and samples (tolerates a truncated file).
    Only the topics of :data:`READ_TOPICS` are decoded; ``messages`` counts all."""
    reader = LogReader(path)
    source = str(reader.path)
    docs: dict[str, Document] = {}
    sessions: list[dict] = []
    events: list[dict] = []
    drive_parts: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(lf.MAX_JOINTS)]
    tracker_parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    drive_index = {t: j for j, t in enumerate(lf.DRIVE_TOPICS)}
    n_messages = 0
    get_drive = operator.itemgetter("position_rad", "velocity_rad_s", "current_a")
    segment = 0
    for count, groups in reader.grouped(READ_TOPICS):
        offset = segment * SEGMENT_NS
        resumes = 0
        n_messages += count
        for topic, (log_times, values) in groups.items():
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
                _add_tracker_samples(tracker_parts, values, _keys(times, offset, source), source)
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

    drives_out = []
    # the log's joints: the robot's N (drives 1..N), or as many as have samples
    n_joints = max((j + 1 for j, parts in enumerate(drive_parts) if parts), default=6)
    robot_doc = docs.get("robot")
    if robot_doc is not None:
        n_joints = max(n_joints, _described_joints(robot_doc.text))
    for parts in drive_parts[:n_joints]:
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
def _monotonic(log_times: list[int], values: list) -> list[int]:
    """Acquisition times on the monotonic clock: each message's ``monotonic_ns``, or its
    log time in logs written before log times became Unix time (docs/log-format.md)."""
    if not values or not isinstance(values[0], dict) or "monotonic_ns" not in values[0]:
        if not any(isinstance(v, dict) and "monotonic_ns" in v for v in values):
            return log_times
    try:        # every payload an object (the usual case): dict.get over them in one C loop
        return list(map(dict.get, values, itertools.repeat("monotonic_ns"), log_times))
    except TypeError:
        return [v.get("monotonic_ns", t) if isinstance(v, dict) else t for t, v in zip(log_times, values)]


def _keys(times: list[int], offset: int, source: str) -> np.ndarray:
    try:
        t = np.array(times, dtype=np.int64)
    except (TypeError, ValueError, OverflowError):       # a monotonic_ns that is no integer time
        raise InputError("a sample's monotonic_ns is not a time in integer nanoseconds", source=source) from None
    if len(t) and (t.max() >= SEGMENT_NS or t.min() < 0):
        raise InputError(f"sample times beyond {SEGMENT_NS} ns (3 years) of the log clock", source=source)
    if offset >= MAX_SEGMENTS * SEGMENT_NS:
        raise InputError(f"more than {MAX_SEGMENTS} resumed sessions in one log", source=source)
    return t + offset
