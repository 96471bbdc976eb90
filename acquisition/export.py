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

import hashlib
import json
import pathlib
import struct
from dataclasses import dataclass, field
from typing import IO, Iterator

import numpy as np
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, Chunk, Footer, Message, Schema
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


@dataclass
class LogReader:
    """Messages of a (possibly truncated) elastocal log, in file order.

    After iterating, ``complete`` tells whether the MCAP footer was reached
    and ``truncated`` whether the file ended inside a record (a killed writer).
    """

    path: pathlib.Path
    complete: bool = False
    truncated: bool = False
    end_offset: int = 0
    topics: dict[int, str] = field(default_factory=dict)
    schemas: dict[int, str] = field(default_factory=dict)

    def __init__(self, path: str | pathlib.Path) -> None:
        self.path = pathlib.Path(path)
        self.complete = False
        self.truncated = False
        self.end_offset = 0
        self.topics = {}
        self.schemas = {}

    def _records(self) -> Iterator[object]:
        try:
            f = open(self.path, "rb")
        except OSError as exc:
            raise InputError(f"cannot read: {exc.strerror}", source=str(self.path)) from None
        with f:
            stream = _ExactReads(f)
            reader = StreamReader(stream, emit_chunks=True, record_size_limit=1 << 30)
            it = reader.records
            while True:
                try:
                    record = next(it)
                except StopIteration:
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
                if isinstance(record, Footer):
                    self.complete = True
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
        try:
            return self.topics[message.channel_id]
        except KeyError:
            raise InputError(f"message on channel {message.channel_id} before its channel record",
                             source=str(self.path)) from None

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

    t_ns: np.ndarray            # (n,) int64
    position_rad: np.ndarray    # (n,)
    velocity_rad_s: np.ndarray  # (n,) NaN when not given
    current_a: np.ndarray       # (n,) NaN when not given


@dataclass(frozen=True, eq=False)
class TrackerSamples:
    """Samples of one marker, in time order."""

    t_ns: np.ndarray  # (n,) int64
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
    for batch in reader.batches():
        n_messages += len(batch)
        drives: list[list] = [[] for _ in range(lf.N_JOINTS)]
        tracker: dict[str, list] = {}
        for topic, t_ns, v in batch:
            j = drive_index.get(topic)
            if j is not None:
                drives[j].append((t_ns, v["position_rad"], v["velocity_rad_s"], v["current_a"]))
            elif topic == lf.TOPIC_TRACKER:
                tracker.setdefault(v["marker"], []).append((t_ns, v["x"], v["y"], v["z"]))
            elif topic == lf.TOPIC_EVENT:
                events.append({**v, "t_ns": t_ns})
            elif topic in (lf.TOPIC_ROBOT, lf.TOPIC_CELL, lf.TOPIC_PLAN):
                doc = _document(v, source)
                docs.setdefault(doc.kind, doc)
            elif topic == lf.TOPIC_SESSION:
                if v.get("format") != lf.LOG_FORMAT:
                    raise InputError(f"log format {v.get('format')!r} is not {lf.LOG_FORMAT}", source=source)
                sessions.append(v)
        for j, rows in enumerate(drives):
            if rows:
                t = np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows))
                vals = np.array([r[1:] for r in rows], dtype=float)
                drive_parts[j].append((t, vals))
        for m, rows in tracker.items():
            t = np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows))
            tracker_parts.setdefault(m, []).append((t, np.array([r[1:] for r in rows], dtype=float)))
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
                       markers=markers_out)


# ------------------------------------------------------------------ tables
def _window(t_ns: np.ndarray, start: int, end: int) -> slice:
    return slice(int(np.searchsorted(t_ns, start, side="left")), int(np.searchsorted(t_ns, end, side="right")))


def _time_origin(contents: LogContents) -> int:
    return min(e["t_ns"] for e in contents.events) if contents.events else 0


def _wrench(value) -> list[float]:
    if value is None:
        return [float("nan")] * 6
    return [float(x) for x in value]


