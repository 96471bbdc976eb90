"""A simulated ATI Net F/T on 127.0.0.1 speaking RDT over UDP (docs/stream.md).

It answers an RDT request (``uint16`` header 0x1234, ``uint16`` command, ``uint32`` count,
big-endian) with a stream of 36-byte records (``uint32`` rdt_sequence, ft_sequence, status,
six ``int32`` counts) at ``rate_hz`` to whoever asked, until command 0 or ``count``
records. The counts are the true process wrench of the guided robot in the sensor's axes
(:meth:`~elastocal.sims.guided.GuidedRobot.sensor_wrench`) plus gauge noise, times the
counts per force and per torque. Faults for tests: ``silent_after_s`` (the sensor stops
sending: a cable pulled) and ``fault_after_s`` (a nonzero status word).
"""

from __future__ import annotations

import select
import socket
import struct
import threading
import time
from dataclasses import dataclass

import numpy as np

from elastocal.sims.guided import GuidedRobot, SensorPlacement

RDT_REQUEST = struct.Struct(">HHI")
RDT_RECORD = struct.Struct(">III6i")
RDT_HEADER = 0x1234
STATUS_GAUGE_FAULT = 0x80010000      # a nonzero status word as the Net F/T sets it on a fault


@dataclass(frozen=True)
class NetFtNoise:
    """Gauge noise of the simulated sensor (one standard deviation)."""

    force_n: float = 0.25
    torque_nm: float = 0.01


class SimNetFt:
    """The simulated Net F/T (see the module docstring)."""

    def __init__(self, robot: GuidedRobot, *, rate_hz: float = 1000.0, counts_per_force: float = 1e6,
                 counts_per_torque: float = 1e6, noise: NetFtNoise = NetFtNoise(), seed: int = 1,
                 placement: SensorPlacement = SensorPlacement(), silent_after_s: float | None = None,
                 fault_after_s: float | None = None) -> None:
        self.robot = robot
        self.period_s = 1.0 / rate_hz
        self.counts = np.array([counts_per_force] * 3 + [counts_per_torque] * 3)
        self.noise = noise
        self.placement = placement
        self.silent_after_s = silent_after_s
        self.fault_after_s = fault_after_s
        self._rng = np.random.default_rng(seed)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.sent = 0

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def url(self) -> str:
        host, port = self.address
        return f"netft://{host}:{port}"

    def start(self) -> "SimNetFt":
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name="sim-netft", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._sock.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _serve(self) -> None:
        client = None
        remaining = 0                       # records left (0 with a client: unlimited)
        started_ns = 0
        next_ns = time.monotonic_ns()
        seq = 0
        while not self._stop.is_set():
            wait = 0.05 if client is None else max(0.0, (next_ns - time.monotonic_ns()) * 1e-9)
            ready, _, _ = select.select([self._sock], [], [], wait)
            if ready:
                data, peer = self._sock.recvfrom(1024)
                if len(data) >= RDT_REQUEST.size:
                    header, command, count = RDT_REQUEST.unpack_from(data)
                    if header == RDT_HEADER and command == 0:
                        client = None
                    elif header == RDT_HEADER and command == 2:
                        client, remaining, started_ns = peer, count, time.monotonic_ns()
                        next_ns = started_ns
                continue
            if client is None or time.monotonic_ns() < next_ns:
                continue
            age_s = (time.monotonic_ns() - started_ns) * 1e-9
            next_ns += int(self.period_s * 1e9)
            if self.silent_after_s is not None and age_s >= self.silent_after_s:
                continue
            seq = (seq + 1) & 0xFFFFFFFF
            status = STATUS_GAUGE_FAULT if self.fault_after_s is not None and age_s >= self.fault_after_s else 0
            w = self.robot.sensor_wrench(self.placement)
            w = w + self._rng.normal(0.0, 1.0, 6) * np.array([self.noise.force_n] * 3 + [self.noise.torque_nm] * 3)
            counts = np.clip(np.rint(w * self.counts), -2**31, 2**31 - 1).astype(np.int64)
            self._sock.sendto(RDT_RECORD.pack(seq, seq, status, *counts.tolist()), client)
            self.sent += 1
            if remaining:
                remaining -= 1
                if remaining == 0:
                    client = None
