"""What devices deliver: the one sample type per device kind (:class:`DriveSample`,
:class:`TrackerSample`), device identity, and the :class:`Stream` a backend thread fills
and the caller reads.

Samples carry ``t_ns``: integer nanoseconds from :func:`time.monotonic_ns`
taken at acquisition (for synchronous CANopen data, the instant the SYNC that
latched the values was sent).

A :class:`Stream` is filled by a backend thread and read by the caller:
``read(timeout_s)`` returns a :class:`Batch` of the samples and gaps since the
last call; after a fatal error it first hands out what arrived before the
error, then raises it. The device bases that fill them are in
:mod:`elastocal.drivers.base`.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Callable, Generic, TypeVar

from elastocal.errors import DeviceTimeout

S = TypeVar("S")


# ----------------------------------------------------------------- records
@dataclass(frozen=True)
class DeviceInfo:
    """What a device says about itself."""

    kind: str                       # "drive", "tracker" or "controller"
    url: str
    vendor: str
    model: str
    serial: str = ""
    revision: str = ""
    details: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class DriveSample:
    """One reading of a joint drive. ``velocity_rad_s`` and ``torque_nm`` are
    None when the stream or register map does not carry them (fixed per stream)."""

    t_ns: int
    joint: int
    position_rad: float             # motor-side joint coordinate q [rad]
    current_a: float                # signed motor current [A]
    velocity_rad_s: float | None = None
    torque_nm: float | None = None  # joint-side torque reported by the drive [N·m]
    status: int = 0                 # raw statusword / status register


@dataclass(frozen=True)
class TrackerSample:
    """One tracker measurement of one marker, tracker frame [m]."""

    t_ns: int
    seq: int                        # the tracker's measurement counter
    device_time_s: float            # the tracker's own clock [s]
    marker: str
    tracker_p_marker: tuple[float, float, float]
    #: what the tracker reports about the air with the measurement (backends that have it, e.g.
    #: emScon): ``(("temperature_c", 21.3), ("pressure_hpa", 1013.2), ("humidity_pct", 45.0), ...)``
    environment: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class Gap:
    """Samples a stream lost, and why. ``missing`` counts the lost samples."""

    device: str
    start_ns: int                   # time of the last good sample before the gap (or stream start)
    end_ns: int                     # time the gap was closed or detected
    missing: int
    reason: str


@dataclass(frozen=True)
class Batch(Generic[S]):
    samples: tuple[S, ...]
    gaps: tuple[Gap, ...]


@dataclass(frozen=True)
class StreamStats:
    """Counts of a stream; ``expected = received + missing``."""

    device: str
    rate_hz: float                  # requested rate
    received: int
    missing: int
    gaps: int
    elapsed_s: float

    @property
    def expected(self) -> int:
        return self.received + self.missing

    @property
    def measured_rate_hz(self) -> float:
        return self.received / self.elapsed_s if self.elapsed_s > 0 else 0.0


# ------------------------------------------------------------------ stream
class Stream(Generic[S]):
    """Samples of one device, produced by a backend thread.

    Producers call :meth:`emit`, :meth:`gap` and :meth:`fail`; consumers call
    :meth:`read` and :meth:`close` (or use ``with``).
    """

    def __init__(self, device: str, rate_hz: float, stop: Callable[[], None]) -> None:
        self.device = device
        self.rate_hz = float(rate_hz)
        self._stop = stop
        self._cond = threading.Condition()
        self._samples: collections.deque = collections.deque()
        self._gaps: collections.deque = collections.deque()
        self._error: BaseException | None = None
        self._closed = False
        self._received = 0
        self._missing = 0
        self._n_gaps = 0
        self._started_ns = time.monotonic_ns()
        self._ended_ns: int | None = None
        self._last_ns = self._started_ns

    # ---------------------------------------------------------- producer
    def emit(self, sample: S, t_ns: int) -> None:
        with self._cond:
            if self._error is not None or self._closed:
                return
            self._samples.append(sample)
            self._received += 1
            self._last_ns = t_ns
            self._cond.notify_all()

    def gap(self, missing: int, reason: str, *, start_ns: int | None = None, end_ns: int | None = None) -> None:
        if missing <= 0:
            return
        with self._cond:
            if self._error is not None or self._closed:
                return
            g = Gap(self.device, self._last_ns if start_ns is None else start_ns,
                    time.monotonic_ns() if end_ns is None else end_ns, int(missing), reason)
            self._gaps.append(g)
            self._missing += int(missing)
            self._n_gaps += 1
            self._cond.notify_all()

    def fail(self, error: BaseException) -> None:
        """Stop the stream with a typed error (delivered after the data before it)."""
        with self._cond:
            if self._error is None and not self._closed:
                self._error = error
            self._cond.notify_all()

    @property
    def failed(self) -> bool:
        return self._error is not None

    @property
    def closed(self) -> bool:
        return self._closed

    # ---------------------------------------------------------- consumer
    def read(self, timeout_s: float | None = 1.0) -> Batch[S]:
        """Samples and gaps since the last call; waits up to ``timeout_s`` for
        the first one. Raises :class:`DeviceTimeout` when nothing came, or the
        stream's error once the data before it has been read. Returns an empty
        batch once the stream is closed."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._samples and not self._gaps and self._error is None and not self._closed:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise DeviceTimeout(f"{self.device}: no sample for {timeout_s:g} s")
                self._cond.wait(remaining)
            return self._take()

    def poll(self) -> Batch[S]:
        """What has arrived, without waiting (possibly an empty batch); raises
        the stream's error once the data before it has been handed out."""
        with self._cond:
            return self._take()

    def _take(self) -> Batch[S]:
        """(with the lock held) the samples and gaps so far, else the stream's error, else an empty batch."""
        if self._samples or self._gaps:
            batch = Batch(tuple(self._samples), tuple(self._gaps))
            self._samples.clear()
            self._gaps.clear()
            return batch
        if self._error is not None:
            raise self._error
        return Batch((), ())

    def read_for(self, duration_s: float, *, timeout_s: float = 1.0) -> Batch[S]:
        """Everything the stream delivers during ``duration_s`` (DeviceTimeout if
        nothing at all comes for ``timeout_s``; the stream's error as :meth:`read`)."""
        samples: list[S] = []
        gaps: list[Gap] = []
        end = time.monotonic() + duration_s
        quiet_since = time.monotonic()
        while True:
            remaining = end - time.monotonic()
            if remaining <= 0:
                break
            time.sleep(min(0.02, remaining))
            b = self.poll()
            if b.samples or b.gaps:
                quiet_since = time.monotonic()
                samples.extend(b.samples)
                gaps.extend(b.gaps)
            elif self._closed:
                break
            elif time.monotonic() - quiet_since > timeout_s:
                raise DeviceTimeout(f"{self.device}: no sample for {timeout_s:g} s")
        return Batch(tuple(samples), tuple(gaps))

    def stats(self) -> StreamStats:
        """Counts so far; ``elapsed_s`` runs from the start to now, or to :meth:`close`."""
        with self._cond:
            end = self._ended_ns if self._ended_ns is not None else time.monotonic_ns()
            return StreamStats(self.device, self.rate_hz, self._received, self._missing, self._n_gaps,
                               (end - self._started_ns) / 1e9)

    def close(self) -> None:
        """Stop the device streaming; samples still in flight are delivered first."""
        with self._cond:
            if self._closed:
                return
            if self._ended_ns is None:
                self._ended_ns = time.monotonic_ns()
        try:
            self._stop()
        finally:
            with self._cond:
                self._closed = True
                self._cond.notify_all()

    def __enter__(self) -> "Stream[S]":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
