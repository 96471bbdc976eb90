"""The simulated laser tracker: the line protocol of docs/tracker-protocol.md
served on TCP (127.0.0.1) and on a pseudo-terminal from ``os.openpty()``.

Positions come from :meth:`elastocal.sims.world.SimWorld.read_tracker` at the
measurement's own time (drift and noise of the simulated cell included). A
stream is clocked by the tracker: measurement ``k`` is taken at
``start + k / rate`` on the grid of the tracker's clock; when the sending thread falls behind it sends the
backlog, so no measurement is lost by the simulator itself.

Fault injection (tests): :meth:`SimTracker.break_beam`, :meth:`drop_lines`,
:meth:`corrupt_lines`, :meth:`stall`, :meth:`disconnect_all`.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import socket
import threading
import time
import tty

from elastocal.drivers.tracker_protocol import (
    STATUS_BEAM_BROKEN,
    STATUS_OK,
    Measurement,
    decode_line,
    encode_line,
    valid_name,
)
from elastocal.errors import ProtocolError
from elastocal.sims.tcp_listener import TcpListener
from elastocal.sims.world import SimWorld

MAX_RATE_HZ = 1000.0


class _Session:
    """One connection (a TCP client or the pty line)."""

    def __init__(self, tracker: "SimTracker", send, recv, close, name: str) -> None:
        self.tracker = tracker
        self._send_raw = send
        self._recv = recv
        self._close = close
        self.name = name
        self.target = tracker.markers[0]
        self._send_lock = threading.Lock()
        self._stream_stop = threading.Event()
        self._streamer: threading.Thread | None = None
        self._closed = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name=f"sim-tracker-{name}", daemon=True)

    def start(self) -> None:
        self._reader.start()

    def send(self, data: bytes) -> bool:
        with self._send_lock:
            try:
                self._send_raw(data)
                return True
            except OSError:
                self._closed.set()
                return False

    def _read_loop(self) -> None:
        buffer = b""
        while not self._closed.is_set():
            try:
                data = self._recv()
            except OSError:
                break
            if data is None:
                continue
            if data == b"":
                break
            buffer += data
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                self.tracker.wait_if_stalled()
                reply = self._handle(raw + b"\n")
                if reply is not None:
                    delay = self.tracker.reply_delay_s
                    if delay:
                        time.sleep(delay)
                    self.send(reply)
            if len(buffer) > 4096:
                buffer = b""
        self.stop_stream()
        self._closed.set()

    def _handle(self, raw: bytes) -> bytes | None:
        try:
            body = decode_line(raw)
        except ProtocolError:
            try:   # hosts may omit the checksum
                body = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                return encode_line("ERR 1 bad line")
            if "*" in body:
                return encode_line("ERR 1 bad checksum")
        words = body.split()
        if not words:
            return None
        cmd = words[0].upper()
        if cmd == "IDN?" and len(words) == 1:
            t = self.tracker
            return encode_line(f"IDN elastocal,SimTracker,{t.serial},0.1.0")
        if cmd == "TARGET" and len(words) == 2:
            name = words[1]
            if not valid_name(name) or name not in self.tracker.markers:
                return encode_line(f"ERR 2 unknown target {name[:32]}")
            self.target = name
            self.tracker.world.select_marker(name)      # a new reading begins (sims/world.py)
            return encode_line(f"OK TARGET {name}")
        if cmd == "MEAS?" and len(words) == 1:
            if self._streamer is not None:
                return encode_line("ERR 4 stream running")
            line = self.tracker.measurement_line(self.target, self.tracker.world.now_ns())
            return line if line is not None else None
        if cmd == "STREAM" and len(words) == 2:
            try:
                rate = float(words[1])
            except ValueError:
                return encode_line("ERR 3 bad rate")
            if not (0 < rate <= MAX_RATE_HZ) or not math.isfinite(rate):
                return encode_line(f"ERR 3 rate must be in (0, {MAX_RATE_HZ:g}]")
            self.stop_stream()
            self.send(encode_line(f"OK STREAM {rate:g}"))
            self._stream_stop.clear()
            self._streamer = threading.Thread(target=self._stream_loop, args=(rate,),
                                              name=f"sim-tracker-stream-{self.name}", daemon=True)
            self._streamer.start()
            return None
        if cmd == "STOP" and len(words) == 1:
            self.stop_stream()
            return encode_line("OK STOP")
        return encode_line(f"ERR 1 unknown command {body[:32]}")

    def _stream_loop(self, rate: float) -> None:
        world = self.tracker.world
        period_ns = int(round(1e9 / rate))
        # measurements fall on the tracker clock's grid of the period
        t0 = self.tracker.clock_origin_ns
        start = t0 + -(-(world.now_ns() - t0) // period_ns) * period_ns
        k = 0
        while not self._stream_stop.is_set() and not self._closed.is_set():
            now = world.now_ns()
            due = start + k * period_ns
            if now < due:
                self._stream_stop.wait((due - now) / 1e9)
                continue
            if self.tracker.stalled():
                # a stalled tracker keeps measuring but sends the backlog only afterwards
                self.tracker.wait_if_stalled()
                continue
            chunk = []
            while due <= now and len(chunk) < 200:
                line = self.tracker.measurement_line(self.target, due)
                if line is not None:
                    chunk.append(line)
                k += 1
                due = start + k * period_ns
            if chunk and not self.send(b"".join(chunk)):
                return

    def stop_stream(self) -> None:
        self._stream_stop.set()
        streamer = self._streamer
        if streamer is not None and streamer is not threading.current_thread():
            streamer.join(timeout=2.0)
        self._streamer = None

    def close(self) -> None:
        self._closed.set()
        self.stop_stream()
        try:
            self._close()
        except OSError:
            pass
        if self._reader.is_alive() and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)


class SimTracker:
    """A simulated tracker measuring the markers of ``world``."""

    def __init__(self, world: SimWorld, *, serial: str = "SIM0001", reply_delay_s: float = 0.0) -> None:
        self.world = world
        self.markers = world.markers
        self.serial = serial
        self.reply_delay_s = float(reply_delay_s)
        self._t0_ns = world.now_ns()
        self._lock = threading.Lock()
        self._seq = 0
        #: the instant the tracker's clock reads 0 [ns, world clock]
        self.clock_origin_ns = self._t0_ns
        self._beam_broken_until = 0.0
        self._drop = 0
        self._corrupt = 0
        self._stall_until = 0.0
        self._stall_event = threading.Event()
        self._stall_event.set()
        self._sessions: list[_Session] = []
        self._listener: TcpListener | None = None
        self._pty: tuple[int, int] | None = None
        self.tcp_port: int | None = None
        self.pty_path: str | None = None
        #: TCP connections accepted so far
        self.connections = 0

    # ---------------------------------------------------------- faults
    def break_beam(self, duration_s: float | None = None) -> None:
        """Interrupt the beam for ``duration_s`` (None: until :meth:`restore_beam`)."""
        with self._lock:
            self._beam_broken_until = math.inf if duration_s is None else time.monotonic() + duration_s

    def restore_beam(self) -> None:
        with self._lock:
            self._beam_broken_until = 0.0

    def drop_lines(self, count: int) -> None:
        """Take the next ``count`` measurements but never send them."""
        with self._lock:
            self._drop += count

    def corrupt_lines(self, count: int) -> None:
        """Garble one character of the next ``count`` measurement lines."""
        with self._lock:
            self._corrupt += count

    def stall(self, duration_s: float) -> None:
        """Neither measure nor answer for ``duration_s``."""
        with self._lock:
            self._stall_until = time.monotonic() + duration_s
            self._stall_event.clear()
        threading.Timer(duration_s, self._stall_event.set).start()

    def stalled(self) -> bool:
        with self._lock:
            return time.monotonic() < self._stall_until

    def wait_if_stalled(self) -> None:
        self._stall_event.wait()

    def disconnect_all(self) -> None:
        """Drop every TCP connection (the pty line stays)."""
        with self._lock:
            sessions = [s for s in self._sessions if s.name.startswith("tcp")]
            self._sessions = [s for s in self._sessions if s not in sessions]
        for s in sessions:
            s.close()

    # ------------------------------------------------------ measuring
    def measurement_line(self, target: str, t_ns: int) -> bytes | None:
        """The protocol line of one measurement at ``t_ns`` (None when it is dropped)."""
        with self._lock:
            self._seq += 1
            seq = self._seq
            broken = time.monotonic() < self._beam_broken_until
            drop = self._drop > 0
            if drop:
                self._drop -= 1
            corrupt = not drop and self._corrupt > 0
            if corrupt:
                self._corrupt -= 1
        if drop:
            return None
        t_us = max(0, (t_ns - self._t0_ns) // 1000)
        if broken:
            m = Measurement(seq, t_us, target, (math.nan, math.nan, math.nan), STATUS_BEAM_BROKEN)
        else:
            p = self.world.read_tracker(target, t_ns)
            m = Measurement(seq, t_us, target, (float(p[0]), float(p[1]), float(p[2])), STATUS_OK)
        line = encode_line(m.body())
        if corrupt:
            i = len(line) // 2
            line = line[:i] + bytes([line[i] ^ 0x01]) + line[i + 1:]
        return line

    # ------------------------------------------------------ transports
    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0: an ephemeral port); returns the port."""
        self._listener = TcpListener(host, port, self._accept, name="sim-tracker-accept")
        self.tcp_port = self._listener.port
        return self.tcp_port

    def _accept(self, conn: socket.socket, addr: tuple) -> None:
        conn.settimeout(0.1)

        def recv(c=conn):
            try:
                return c.recv(4096)
            except socket.timeout:
                return None

        def close(c=conn):
            with contextlib.suppress(OSError):    # the client may have closed it already
                c.shutdown(socket.SHUT_RDWR)
            c.close()

        session = _Session(self, conn.sendall, recv, close, f"tcp{addr[1]}")
        with self._lock:
            self._sessions = [s for s in self._sessions if not s._closed.is_set()]
            self._sessions.append(session)
            self.connections += 1
        session.start()

    def serve_pty(self) -> str:
        """Serve on a new pseudo-terminal; returns the device path to open (e.g. /dev/pts/3)."""
        master, slave = os.openpty()
        tty.setraw(slave)
        self._pty = (master, slave)
        self.pty_path = os.ttyname(slave)

        def recv():
            ready, _, _ = select.select([master], [], [], 0.1)
            if not ready:
                return None
            return os.read(master, 4096)

        def send(data: bytes) -> None:
            view = memoryview(data)
            while view:
                n = os.write(master, view)
                view = view[n:]

        session = _Session(self, send, recv, lambda: None, "pty")
        with self._lock:
            self._sessions.append(session)
        session.start()
        return self.pty_path

    def close(self) -> None:
        self._stall_event.set()
        if self._listener is not None:
            self._listener.close()
        with self._lock:
            sessions, self._sessions = self._sessions, []
        for s in sessions:
            s.close()
        if self._pty is not None:
            for fd in self._pty:
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._pty = None

    def __enter__(self) -> "SimTracker":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
