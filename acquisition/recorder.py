"""Recorder: raw samples and procedure events into an MCAP log (docs/log-format.md).

The recorder is a context manager around :class:`mcap.writer.Writer` (zstd
chunks). Each JSON Schema is registered once, each topic's channel once, on
first use. Samples come with the acquisition timestamp their driver gave them
(integer ns, one monotonic clock); events are stamped by the recorder's clock.
Log times are wall-clock Unix ns: the monotonic stamp plus the offset between
the two clocks taken once when the log opens (so intervals stay monotonic), and
the monotonic stamp is kept in each sample's and event's ``monotonic_ns``.

Once the robot description is recorded, the recorder also publishes the cell in
Foxglove's well-known schemas (:class:`elastocal.acquisition.foxglove.CellPublisher`):
joint frames, links, markers, tracker readings and the procedure's events.

Surviving a kill: the writer keeps the chunk in progress in memory, so the
recorder finishes the chunk and flushes the file at every procedure event and
at least every ``flush_interval_s`` (50 ms, :data:`FLUSH_INTERVAL_S`) while samples arrive. A process killed at
any moment leaves a file whose complete chunks
:class:`elastocal.acquisition.logreader.LogReader` reads up to the kill.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
import pathlib
import threading
import time
from typing import Any, Callable, Sequence

from mcap.writer import CompressionType, Writer

from elastocal import __version__
from elastocal.formats import logformat as lf
from elastocal.acquisition.foxglove import CellPublisher
from elastocal.errors import Arg, InputError
from elastocal.formats.robot_toml import parse_robot

Clock = Callable[[], int]

#: the longest a sample waits in memory before the file has it (what a kill can lose) [s]
FLUSH_INTERVAL_S = 0.05


def _dumps(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _finite_or_none(x):
    """``x`` as a JSON-safe value: None for None and non-finite floats; lists cleaned
    element by element (a non-finite element makes the whole list None)."""
    if x is None or isinstance(x, (bool, str, int, dict)):
        return x
    if isinstance(x, (list, tuple)):
        out = [_finite_or_none(v) for v in x]
        return None if any(v is None for v in out) else out
    x = float(x)
    return x if math.isfinite(x) else None


class Recorder:
    """Write an elastocal MCAP log.

    ``with Recorder(path) as rec: rec.document("robot", ...); rec.drive_sample(...)``.
    Leaving the ``with`` block (normally or by an exception) writes the MCAP
    summary and closes the file.
    """

    def __init__(self, path: str | pathlib.Path, *, overwrite: bool = False,
                 chunk_size: int = 256 * 1024, flush_interval_s: float = FLUSH_INTERVAL_S,
                 clock: Clock = time.monotonic_ns, resumed_from: str | None = None,
                 unix_clock: Clock = time.time_ns, foxglove: bool = True) -> None:
        self.path = pathlib.Path(path)
        self.overwrite = overwrite
        if not overwrite and (self.path.exists() or self.path.is_symlink()):
            raise InputError(("already exists; choose another ", Arg("out"), " or remove it"), source=str(self.path))
        if chunk_size <= 0:
            raise ValueError("chunk_size must be positive")
        if flush_interval_s <= 0:
            raise ValueError("flush_interval_s must be positive")
        self.chunk_size = chunk_size
        self.flush_interval_ns = int(flush_interval_s * 1e9)
        self.clock = clock
        self.unix_clock = unix_clock
        self.foxglove = foxglove
        self.resumed_from = resumed_from
        self._offset_ns = 0                   # Unix time minus the acquisition clock, fixed at opening
        self._cell: CellPublisher | None = None
        self._lock = threading.Lock()
        self._file = None
        self._writer: Writer | None = None
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._sequence = 0
        self._last_flush_ns = 0
        self._messages = 0

    # ---------------------------------------------------------- lifecycle
    def __enter__(self) -> "Recorder":
        self._file = self._create()
        self._writer = Writer(self._file, chunk_size=self.chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile=lf.PROFILE, library=f"elastocal/{__version__}")
        self._writer.add_metadata("elastocal", {"format": lf.LOG_FORMAT, "software": __version__})
        now = self.clock()
        unix_now = int(self.unix_clock())
        self._offset_ns = unix_now - now
        started = datetime.datetime.fromtimestamp(unix_now / 1e9, datetime.timezone.utc)
        self._write(lf.TOPIC_SESSION, now, {
            "format": lf.LOG_FORMAT, "software": __version__,
            "started_utc": started.isoformat(timespec="microseconds"),
            "monotonic_ns": now, "unix_ns": unix_now, "log_clock": "unix", "resumed_from": self.resumed_from,
        }, now)
        self.flush()
        return self

    def _create(self):
        """The log file, created new where it is named: never through a symbolic link and never
        into a device or FIFO; an existing regular file is removed first (``overwrite``)."""
        path = self.path
        if path.is_symlink() or (path.exists() and not path.is_file()):
            raise InputError("is not a regular file (a symbolic link, a device, a FIFO); a log is written to a "
                             "new regular file", source=str(path))
        try:
            if self.overwrite and path.is_file():
                path.unlink()
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except FileExistsError:
            raise InputError(("appeared while the log was being opened; choose another ", Arg("out")),
                             source=str(path)) from None
        except OSError as exc:
            raise InputError(f"cannot write: {exc.strerror}", source=str(path)) from None
        return os.fdopen(fd, "wb")

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            if self._writer is None:
                return
            try:
                self._writer.finish()
            finally:
                self._writer = None
                self._file.close()
                self._file = None

    @property
    def messages_written(self) -> int:
        return self._messages

    # ------------------------------------------------------------ writing
    def _channel(self, topic: str) -> int:
        cid = self._channel_ids.get(topic)
        if cid is None:
            schema_name = lf.TOPIC_SCHEMAS[topic]
            sid = self._schema_ids.get(schema_name)
            if sid is None:
                sid = self._writer.register_schema(schema_name, "jsonschema", lf.schema_bytes(schema_name))
                self._schema_ids[schema_name] = sid
            cid = self._writer.register_channel(topic, "json", sid)
            self._channel_ids[topic] = cid
        return cid

    def _write(self, topic: str, log_time_ns: int, message: dict | bytes, publish_ns: int) -> None:
        """Write one message; ``log_time_ns`` and ``publish_ns`` on the acquisition clock."""
        self._write_unix(topic, int(log_time_ns) + self._offset_ns, message, int(publish_ns) + self._offset_ns)

    def _write_unix(self, topic: str, log_time_ns: int, message: dict | bytes, publish_ns: int) -> None:
        if self._writer is None:
            raise RuntimeError("the recorder is not open; use it in a with block")
        data = message if isinstance(message, bytes) else _dumps(message)
        self._sequence += 1
        self._writer.add_message(self._channel(topic), int(log_time_ns), data, int(publish_ns),
                                 sequence=self._sequence & 0xFFFFFFFF)
        self._messages += 1

    def _publish(self, topic: str, unix_ns: int, message: dict) -> None:
        """A Foxglove message (the lock is held)."""
        self._write_unix(topic, unix_ns, message, unix_ns)

    @property
    def offset_ns(self) -> int:
        """Unix time minus the acquisition clock [ns] (fixed when the log opened)."""
        return self._offset_ns

    def _maybe_flush(self, now_ns: int) -> None:
        if now_ns - self._last_flush_ns >= self.flush_interval_ns:
            self._flush_locked(now_ns)

    def _flush_locked(self, now_ns: int) -> None:
        self._writer.flush()
        self._last_flush_ns = now_ns

    def flush(self) -> None:
        """Finish the chunk in progress and push everything to the file."""
        with self._lock:
            if self._writer is not None:
                self._flush_locked(self.clock())

    def document(self, kind: str, name: str, text: str, path: str | None = None) -> None:
        """Record a configuration document (``robot``, ``cell`` or ``plan``) verbatim."""
        topic = {"robot": lf.TOPIC_ROBOT, "cell": lf.TOPIC_CELL, "plan": lf.TOPIC_PLAN}[kind]
        msg = {"kind": kind, "name": name, "path": path,
               "sha256": hashlib.sha256(text.encode()).hexdigest(), "text": text}
        with self._lock:
            now = self.clock()
            self._write(topic, now, msg, now)
            if kind == "robot" and self.foxglove and self._cell is None:
                self._start_cell(text)
            self._flush_locked(now)

    def _start_cell(self, text: str) -> None:
        """Publish the robot in Foxglove's schemas from now on (a description elastocal
        cannot build alone, e.g. one naming a URDF file beside it, gives the log no 3-D view)."""
        try:
            robot = parse_robot(text, source="recorded robot")
        except InputError:
            return
        self._cell = CellPublisher(robot, self._publish)

    def drive_sample(self, joint: int, t_ns: int, position_rad: float, velocity_rad_s: float | None,
                     current_a: float | None, status: int | None = None) -> None:
        """One raw drive sample; ``t_ns`` is its acquisition time."""
        msg = {"joint": int(joint), "position_rad": float(position_rad),
               "velocity_rad_s": _finite_or_none(velocity_rad_s), "current_a": _finite_or_none(current_a),
               "status": None if status is None else int(status), "monotonic_ns": int(t_ns)}
        with self._lock:
            now = self.clock()
            self._write(lf.drive_topic(joint), t_ns, msg, now)
            if self._cell is not None:
                self._cell.measured_sample(joint, t_ns, msg["position_rad"], self._offset_ns)
            self._maybe_flush(now)

    def tracker_sample(self, t_ns: int, marker: str, xyz: Sequence[float],
                       environment: Sequence[tuple[str, float]] = ()) -> None:
        """One raw tracker measurement of ``marker`` [m]; ``t_ns`` is its acquisition time;
        ``environment`` the weather/refraction values the tracker reported with it
        (keys of ``logformat.TRACKER_ENVIRONMENT``)."""
        x, y, z = (float(v) for v in xyz)
        msg = {"marker": str(marker), "x": x, "y": y, "z": z}
        for key, value in environment:
            if key in lf.TRACKER_ENVIRONMENT and _finite_or_none(value) is not None:
                msg[key] = float(value)
        with self._lock:
            now = self.clock()
            msg["monotonic_ns"] = int(t_ns)
            self._write(lf.TOPIC_TRACKER, t_ns, msg, now)
            if self._cell is not None:
                self._cell.tracker_sample(str(marker), (x, y, z), int(t_ns), self._offset_ns)
            self._maybe_flush(now)

    def message(self, topic: str, t_ns: int, message: dict) -> None:
        """A message of one of the log's other topics (``logformat.TOPIC_SCHEMAS``: the stream's
        cycles, Foxglove's scenes) at acquisition time ``t_ns``; flushed like the samples."""
        if topic not in lf.TOPIC_SCHEMAS:
            raise ValueError(f"unknown topic {topic!r}")
        with self._lock:
            now = self.clock()
            self._write(topic, t_ns, message, now)
            self._maybe_flush(now)

    def event(self, kind: str, **fields: Any) -> int:
        """Record a procedure event stamped now; flushes the file. Returns its time [ns].
        Fields that are None or not finite numbers are left out."""
        clean = {k: _finite_or_none(v) for k, v in fields.items()}
        msg = {"kind": kind, **{k: v for k, v in clean.items() if v is not None}}
        with self._lock:
            now = self.clock()
            msg["monotonic_ns"] = now
            self._write(lf.TOPIC_EVENT, now, msg, now)
            if self._cell is not None:
                self._cell.event(msg, now + self._offset_ns)
            self._flush_locked(now)
        return now

    def copy(self, topic: str, log_time_ns: int, publish_time_ns: int, data: bytes) -> None:
        """Copy a message of an earlier log unchanged, its times included (resuming an
        interrupted procedure)."""
        if topic not in lf.TOPIC_SCHEMAS:
            raise InputError(f"unknown topic {topic!r} in the log being resumed")
        with self._lock:
            self._write_unix(topic, log_time_ns, bytes(data), publish_time_ns)
            self._maybe_flush(self.clock())
