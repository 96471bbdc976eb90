"""Force/torque sensors: one small interface, the ATI Net F/T as its backend (``netft://HOST[:PORT]``).

A :class:`ForceSensor` streams in a thread of its own and keeps the newest sample; the
caller asks for it when it needs it (:meth:`ForceSensor.latest`) and judges its age. Wrenches
are in the sensor's own axes [N, N·m]; turning them into the robot's base axes needs the
robot's pose and is the caller's business.

The Net F/T speaks RDT (Raw Data Transfer) over UDP, port 49152: a request of 8 bytes
(``uint16`` header 0x1234, ``uint16`` command: 2 starts high-speed streaming, 0 stops;
``uint32`` sample count, 0 for unlimited), then a record of 36 bytes per sample
(``uint32`` rdt_sequence, ``uint32`` ft_sequence, ``uint32`` status, six ``int32`` counts
Fx Fy Fz Tx Ty Tz), all big-endian; forces are counts / counts-per-force, torques counts /
counts-per-torque (the sensor's calibration, 1,000,000 by default: ``?counts_per_force=``,
``?counts_per_torque=``). The ``NetFT`` package (2.0.1) speaks the same layout but cannot
serve here: its port is fixed at 49152 (a simulated sensor on a free port, or two tests at
once, cannot use it), its receive call has no timeout (an unplugged sensor blocks the
caller for ever), it returns raw counts and drops the status word. So the two ``struct``
layouts are written here (docs/stream.md gives the sources).
"""

from __future__ import annotations

import abc
import contextlib
import enum
import socket
import struct
import threading
import time
from dataclasses import dataclass

import numpy as np

from elastocal.drivers.samples import DeviceInfo
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import DeviceDisconnected, DeviceFault, DeviceTimeout, InputError

RDT_PORT = 49152
RDT_HEADER = 0x1234
RDT_REQUEST = struct.Struct(">HHI")
RDT_RECORD = struct.Struct(">III6i")


class RdtCommand(enum.IntEnum):
    STOP = 0
    START_HIGH_SPEED = 2


class SensorLost(DeviceTimeout):
    """The force sensor's samples stopped arriving."""


class SensorFault(DeviceFault):
    """The sensor reports an error in its status word (saturation, a broken gauge, ...)."""


@dataclass(frozen=True)
class WrenchSample:
    """One force/torque reading in the sensor's axes."""

    t_ns: int                 # arrival (time.monotonic_ns of this computer)
    sequence: int             # the sensor's record counter (RDT sequence)
    wrench: np.ndarray        # (6,) fx fy fz [N], tx ty tz [N·m]
    status: int = 0


@dataclass(frozen=True)
class NetFtParams:
    """A ``netft://`` URL parsed once."""

    host: str
    port: int
    counts_per_force: float
    counts_per_torque: float
    timeout_s: float

    @classmethod
    def from_url(cls, url: DeviceUrl, *, source: str = "url") -> "NetFtParams":
        if not url.host:
            raise InputError(f"{url.text}: give the sensor's address, e.g. netft://192.168.1.1", source=source)
        return cls(host=url.host, port=RDT_PORT if url.port is None else int(url.port),
                   counts_per_force=url.float_param("counts_per_force", 1e6, source=source),
                   counts_per_torque=url.float_param("counts_per_torque", 1e6, source=source),
                   timeout_s=url.float_param("timeout_s", 0.05, source=source))


def rdt_request(command: RdtCommand, count: int = 0) -> bytes:
    return RDT_REQUEST.pack(RDT_HEADER, int(command), int(count))


class ForceSensor(abc.ABC):
    """A streaming force/torque sensor (see the module docstring)."""

    def __init__(self, url: DeviceUrl) -> None:
        self.url = url
        self.name = "force sensor"
        self._lock = threading.Lock()
        self._latest: WrenchSample | None = None
        self._error: BaseException | None = None
        self._received = 0

    def latest(self) -> WrenchSample | None:
        """The newest sample (None before the first); raises what stopped the stream."""
        with self._lock:
            if self._error is not None:
                raise self._error
            return self._latest

    @property
    def received(self) -> int:
        return self._received

    def wait_first(self, timeout_s: float) -> WrenchSample:
        """Block until the first sample arrived; :class:`SensorLost` when none comes in time."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            s = self.latest()
            if s is not None:
                return s
            time.sleep(0.001)
        raise SensorLost(f"{self.name}: no sample within {timeout_s:g} s of starting ({self.url})")

    def _store(self, sample: WrenchSample) -> None:
        with self._lock:
            self._latest = sample
            self._received += 1

    def _fail(self, exc: BaseException) -> None:
        with self._lock:
            if self._error is None:
                self._error = exc

    @abc.abstractmethod
    def start(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    def identify(self) -> DeviceInfo:
        return DeviceInfo(kind="force", url=self.url.text, vendor="ATI", model="Net F/T (RDT)")

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class NetFtSensor(ForceSensor):
    """The ATI Net F/T over RDT (see the module docstring)."""

    def __init__(self, url: DeviceUrl, *, source: str = "url") -> None:
        super().__init__(url)
        self.params = url.settings if isinstance(url.settings, NetFtParams) else \
            NetFtParams.from_url(url, source=source)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.connect((self.params.host, self.params.port))
        except OSError as exc:
            self._sock.close()
            raise DeviceDisconnected(f"{self.name}: cannot reach {self.params.host}:{self.params.port}: "
                                     f"{exc.strerror}") from None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is not None:
            return
        self._sock.settimeout(self.params.timeout_s)
        self._send(rdt_request(RdtCommand.START_HIGH_SPEED, 0))
        self._thread = threading.Thread(target=self._receive_loop, name="netft-rdt", daemon=True)
        self._thread.start()

    def _send(self, data: bytes) -> None:
        try:
            self._sock.send(data)
        except OSError as exc:
            raise DeviceDisconnected(f"{self.name}: {exc.strerror or exc}") from None

    def decode(self, data: bytes, t_ns: int) -> WrenchSample:
        rdt_seq, _ft_seq, status, *counts = RDT_RECORD.unpack_from(data)
        p = self.params
        w = np.array(counts, dtype=float)
        w[:3] /= p.counts_per_force
        w[3:] /= p.counts_per_torque
        return WrenchSample(t_ns=t_ns, sequence=rdt_seq, wrench=w, status=status)

    def _receive_loop(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(1024)
            except socket.timeout:
                continue              # the caller judges the age of the latest sample
            except OSError as exc:
                if not self._stop.is_set():
                    self._fail(DeviceDisconnected(f"{self.name}: {exc.strerror or exc}"))
                return
            t_ns = time.monotonic_ns()
            if len(data) < RDT_RECORD.size:
                continue              # not an RDT record: ignored, its absence shows as age
            sample = self.decode(data, t_ns)
            if sample.status != 0:
                self._fail(SensorFault(f"{self.name}: status word 0x{sample.status:08X} (see the Net F/T's "
                                       "diagnostics page)"))
                return
            self._store(sample)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        with contextlib.suppress(OSError):      # the sensor may be gone already; closing goes on
            self._sock.send(rdt_request(RdtCommand.STOP, 0))
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        self._sock.close()
