"""One small interface per device kind, and the policy they share.

:class:`Drive`, :class:`Tracker` and :class:`CellController` own the policy
(timeouts, retries, reconnects, unit and plausibility checks, state checks);
a backend implements a few ``_methods`` that talk its protocol. A backend never
returns bad data silently: it raises a typed error from :mod:`elastocal.errors`
or, in a stream, records a :class:`~elastocal.drivers.samples.Gap`.

The samples, the device identity and the :class:`~elastocal.drivers.samples.Stream`
a backend fills are in :mod:`elastocal.drivers.samples`.
"""

from __future__ import annotations

import abc
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence, TypeVar

from elastocal.drivers.samples import DeviceInfo, DriveSample, Stream, TrackerSample
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    InputError,
    ProtocolError,
)

T = TypeVar("T")


class ModbusExceptionError(DeviceError):
    """A Modbus device answered with an exception response (``code``, e.g. 2 = illegal address)."""

    NAMES = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
             4: "device failure", 5: "acknowledge", 6: "device busy", 8: "memory parity error",
             10: "gateway path unavailable", 11: "gateway target failed to respond"}

    #: exception codes a later request may not get (the device or a gateway was busy or failed for a
    #: moment): retried like a timeout; the others (illegal function, address, value) say the
    #: register map is wrong and end the request at once
    TRANSIENT = frozenset({4, 5, 6, 10, 11})

    def __init__(self, message: str, code: int) -> None:
        self.code = code
        super().__init__(f"{message}: Modbus exception {code} ({self.NAMES.get(code, 'unknown')})")

    @property
    def transient(self) -> bool:
        return self.code in self.TRANSIENT


# ------------------------------------------------------------ shared links
class SharedLinks:
    """Connections several devices share (one CAN network per channel), owned
    by whoever opened the devices together and closed with it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: dict[tuple, object] = {}
        self._users: dict[tuple, int] = {}
        self._closers: dict[tuple, Callable[[], None]] = {}

    def acquire(self, key: tuple, factory: Callable[[], T], close: Callable[[T], None]) -> T:
        with self._lock:
            if key not in self._items:
                item = factory()
                self._items[key] = item
                self._closers[key] = lambda: close(item)
                self._users[key] = 0
            self._users[key] += 1
            return self._items[key]  # type: ignore[return-value]

    def release(self, key: tuple) -> None:
        with self._lock:
            if key not in self._items:
                return
            self._users[key] -= 1
            if self._users[key] > 0:
                return
            closer = self._closers.pop(key)
            del self._items[key], self._users[key]
        closer()

    def close(self) -> None:
        with self._lock:
            closers = list(self._closers.values())
            self._items.clear()
            self._users.clear()
            self._closers.clear()
        for closer in closers:
            closer()


# ------------------------------------------------------------------ devices
RETRYABLE = (DeviceTimeout, DeviceDisconnected, ProtocolError)


class Device(abc.ABC):
    """Policy shared by all device kinds: retries, reconnects, closing."""

    kind = "device"

    def __init__(self, url: DeviceUrl, *, name: str, timeout_s: float, retries: int) -> None:
        if not (timeout_s > 0 and math.isfinite(timeout_s)):
            raise InputError(f"{name}: timeout_s must be > 0, got {timeout_s!r}")
        if retries < 0:
            raise InputError(f"{name}: retries must be >= 0, got {retries!r}")
        self.url = url
        self.name = name
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self._closed = False
        self._streams: list[Stream] = []
        self._lock = threading.RLock()

    # ------------------------------------------------------------- policy
    def _call(self, what: str, fn: Callable[..., T], *args, **kwargs) -> T:
        """Run ``fn``; on a timeout, lost connection or garbled reply, reconnect
        if needed and try again up to ``retries`` times, then raise the last error."""
        if self._closed:
            raise DeviceDisconnected(f"{self.name}: device is closed")
        last: DeviceError | None = None
        for attempt in range(self.retries + 1):
            try:
                if isinstance(last, DeviceDisconnected):
                    self._reconnect()
                return fn(*args, **kwargs)
            except RETRYABLE as exc:
                last = exc
            except ModbusExceptionError as exc:
                if not exc.transient:
                    raise
                last = exc
        assert last is not None
        if isinstance(last, ModbusExceptionError):
            raise ModbusExceptionError(f"{last} ({what}, after {self.retries + 1} attempts)", last.code) from last
        raise type(last)(f"{last} ({what}, after {self.retries + 1} attempts)") from last

    def _reconnect(self) -> None:
        """Re-open the connection (backends with connections override this)."""

    def _register_stream(self, stream: Stream) -> Stream:
        self._streams.append(stream)
        return stream

    # -------------------------------------------------------------- public
    def identify(self) -> DeviceInfo:
        """Ask the device who it is."""
        return self._call("identify", self._identify)

    @abc.abstractmethod
    def _identify(self) -> DeviceInfo: ...

    def close(self) -> None:
        if self._closed:
            return
        try:
            for s in list(self._streams):
                s.close()
        finally:
            self._closed = True
            self._close()

    @abc.abstractmethod
    def _close(self) -> None: ...

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} {self.url}>"


class Drive(Device):
    """A joint drive: reads motor current and position (and velocity, torque)."""

    kind = "drive"

    def __init__(self, url: DeviceUrl, *, joint: int, timeout_s: float, retries: int,
                 max_current_a: float = 200.0, max_rate_hz: float = 1000.0) -> None:
        super().__init__(url, name=f"drive J{joint}", timeout_s=timeout_s, retries=retries)
        self.joint = joint
        self.max_current_a = float(max_current_a)
        self.max_rate_hz = float(max_rate_hz)

    def read(self) -> DriveSample:
        """One reading on demand; raises DeviceFault if the drive is not
        operational, and checks the values' plausibility."""
        return self.check_sample(self._call("read", self._read))

    def stream(self, rate_hz: float) -> Stream[DriveSample]:
        """Start streaming at ``rate_hz``; close the stream (or use ``with``) to stop."""
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise InputError(f"{self.name}: rate_hz must be > 0, got {rate_hz!r}")
        if rate_hz > self.max_rate_hz:
            raise InputError(f"{self.name}: {rate_hz:g} Hz is above this backend's maximum "
                             f"{self.max_rate_hz:g} Hz")
        if self._closed:
            raise DeviceDisconnected(f"{self.name}: device is closed")
        return self._register_stream(self._stream(float(rate_hz)))

    def check_sample(self, s: DriveSample) -> DriveSample:
        """Unit and plausibility checks every sample passes (raises ProtocolError)."""
        isfinite = math.isfinite
        if not (isfinite(s.position_rad) and isfinite(s.current_a)
                and (s.velocity_rad_s is None or isfinite(s.velocity_rad_s))
                and (s.torque_nm is None or isfinite(s.torque_nm))):
            raise ProtocolError(f"{self.name}: non-finite value in {s}")
        if abs(s.current_a) > self.max_current_a:
            raise ProtocolError(f"{self.name}: current {s.current_a:.6g} A is above max_current_a "
                                f"{self.max_current_a:g} A; check the current scale and unit")
        if abs(s.position_rad) > 8 * math.pi:
            raise ProtocolError(f"{self.name}: position {s.position_rad:.6g} rad is beyond 4 turns; "
                                "check the position scale and unit")
        return s

    @abc.abstractmethod
    def _read(self) -> DriveSample: ...

    @abc.abstractmethod
    def _stream(self, rate_hz: float) -> Stream[DriveSample]: ...


