"""Externally guided motion: the robot controller asks, every cycle, where the robot goes next.

One small interface for the controllers' real-time guidance channels (ABB EGM, KUKA RSI):
the controller sends its state each interpolation cycle (4 ms, or 12 ms for RSI's slow
mode) over UDP; the external computer answers with the joint targets of that cycle. The
computer is the UDP *server* of both: the controller is configured with its address and
sends first, the answer goes back to where the state came from.

:class:`Guidance` owns the policy (units, plausibility, the cycle budget, typed faults);
a backend implements the protocol of one controller. Angles are radians at this
interface whatever the wire carries (degrees for both EGM and RSI).
"""

from __future__ import annotations

import abc
import dataclasses
import enum
import math
import socket
import struct
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.drivers.samples import DeviceInfo
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import DeviceDisconnected, DeviceFault, DeviceTimeout, InputError, ProtocolError


class GuidanceKind(enum.Enum):
    """Which controller channel: the URL scheme of the backend."""

    EGM = "egm"
    RSI = "rsi"


class ControllerLost(DeviceTimeout):
    """The controller's state messages stopped (a cable, the robot program ended, a stop)."""


class ControllerRefused(DeviceFault):
    """The controller says it does not follow: motors off, its program stopped, guidance off."""


@dataclass(frozen=True)
class GuidanceParams:
    """A guidance URL parsed once: where to listen and how the controller runs."""

    kind: GuidanceKind
    host: str                      # the address to bind on this computer
    port: int                      # 0: any free port (simulated controllers only)
    cycle_s: float                 # the controller's interpolation cycle
    timeout_s: float               # no state message this long: ControllerLost
    #: amperes per unit of the current the controller reports (RSI MACur, EGM test signals)
    current_scale_a: float
    sen_type: str = "ImFree"       # RSI: the name in <Sen Type="...">, as in the controller's config

    @classmethod
    def from_url(cls, url: DeviceUrl, *, source: str = "url") -> "GuidanceParams":
        kind = GuidanceKind(url.scheme)
        if url.port is None:
            raise InputError(f"{url.text}: give the address and UDP port to listen on, e.g. "
                             f"{url.scheme}://0.0.0.0:{6510 if kind is GuidanceKind.EGM else 59152}",
                             source=source)
        host = url.host or "0.0.0.0"
        if kind is GuidanceKind.RSI:
            cycle_ms = url.int_param("cycle_ms", 4, source=source, low=1, high=100)
            if cycle_ms not in (4, 12):
                raise InputError(f"cycle_ms={cycle_ms} in {url.text}: RSI runs every 4 ms (IPO_FAST) or 12 ms (IPO)",
                                 source=source)
        else:
            cycle_ms = url.int_param("cycle_ms", 4, source=source, low=4, high=100)
        cycle_s = cycle_ms / 1000.0
        return cls(kind=kind, host=host, port=int(url.port), cycle_s=cycle_s,
                   timeout_s=url.float_param("timeout_s", 0.5, source=source),
                   current_scale_a=url.float_param("current_scale_a", 1.0, source=source),
                   sen_type=url.param("sen_type", "ImFree") or "ImFree")


@dataclass(frozen=True)
class ControllerState:
    """One state message of the controller, in SI units."""

    t_ns: int                      # when it arrived (time.monotonic_ns of this computer)
    sequence: int                  # the controller's counter (EGM header seqno, RSI IPOC)
    q: np.ndarray                  # motor-side joint coordinates the controller measures [rad]
    currents_a: np.ndarray | None  # motor currents [A] when the controller sends them
    controller_time_ms: int        # the controller's own clock [ms] (EGM header tm, RSI IPOC)
    late_packets: int = 0          # the controller's count of late answers (RSI Delay), when it sends one
    ready: bool = True             # motors on and the guidance program running
    #: older state messages that were waiting behind this one, left unanswered (this computer fell behind)
    skipped: int = 0


