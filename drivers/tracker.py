"""Laser tracker over TCP or a serial line (``tracker+tcp://``, ``tracker+serial://``).

Speaks the line protocol of docs/tracker-protocol.md
(:mod:`elastocal.drivers.tracker_protocol`). One reader thread per connection
splits the byte stream into lines: measurement lines of a running stream go
to the :class:`~elastocal.drivers.base.Stream`, everything else answers the
pending command.

Stream policy (nothing is delivered that the protocol does not vouch for):

* the sequence number must grow by one per measurement: a jump is a recorded
  gap (``lost lines``, or ``malformed line`` when garbled lines were dropped in
  between); a step backwards ends the stream with :class:`ProtocolError`;
* ``BEAM_BROKEN`` / ``NO_TARGET`` lines are a recorded gap for as long as they
  last;
* more than ``MAX_BAD_LINES`` garbled lines in a row end the stream with
  :class:`ProtocolError`;
* a lost connection is re-opened (``retries`` attempts within ``timeout_s``
  each) and the stream restarted; the measurements missed meanwhile are a gap
  (counted from the tracker's clock); failing that, the stream ends with
  :class:`DeviceDisconnected`; ``timeout_s`` without any line ends it with
  :class:`DeviceTimeout`.

A command that timed out may still be answered later: the next command first
re-opens the connection (TCP) or the port (serial, input flushed), so a late
reply never answers a newer request.

``t_ns`` of a streamed sample is the tracker's own measurement time mapped
onto ``time.monotonic_ns()`` (offset = the smallest receive delay seen), so
samples are not bunched by network buffering; a single measurement is stamped
at the middle of its request and reply. Two things keep the stamps strictly
increasing on the tracker's grid when lines arrive late (a loaded host reads a
backlog of lines at once): the lines of one read share its receive time, so
the offset is taken from the newest of them before any is stamped (each older
one would otherwise see a larger delay, and the smallest-delay rule would
stamp them all with the one receive time); and when a later line shows a
smaller delay than the stamps so far assumed, the offset in use slews towards
it by at most half the tracker's interval per sample (:data:`MAX_SLEW`), never
stepping back behind a sample already delivered.
"""

from __future__ import annotations

import queue
import socket
import threading
import time

import serial

from elastocal.drivers.base import Tracker
from elastocal.drivers.samples import DeviceInfo, Stream, TrackerSample
from elastocal.drivers.config import TrackerConfig
from elastocal.drivers.tracker_protocol import (
    STATUS_OK,
    Measurement,
    decode_line,
    encode_line,
    parse_measurement,
    valid_name,
)
from elastocal.errors import BeamBroken, DeviceDisconnected, DeviceError, DeviceTimeout, InputError, ProtocolError

MAX_BAD_LINES = 10
#: bytes of a typical measurement line, for the serial bandwidth check
LINE_BYTES = 72
#: the fastest stream the protocol allows
MAX_RATE_HZ = 1000.0
#: the largest share of the tracker's interval between two samples by which the offset in use
#: may move back towards a smaller receive delay (< 1: the stamps stay strictly increasing)
MAX_SLEW = 0.5