def static_table_from_log(contents: LogContents, robot: Robot | None = None) -> StaticTable | None:
    """The static deflection table of the log's completed static steps, or None.

    One row per ``reading`` event: the mean tracker position of its marker and
    the mean current of each drive over the reading's window; ``t`` is the
    window's middle in seconds from the log's first event; ``q`` and the wrench
    are the commanded pose and the nominal load the event names.
    """
    done = set(contents.completed_steps)
    readings = [e for e in contents.events if e["kind"] == "reading" and e.get("step_id") in done]
    if not readings:
        return None
    origin = _time_origin(contents)
    pose, load, t, q, wrench, currents, marker, xyz = [], [], [], [], [], [], [], []
    for e in readings:
        start, end = (int(v) for v in e["window_ns"])
        m = e["marker"]
        samples = contents.markers.get(m)
        sl = _window(samples.t_ns, start, end) if samples is not None else slice(0, 0)
        if samples is None or sl.stop <= sl.start:
            raise InputError(f"reading of marker {m} at pose {e['pose']} load {e['load']} has no tracker sample "
                             f"in its window", source=contents.path)
        xyz.append(samples.xyz[sl].mean(axis=0))
        cur = []
        for d in contents.drives:
            dsl = _window(d.t_ns, start, end)
            cur.append(float(np.mean(d.current_a[dsl])) if dsl.stop > dsl.start else float("nan"))
        currents.append(cur)
        pose.append(str(e["pose"]))
        load.append(str(e["load"]))
        t.append(((start + end) // 2 - origin) * 1e-9)
        q.append([float(v) for v in e["q"]])
        wrench.append(_wrench(e.get("wrench")))
        marker.append(m)
    try:
        return static_table_from_arrays(pose=pose, load=load, t=t, q=q, wrench=wrench, currents=currents,
                                        marker=marker, xyz=xyz, source=contents.path)
    except InputError as exc:
        raise InputError(f"the log's static readings do not make a deflection table: {exc.detail}",
                         source=contents.path) from None


def run_table_from_log(contents: LogContents) -> RunTable | None:
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
        sl = _window(ref.t_ns, int(start["t_ns"]), int(end["t_ns"]))
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
        cols["t"].append((t_rows - origin) * 1e-9)
        cols["q"].append(q)
        cols["dq"].append(dq)
        cols["i"].append(cur)
        cols["w"].append(np.tile(_wrench(start.get("wrench")), (n, 1)))
        cols["marker"] += list(marker)
        cols["xyz"].append(xyz)
    return run_table_from_arrays(run=cols["run"], direction=cols["direction"], load=cols["load"],
                                 t=np.concatenate(cols["t"]), q=np.concatenate(cols["q"]),
                                 dq=np.concatenate(cols["dq"]), currents=np.concatenate(cols["i"]),
                                 wrench=np.concatenate(cols["w"]), marker=cols["marker"],
                                 xyz=np.concatenate(cols["xyz"]), source=contents.path)


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
    contents = read_log(path)
    robot = robot_from_log(contents)
    return robot, static_table_from_log(contents, robot), run_table_from_log(contents)


@dataclass(frozen=True)
class ExportResult:
    files: tuple[str, ...]
    static_rows: int
    run_rows: int
    complete: bool
    truncated: bool
    incomplete_steps: tuple[str, ...]


def export_log(path: str | pathlib.Path, out_dir: str | pathlib.Path) -> ExportResult:
    """Write ``robot.toml``, ``static.csv`` and/or ``runs.csv`` (and the recorded
    ``cell.toml`` and ``plan.toml``) of a log into ``out_dir``."""
    contents = read_log(path)
    robot = robot_from_log(contents)
    static = static_table_from_log(contents, robot)
    runs = run_table_from_log(contents)
    out = pathlib.Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create: {exc.strerror}", source=str(out)) from None
    files = []
    (out / "robot.toml").write_text(contents.robot.text, encoding="utf-8")
    files.append(str(out / "robot.toml"))
    for doc, name in ((contents.cell, "cell.toml"), (contents.plan, "plan.toml")):
        if doc is not None:
            (out / name).write_text(doc.text, encoding="utf-8")
            files.append(str(out / name))
    if static is not None:
        write_static_table(out / "static.csv", static)
        files.append(str(out / "static.csv"))
    if runs is not None:
        write_run_table(out / "runs.csv", runs)
        files.append(str(out / "runs.csv"))
    return ExportResult(files=tuple(files), static_rows=0 if static is None else len(static),
                        run_rows=0 if runs is None else len(runs), complete=contents.complete,
                        truncated=contents.truncated, incomplete_steps=contents.incomplete_steps)