class Tracker(Device):
    """A laser tracker measuring one marker (reflector) at a time."""

    kind = "tracker"
    #: the farthest plausible measurement [m]
    MAX_RANGE_M = 160.0

    def __init__(self, url: DeviceUrl, *, markers: Sequence[str], timeout_s: float, retries: int) -> None:
        super().__init__(url, name="tracker", timeout_s=timeout_s, retries=retries)
        if not markers:
            raise InputError("tracker: at least one marker name is needed")
        self.markers = tuple(markers)
        self._marker = self.markers[0]

    @property
    def marker(self) -> str:
        """The marker the tracker currently measures."""
        return self._marker

    def select(self, marker: str) -> None:
        """Point the tracker at ``marker`` (one of the configured markers)."""
        if marker not in self.markers:
            raise InputError(f"tracker: unknown marker {marker!r}; configured: {', '.join(self.markers)}")
        self._call("select", self._select, marker)
        self._marker = marker

    def measure(self) -> TrackerSample:
        """One measurement of the current marker; DeviceFault when the beam is broken."""
        return self.check_sample(self._call("measure", self._measure))

    def stream(self, rate_hz: float) -> Stream[TrackerSample]:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise InputError(f"tracker: rate_hz must be > 0, got {rate_hz!r}")
        if self._closed:
            raise DeviceDisconnected("tracker: device is closed")
        return self._register_stream(self._stream(float(rate_hz)))

    def check_sample(self, s: TrackerSample) -> TrackerSample:
        p = s.tracker_p_marker
        if len(p) != 3 or not all(math.isfinite(v) for v in p):
            raise ProtocolError(f"tracker: non-finite position in measurement {s.seq}")
        if max(abs(v) for v in p) > self.MAX_RANGE_M:
            raise ProtocolError(f"tracker: position {p} is beyond {self.MAX_RANGE_M:g} m; positions are metres")
        return s

    @abc.abstractmethod
    def _select(self, marker: str) -> None: ...

    @abc.abstractmethod
    def _measure(self) -> TrackerSample: ...

    @abc.abstractmethod
    def _stream(self, rate_hz: float) -> Stream[TrackerSample]: ...


# ----------------------------------------------------------- cell controller
STATUS_IN_POSITION = 0x01
STATUS_RUN_DONE = 0x02
STATUS_BUSY = 0x04
STATUS_FAULT = 0x08

COMMAND_MOVE_POSE = 1
COMMAND_MOVE_JOINTS = 2
COMMAND_RUN_UV = 3
COMMAND_RUN_VU = 4
COMMAND_NAMES = {COMMAND_MOVE_POSE: "move to pose", COMMAND_MOVE_JOINTS: "move to joint targets",
                 COMMAND_RUN_UV: "run UV", COMMAND_RUN_VU: "run VU"}