class _TcpTransport:
    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        self.where = f"{host}:{port}"
        try:
            self.sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise DeviceDisconnected(f"tracker {self.where}: cannot connect: {exc}") from exc
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.settimeout(0.05)

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise DeviceDisconnected(f"tracker {self.where}: send failed: {exc}") from exc

    def read(self) -> bytes | None:
        """Some bytes, None when nothing came within the poll interval; DeviceDisconnected on EOF."""
        try:
            data = self.sock.recv(65536)
        except socket.timeout:
            return None
        except OSError as exc:
            raise DeviceDisconnected(f"tracker {self.where}: connection lost: {exc}") from exc
        if not data:
            raise DeviceDisconnected(f"tracker {self.where}: connection closed by the tracker")
        return data

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class _SerialTransport:
    def __init__(self, path: str, baud: int, timeout_s: float) -> None:
        self.where = path
        try:
            self.port = serial.Serial(path, baudrate=baud, timeout=0.05, write_timeout=timeout_s)
            self.port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnected(f"tracker {path}: cannot open: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnected(f"tracker {self.where}: write failed: {exc}") from exc

    def read(self) -> bytes | None:
        try:
            data = self.port.read(max(1, self.port.in_waiting))
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnected(f"tracker {self.where}: read failed: {exc}") from exc
        return data or None

    def close(self) -> None:
        self.port.close()


class _StreamState:
    def __init__(self, stream: Stream[TrackerSample], rate_hz: float) -> None:
        self.stream = stream
        self.rate_hz = rate_hz
        self.next_seq: int | None = None
        self.bad_since_good = 0
        self.bad_in_row = 0
        self.blocked = 0
        self.blocked_reason = ""
        #: the smallest receive delay seen (host time - tracker time) [ns]
        self.offset_ns: int | None = None
        #: the offset the stamps use: the smallest delay, reached by slewing (module docstring)
        self.applied_offset_ns: int | None = None
        self.last_t_us: int | None = None
        self.last_line_ns = time.monotonic_ns()
        self.reconnected = False


class LineTracker(Tracker):
    """A tracker speaking the elastocal tracker line protocol."""

    def __init__(self, config: TrackerConfig, *, links=None) -> None:
        super().__init__(config.url, markers=config.markers, timeout_s=config.timeout_s, retries=config.retries)
        for m in config.markers:
            if not valid_name(m):
                raise InputError(f"tracker: marker name {m!r} cannot be sent in the protocol "
                                 "(letters, digits, _ . - ; at most 32)")
        self.config = config
        self.baud = config.url.settings.baud if config.url.scheme == "tracker+serial" else None
        self._replies: queue.Queue = queue.Queue()
        self._cmd_lock = threading.Lock()
        self._state: _StreamState | None = None
        self._state_lock = threading.Lock()
        self._transport = None
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._buffer = b""
        self._resync = False
        self._call("open", self._open)
        try:
            self._call("select", self._select, self.markers[0])
        except BaseException:
            self._shutdown_transport()
            raise

    # --------------------------------------------------------- transport
    def _make_transport(self):
        settings = self.config.url.settings      # parsed once with the URL (drivers.url_params)
        if self.config.url.scheme == "tracker+tcp":
            return _TcpTransport(settings.host, settings.port, self.timeout_s)
        return _SerialTransport(settings.device, settings.baud, self.timeout_s)

    def _open(self) -> None:
        self._shutdown_transport()
        self._resync = False
        while not self._replies.empty():
            self._replies.get_nowait()
        self._transport = self._make_transport()
        self._buffer = b""
        self._stop_reader.clear()
        self._reader = threading.Thread(target=self._read_loop, name="tracker-reader", daemon=True)
        self._reader.start()

    def _reconnect(self) -> None:
        self._open()

    def _shutdown_transport(self) -> None:
        self._stop_reader.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        self._reader = None
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    # ------------------------------------------------------------ reader
    def _read_loop(self) -> None:
        transport = self._transport
        while not self._stop_reader.is_set():
            try:
                data = transport.read()
            except DeviceDisconnected as exc:
                if self._state is not None and not self._stop_reader.is_set():
                    transport = self._resume_stream(exc)
                    if transport is None:
                        return
                    continue
                self._replies.put(exc)
                return
            now = time.monotonic_ns()
            if data is None:
                self._check_silence(now)
                continue
            self._buffer += data
            if b"\n" in self._buffer:
                *lines, self._buffer = self._buffer.split(b"\n")
                self._on_lines([raw + b"\n" for raw in lines], now)
            if len(self._buffer) > 4096:
                self._buffer = b""
                self._on_bad_line(ProtocolError("tracker: no line end in 4096 bytes"))

    def _check_silence(self, now: int) -> None:
        state = self._state
        if state is None:
            return
        if (now - state.last_line_ns) / 1e9 > self.timeout_s:
            state.last_line_ns = now
            state.stream.fail(DeviceTimeout(f"tracker: no line for {self.timeout_s:g} s while streaming"))
            self._state = None

    def _on_lines(self, lines: list[bytes], rx_ns: int) -> None:
        """The lines of one read, all received at ``rx_ns``, in order."""
        state = self._state
        items: list[str | Measurement | ProtocolError] = []
        for raw in lines:
            try:
                body = decode_line(raw)
                items.append(parse_measurement(body) if body.startswith("M ") and state is not None else body)
            except ProtocolError as exc:
                items.append(exc)
        if state is not None:      # the newest measurement of the read has its smallest delay
            newest = [m.t_us for m in items if isinstance(m, Measurement)]
            if newest:
                self._observe_delay(state, rx_ns - max(newest) * 1000)
        for item in items:
            if isinstance(item, ProtocolError):
                self._on_bad_line(item)
            elif isinstance(item, Measurement):
                if self._state is state:        # a failed stream takes no more lines
                    self._on_measurement(state, item, rx_ns)
            else:
                self._replies.put((item, rx_ns))

    @staticmethod
    def _observe_delay(state: _StreamState, delay_ns: int) -> None:
        if state.offset_ns is None or delay_ns < state.offset_ns:
            state.offset_ns = delay_ns
        if state.applied_offset_ns is None:
            state.applied_offset_ns = state.offset_ns

    @staticmethod
    def _stamp(state: _StreamState, device_ns: int, previous_device_ns: int | None) -> int:
        """``device_ns`` on the host's clock, the offset in use slewed towards the smallest delay."""
        if previous_device_ns is not None and state.applied_offset_ns > state.offset_ns:
            step = min(state.applied_offset_ns - state.offset_ns,
                       int(MAX_SLEW * max(device_ns - previous_device_ns, 0)))
            state.applied_offset_ns -= step
        else:
            state.applied_offset_ns = state.offset_ns
        return device_ns + state.applied_offset_ns

    def _on_bad_line(self, exc: ProtocolError) -> None:
        state = self._state
        if state is None:
            self._replies.put(exc)
            return
        state.bad_since_good += 1
        state.bad_in_row += 1
        if state.bad_in_row > MAX_BAD_LINES:
            state.stream.fail(ProtocolError(f"{exc} ({state.bad_in_row} bad lines in a row)"))
            self._state = None

    def _flush_blocked(self, state: _StreamState, end_ns: int) -> None:
        if state.blocked:
            state.stream.gap(state.blocked, state.blocked_reason, end_ns=end_ns)
            state.blocked = 0

    def _on_measurement(self, state: _StreamState, m: Measurement, rx_ns: int) -> None:
        state.last_line_ns = rx_ns
        state.bad_in_row = 0
        if state.next_seq is not None:
            if m.seq < state.next_seq:
                state.stream.fail(ProtocolError(f"tracker: sequence went back from {state.next_seq - 1} to {m.seq}"))
                self._state = None
                return
            lost = m.seq - state.next_seq
            if state.reconnected and state.last_t_us is not None:
                # measurements not taken while the connection was down do not use sequence numbers
                by_time = int(round((m.t_us - state.last_t_us) / 1e6 * state.rate_hz)) - 1
                lost = max(lost, by_time)
            if lost:
                self._flush_blocked(state, rx_ns)
                reason = ("reconnected" if state.reconnected else
                          "malformed line" if state.bad_since_good else "lost lines")
                state.stream.gap(lost, reason, end_ns=rx_ns)
        state.reconnected = False
        state.bad_since_good = 0
        state.next_seq = m.seq + 1
        previous_us, state.last_t_us = state.last_t_us, m.t_us
        device_ns = m.t_us * 1000
        self._observe_delay(state, rx_ns - device_ns)
        t_ns = self._stamp(state, device_ns, None if previous_us is None else previous_us * 1000)
        if m.status != STATUS_OK:
            reason = "beam broken" if m.status == "BEAM_BROKEN" else "no target"
            if state.blocked and state.blocked_reason != reason:
                self._flush_blocked(state, rx_ns)
            state.blocked += 1
            state.blocked_reason = reason
            return
        self._flush_blocked(state, t_ns)
        try:
            sample = self.check_sample(TrackerSample(t_ns, m.seq, m.t_us / 1e6, m.target, m.xyz_m))
        except ProtocolError as exc:
            state.stream.fail(exc)
            self._state = None
            return
        state.stream.emit(sample, t_ns)

    def _resume_stream(self, cause: DeviceDisconnected):
        """Re-open the connection and restart the stream; None when that fails."""
        state = self._state
        last: DeviceError = cause
        for attempt in range(self.retries + 1):
            if self._stop_reader.is_set():
                return None
            try:
                old = self._transport
                if old is not None:
                    old.close()
                transport = self._make_transport()
                self._transport = transport
                self._buffer = b""
                self._handshake(transport, f"TARGET {self._marker}", "OK TARGET")
                self._handshake(transport, f"STREAM {state.rate_hz:g}", "OK STREAM")
                state.reconnected = True
                state.last_line_ns = time.monotonic_ns()
                return transport
            except DeviceError as exc:
                last = exc
                time.sleep(min(0.05 * (attempt + 1), self.timeout_s))
        state.stream.fail(DeviceDisconnected(f"{last} (stream could not be resumed after "
                                             f"{self.retries + 1} attempts)"))
        self._state = None
        return None

    def _handshake(self, transport, command: str, expect: str) -> None:
        """Send a command from the reader thread and wait for its reply there."""
        transport.write(encode_line(command))
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            data = transport.read()
            if data is None:
                continue
            self._buffer += data
            while b"\n" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\n", 1)
                body = decode_line(raw + b"\n")
                if body.startswith(expect):
                    return
                if body.startswith("ERR"):
                    raise DeviceError(f"tracker: {command!r} refused: {body}")
        raise DeviceTimeout(f"tracker: no reply to {command!r} within {self.timeout_s:g} s")

    # ---------------------------------------------------------- commands
    def _command(self, command: str, expect: str) -> tuple[str, int]:
        if self._resync or self._transport is None:
            self._open()
        with self._cmd_lock:
            while not self._replies.empty():
                self._replies.get_nowait()
            self._transport.write(encode_line(command))
            deadline = time.monotonic() + self.timeout_s
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._resync = True
                    raise DeviceTimeout(f"tracker: no reply to {command!r} within {self.timeout_s:g} s")
                try:
                    item = self._replies.get(timeout=remaining)
                except queue.Empty:
                    continue
                if isinstance(item, DeviceError):
                    raise item
                body, rx_ns = item
                if body.startswith("ERR"):
                    raise DeviceError(f"tracker: {command!r} refused: {body}")
                if body.startswith(expect):
                    return body, rx_ns
                # a stray line (e.g. a measurement from a stream being stopped): ignore it

    def _identify(self) -> DeviceInfo:
        body, _ = self._command("IDN?", "IDN ")
        fields = body[4:].split(",")
        if len(fields) != 4:
            raise ProtocolError(f"tracker: bad identification {body!r}")
        vendor, model, serial_no, firmware = fields
        return DeviceInfo(kind="tracker", url=self.url.text, vendor=vendor, model=model, serial=serial_no,
                          revision=firmware, details=(("markers", ", ".join(self.markers)),
                                                      ("target", self._marker)))

    def _select(self, marker: str) -> None:
        self._command(f"TARGET {marker}", "OK TARGET")

    def _measure(self) -> TrackerSample:
        if self._state is not None:
            raise DeviceError("tracker: a stream is running; read it or close it first")
        t0 = time.monotonic_ns()
        body, rx_ns = self._command("MEAS?", "M ")
        m = parse_measurement(body)
        if m.status != STATUS_OK:
            raise BeamBroken(f"tracker: {m.status.lower().replace('_', ' ')} (measurement {m.seq})")
        return TrackerSample((t0 + rx_ns) // 2, m.seq, m.t_us / 1e6, m.target, m.xyz_m)

    def _stream(self, rate_hz: float) -> Stream[TrackerSample]:
        if rate_hz > MAX_RATE_HZ:
            raise InputError(f"tracker: {rate_hz:g} Hz is above the protocol's {MAX_RATE_HZ:g} Hz")
        if self.baud is not None:
            need = LINE_BYTES * 10 * rate_hz
            if need > self.baud:
                raise InputError(f"tracker: streaming at {rate_hz:g} Hz needs about {need / 1000:.0f} kbit/s; "
                                 f"the serial line runs at {self.baud} baud (at most "
                                 f"{self.baud / (LINE_BYTES * 10):.0f} Hz)")
        if self._state is not None:
            raise DeviceError("tracker: a stream is already running")
        stream: Stream[TrackerSample] = Stream("tracker", rate_hz, stop=self._stop_stream)
        self._state = _StreamState(stream, rate_hz)
        try:
            self._call("stream", self._command, f"STREAM {rate_hz:g}", "OK STREAM")
        except BaseException:
            self._state = None
            raise
        return stream

    def _stop_stream(self) -> None:
        state, self._state = self._state, None
        if state is not None:
            self._flush_blocked(state, time.monotonic_ns())
        try:
            self._command("STOP", "OK STOP")
        except DeviceError:
            # the connection is gone or the tracker does not answer: reopen so
            # the next command starts from a clean line
            try:
                self._open()
            except DeviceError:
                pass

    def _close(self) -> None:
        if self._state is not None:
            self._stop_stream()
        self._shutdown_transport()