class Guidance(abc.ABC):
    """A real-time guidance channel to a robot controller (see the module docstring)."""

    kind: GuidanceKind

    def __init__(self, url: DeviceUrl, *, n_joints: int, source: str = "url") -> None:
        if n_joints < 1:
            raise InputError(f"the robot needs at least one joint, got {n_joints}")
        self.url = url
        # parsed once with the URL; a DeviceUrl made by hand (no settings) is parsed here
        self.params = url.settings if isinstance(url.settings, GuidanceParams) else \
            GuidanceParams.from_url(url, source=source)
        self.n_joints = int(n_joints)
        self._check_joints()
        self.name = f"{self.kind.value} controller"
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        # the kernel's arrival time of each message: the cycle's response time counts from there,
        # whatever kept this process from reading it at once
        self._kernel_stamps = hasattr(socket, "SO_TIMESTAMPNS")
        if self._kernel_stamps:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_TIMESTAMPNS, 1)
        try:
            self._sock.bind((self.params.host, self.params.port))
        except OSError as exc:
            self._sock.close()
            raise DeviceDisconnected(f"{self.name}: cannot listen on {self.params.host}:{self.params.port}: "
                                     f"{exc.strerror}") from None
        self._peer: tuple[str, int] | None = None
        self._last: ControllerState | None = None
        self._closed = False

    def _check_joints(self) -> None:
        """Refuse a robot the protocol cannot carry (backends override)."""

    @property
    def address(self) -> tuple[str, int]:
        """The (host, port) this computer listens on (the port chosen when the URL gave 0)."""
        return self._sock.getsockname()

    @property
    def cycle_s(self) -> float:
        return self.params.cycle_s

    def identify(self) -> DeviceInfo:
        host, port = self.address
        return DeviceInfo(kind="guidance", url=self.url.text, vendor={"egm": "ABB", "rsi": "KUKA"}[self.kind.value],
                          model={"egm": "Externally Guided Motion", "rsi": "Robot Sensor Interface"}[self.kind.value],
                          details=(("listening", f"{host}:{port}"), ("cycle_ms", f"{self.cycle_s * 1e3:g}")))

    # ------------------------------------------------------------------ cycle
    def receive(self, timeout_s: float | None = None) -> ControllerState:
        """The controller's newest state message (older ones waiting behind it are counted in
        ``skipped`` and left unanswered); :class:`ControllerLost` when none comes within
        ``timeout_s`` (default the URL's ``timeout_s``); a message that breaks the protocol
        raises :class:`ProtocolError`."""
        if self._closed:
            raise DeviceDisconnected(f"{self.name}: closed")
        wait = self.params.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + wait
        state = None
        skipped = -1
        while True:
            if state is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ControllerLost(f"{self.name}: no state message for {wait * 1e3:.0f} ms")
                self._sock.settimeout(left)
            else:
                self._sock.settimeout(0.0)          # only what is waiting already
            try:
                data, t_ns, peer = self._read()
            except (socket.timeout, BlockingIOError):
                if state is None:
                    continue
                return dataclasses.replace(state, skipped=skipped)
            except OSError as exc:
                raise DeviceDisconnected(f"{self.name}: {exc.strerror or exc}") from None
            if self._peer is not None and peer != self._peer:
                continue          # only the controller that started the session is followed
            new = self._decode(data, t_ns)
            self._check_state(new)
            self._peer = peer
            self._last = state = new
            skipped += 1

    def _read(self) -> tuple[bytes, int, tuple]:
        """One datagram, its arrival on the monotonic clock [ns] and its sender."""
        if not self._kernel_stamps:
            data, peer = self._sock.recvfrom(65536)
            return data, time.monotonic_ns(), peer
        data, ancillary, _flags, peer = self._sock.recvmsg(65536, 64)
        now_mono, now_real = time.monotonic_ns(), time.time_ns()
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == socket.SO_TIMESTAMPNS and len(payload) >= 16:
                sec, nsec = struct.unpack("qq", payload[:16])
                return data, now_mono - max(0, now_real - (sec * 1_000_000_000 + nsec)), peer
        return data, now_mono, peer

    def send(self, q_target: Sequence[float]) -> None:
        """Answer the last state message with the joint targets ``q_target`` [rad] of this cycle."""
        if self._last is None or self._peer is None:
            raise ProtocolError(f"{self.name}: nothing to answer; receive a state message first")
        q = np.asarray(q_target, dtype=float)
        if q.shape != (self.n_joints,) or not np.all(np.isfinite(q)):
            raise InputError(f"{self.name}: joint targets need {self.n_joints} finite values, got {q_target!r}")
        payload = self._encode(q, self._last)
        try:
            self._sock.sendto(payload, self._peer)
        except OSError as exc:
            raise DeviceDisconnected(f"{self.name}: {exc.strerror or exc}") from None

    def _check_state(self, s: ControllerState) -> None:
        if s.q.shape != (self.n_joints,):
            raise ProtocolError(f"{self.name}: the controller sent {s.q.shape[0]} joints, the robot has "
                                f"{self.n_joints}")
        if not np.all(np.isfinite(s.q)) or np.any(np.abs(s.q) > 8 * math.pi):
            raise ProtocolError(f"{self.name}: implausible joint positions {s.q}; check the unit (degrees)")
        if s.currents_a is not None and s.currents_a.shape != (self.n_joints,):
            raise ProtocolError(f"{self.name}: {s.currents_a.shape[0]} motor currents for {self.n_joints} joints")

    @abc.abstractmethod
    def _decode(self, data: bytes, t_ns: int) -> ControllerState: ...

    @abc.abstractmethod
    def _encode(self, q_target: np.ndarray, last: ControllerState) -> bytes: ...

    # -------------------------------------------------------------- closing
    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}>"