@dataclass(frozen=True)
class ControllerStatus:
    ack: int                        # last request sequence the controller accepted
    status: int                     # status bits (STATUS_*)
    error: int = 0                  # controller error code when faulted
    q: tuple[float, ...] | None = None   # joint positions [rad] when the map has them

    @property
    def in_position(self) -> bool:
        return bool(self.status & STATUS_IN_POSITION)

    @property
    def run_done(self) -> bool:
        return bool(self.status & STATUS_RUN_DONE)

    @property
    def busy(self) -> bool:
        return bool(self.status & STATUS_BUSY)

    @property
    def fault(self) -> bool:
        return bool(self.status & STATUS_FAULT)


class CellController(Device):
    """The robot cell's controller: moves to poses and runs paths on request.

    Handshake (docs/cell-config.md): write the parameters, then the command,
    then a new ``sequence`` number; the controller copies it to ``ack`` when
    it accepts, sets ``busy`` while moving, then ``in_position`` (moves) or
    ``run_done`` (runs); ``fault`` with an ``error`` code when it cannot.
    """

    kind = "controller"
    POLL_S = 0.01

    def __init__(self, url: DeviceUrl, *, timeout_s: float, retries: int, move_timeout_s: float) -> None:
        super().__init__(url, name="controller", timeout_s=timeout_s, retries=retries)
        self.move_timeout_s = float(move_timeout_s)
        self._sequence: int | None = None

    def status(self) -> ControllerStatus:
        return self._call("status", self._status)

    def move_to_pose(self, number: int, *, timeout_s: float | None = None) -> ControllerStatus:
        """Request taught pose ``number``; return when the controller reports in position."""
        if isinstance(number, bool) or not isinstance(number, int) or not 0 < number < 65536:
            raise InputError(f"controller: pose number must be 1..65535, got {number!r}")
        return self._handshake(COMMAND_MOVE_POSE, {"pose": number}, STATUS_IN_POSITION, timeout_s)

    def move_joints(self, q: Sequence[float], *, timeout_s: float | None = None) -> ControllerStatus:
        """Request joint targets ``q`` [rad]; return when in position."""
        q = tuple(float(v) for v in q)
        if not q or not all(math.isfinite(v) for v in q):
            raise InputError(f"controller: joint targets need one finite value per joint, got {q}")
        return self._handshake(COMMAND_MOVE_JOINTS, {"target": q}, STATUS_IN_POSITION, timeout_s)

    def run(self, path: int, direction: str, *, speed_rad_s: float | None = None,
            timeout_s: float | None = None) -> ControllerStatus:
        """Run taught ``path`` forward (``"UV"``) or backward (``"VU"``); return when done."""
        if direction not in ("UV", "VU"):
            raise InputError(f"controller: direction must be 'UV' or 'VU', got {direction!r}")
        if isinstance(path, bool) or not isinstance(path, int) or not 0 < path < 65536:
            raise InputError(f"controller: path number must be 1..65535, got {path!r}")
        params: dict[str, object] = {"path": path}
        if speed_rad_s is not None:
            if not (speed_rad_s > 0 and math.isfinite(speed_rad_s)):
                raise InputError(f"controller: speed_rad_s must be > 0, got {speed_rad_s!r}")
            params["speed"] = float(speed_rad_s)
        command = COMMAND_RUN_UV if direction == "UV" else COMMAND_RUN_VU
        return self._handshake(command, params, STATUS_RUN_DONE, timeout_s)

    def _handshake(self, command: int, params: dict[str, object], done_bit: int,
                   timeout_s: float | None) -> ControllerStatus:
        what = COMMAND_NAMES[command]
        timeout = self.move_timeout_s if timeout_s is None else float(timeout_s)
        with self._lock:
            if self._sequence is None:
                self._sequence = self.status().ack
            seq = (self._sequence % 65535) + 1
            self._call(what, self._request, command, params, seq)
            self._sequence = seq
            deadline = time.monotonic() + timeout
            accepted = False
            while True:
                st = self.status()
                if st.ack == seq:
                    accepted = True
                    if st.fault:
                        raise DeviceFault(f"controller: {what} failed, error code {st.error}")
                    if st.status & done_bit and not st.busy:
                        return st
                if time.monotonic() > deadline:
                    state = "did not accept the request" if not accepted else "did not finish"
                    raise DeviceTimeout(f"controller: {what} {state} within {timeout:g} s")
                time.sleep(self.POLL_S)

    @abc.abstractmethod
    def _status(self) -> ControllerStatus: ...

    @abc.abstractmethod
    def _request(self, command: int, params: dict[str, object], sequence: int) -> None: ...


# ----------------------------------------------------------------- helpers
def close_all(items: Iterable[object]) -> None:
    """Close every item even if some fail; re-raise the first failure."""
    first: BaseException | None = None
    for item in items:
        try:
            item.close()  # type: ignore[attr-defined]
        except BaseException as exc:  # noqa: BLE001 - re-raised below
            if first is None:
                first = exc
    if first is not None:
        raise first
