"""Leica laser trackers through the emScon server (``tracker+emscon://host:700``).

emScon is the TCP interface of Leica's tracker server (AT4xx and earlier
controllers); its packets are CESAPI's (:mod:`elastocal.drivers.emscon_packets`).
At open the driver

1. asks the system status and, when the tracker is not initialised,
   initialises it (``?initialize=0`` refuses instead: ``DeviceFault`` "not
   initialised"), waiting up to ``init_timeout_s`` (URL, default 120 s);
2. sets the units to metres, radians, °C, hPa and %RH, the coordinate
   system to right-handed cartesian and the stationary measurement mode;
3. reads the tracker's reflector table and resolves each marker's reflector:
   ``?reflector.R1=<name or id>`` per marker, else ``?reflector=<name or id>``
   for all, else the reflector whose name is the marker's name;
4. reads the environment (temperature, pressure, humidity) and the
   refraction indices; they ride on every sample (``TrackerSample.environment``)
   and go to the log with it. A status change "environment/refraction
   params changed" makes the driver read them again.

``select(marker)`` sets that marker's reflector (``SetReflector``). emScon
measures whatever reflector the beam is on: bringing the beam to the marker
(PowerLock/ATR, the tracker software) is the cell's job (docs/trackers.md).

``measure()`` is one stationary measurement (``StartMeasurement`` ->
``SingleMeasResult``). ``stream(rate_hz)`` repeats it on the host's clock:
slot ``k`` is due at ``start + k / rate`` (``seq = k``, ``device_time_s`` the
slot's time since the driver opened, ``t_ns`` the middle of its request and
answer); a slot requested up to ``CATCH_UP_S`` late is still measured, a later
one is a recorded gap, and so are a beam break and a missing target; a lost connection
is re-opened with a gap ``reconnected``; ``timeout_s`` without an answer ends
the stream with :class:`DeviceTimeout`. The fastest stream is the tracker's
own ``iMaxDataRate`` (GetTrackerInfo).

Result codes (ES_ResultStatus) -> elastocal:

=================================================  ===================================
``ES_RS_MeasurementStatusNotReady`` (10004)        beam broken: gap / ``DeviceFault``
``ES_RS_NoStationaryResult`` (10009)               no target: gap / ``DeviceFault``
``ES_RS_TrackerNotInitialized`` (39)               ``DeviceFault`` "not initialised"
``ES_RS_ServerBusy`` (1)                           ``DeviceTimeout`` (retried)
any other non-zero status, ``ErrorResponse``       ``DeviceFault`` naming the ES_RS_ code
=================================================  ===================================

Why one module over 500 lines: the emScon session (initialisation, units, reflectors,
environment) and its stream share one connection and one packet loop; split, the
stream would reach into the session's private state.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from CESAPI import packet as es

from elastocal.drivers.base import Tracker
from elastocal.drivers.samples import DeviceInfo, Stream, TrackerSample
from elastocal.drivers.config import TrackerConfig
from elastocal.drivers.emscon_packets import (
    PacketSocket,
    STATUS_CHANGE_NAMES,
    command_name,
    expect_timeout,
    packet_command,
    packet_status,
    packet_type,
    result_name,
)
from elastocal.errors import BeamBroken, DeviceDisconnected, DeviceError, DeviceFault, DeviceTimeout, InputError, ProtocolError

#: result status -> gap reason (in a stream) / fault text (single measurement)
BLOCKED = {es.ES_RS_MeasurementStatusNotReady: "beam broken", es.ES_RS_NoStationaryResult: "no target"}
#: a slot is still measured when its request is this late [s] (its sample says when it was
#: taken); slots later than that are a gap "request could not be sent on time"
CATCH_UP_S = 0.1
#: garbled answers in a row that end a stream
MAX_BAD_PACKETS = 10


@dataclass(frozen=True)
class Reflector:
    id: int
    name: str
    target_type: int
    surface_offset_m: float


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


class EmsconTracker(Tracker):
    """A Leica tracker behind an emScon server."""

    def __init__(self, config: TrackerConfig, *, links=None) -> None:
        super().__init__(config.url, markers=config.markers, timeout_s=config.timeout_s, retries=config.retries)
        url = config.url
        self.config = config
        settings = url.settings                 # drivers.url_params.EmsconParams
        self.host = settings.host
        self.port = settings.port
        self.auto_initialize = settings.initialize
        self.init_timeout_s = settings.init_timeout_s
        self._lock = threading.RLock()
        self._sock: PacketSocket | None = None
        self._resync = False
        self._t0_ns = time.monotonic_ns()
        self._reflectors: tuple[Reflector, ...] = ()
        self._marker_reflector: dict[str, Reflector] = {}
        self._info: dict[str, object] = {}
        self._environment: tuple[tuple[str, float], ...] = ()
        self._refraction: tuple[tuple[str, float], ...] = ()
        self._env_stale = False
        self.max_rate_hz = math.inf
        self._stream_state: _EmsconStream | None = None
        self._seq_single = 0
        self._call("open", self._connect)
        try:
            self._call("select", self._select, self.markers[0])
        except BaseException:
            self._drop_socket()
            raise

    # ------------------------------------------------------------ socket
    def _drop_socket(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _exchange(self, command, *, timeout_s: float | None = None, results: int = 0):
        """Send ``command``; return its answer (and ``results`` result packets after it).

        Status changes arriving meanwhile are taken in; a non-zero status
        raises the mapped error (see the module docstring). Any timeout or
        garbled packet marks the connection for a reconnect (a late answer must
        never answer a newer request)."""
        if self._sock is None or self._resync:
            self._connect()
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        cmd = packet_command(command)
        what = command_name(cmd)
        try:
            self._sock.send(command)
            answer = None
            got: list = []
            deadline = time.monotonic() + timeout_s
            while answer is None or len(got) < results:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise expect_timeout(what, timeout_s)
                p = self._sock.receive(left)
                if p is None:
                    raise expect_timeout(what, timeout_s)
                kind = packet_type(p)
                if kind == es.ES_DT_SystemStatusChange:
                    self._status_change(p.systemStatusChange)
                    continue
                if kind == es.ES_DT_Error:
                    self._raise_status(p.status, what)
                if kind == es.ES_DT_Command:
                    if packet_command(p) != cmd:
                        raise ProtocolError(f"emScon: answer to {command_name(packet_command(p))} while "
                                            f"waiting for {what}")
                    if packet_status(p) != es.ES_RS_AllOK:
                        self._raise_status(packet_status(p), what)
                    if answer is None:
                        answer = p
                    else:
                        got.append(p)       # e.g. the further GetReflectors answers
                    continue
                if kind in (es.ES_DT_SingleMeasResult, es.ES_DT_SingleMeasResult2):
                    if packet_status(p) != es.ES_RS_AllOK:
                        self._raise_status(packet_status(p), what)
                    got.append(p)
                    continue
                # reflector position / nivel results are not used
            return answer, got
        except (DeviceTimeout, ProtocolError):
            self._resync = True
            raise
        except DeviceDisconnected:
            self._drop_socket()
            raise

    def _raise_status(self, status: int, what: str) -> None:
        name = result_name(status)
        if status in BLOCKED:
            raise _Blocked(BLOCKED[status], f"tracker: {BLOCKED[status]} ({name} on {what})")
        if status == es.ES_RS_TrackerNotInitialized:
            raise DeviceFault(f"tracker: not initialised ({name} on {what}); initialise it in the tracker "
                              "software or open with ?initialize=1")
        if status == es.ES_RS_ServerBusy:
            raise DeviceTimeout(f"tracker: emScon server busy ({name} on {what})")
        raise DeviceFault(f"tracker: {what} failed: {name} ({status})")

    def _take_status_changes(self) -> None:
        """Read the status changes the server sent since the last command."""
        try:
            while self._sock.readable():
                p = self._sock.receive(self.timeout_s)
                if p is None:
                    break
                if packet_type(p) != es.ES_DT_SystemStatusChange:
                    raise ProtocolError(f"emScon: unexpected {type(p).__name__} between commands")
                self._status_change(p.systemStatusChange)
        except ProtocolError:
            self._resync = True
            raise
        except DeviceDisconnected:
            self._drop_socket()
            raise

    def _status_change(self, change: int) -> None:
        if change in (es.ES_SSC_EnvironmentParamsChanged, es.ES_SSC_RefractionParamsChanged):
            self._env_stale = True
        elif change in (es.ES_SSC_ServerClosing, es.ES_SSC_TPConnectionClosing):
            self._resync = True
        self._info["last status change"] = STATUS_CHANGE_NAMES.get(change, str(change))

    # ------------------------------------------------------------- open
    def _connect(self) -> None:
        """(Re)connect and set the tracker up; see the module docstring."""
        self._drop_socket()
        self._resync = False
        self._sock = PacketSocket.connect(self.host, self.port, self.timeout_s)
        try:
            self._setup()
        except BaseException:
            self._drop_socket()
            raise

    def _setup(self) -> None:
        status, _ = self._exchange(es.GetSystemStatusCT())
        if status.trackerProcessorStatus != es.ES_TPS_Initialized:
            if not self.auto_initialize:
                raise DeviceFault("tracker: not initialised (tracker processor status "
                                  f"{status.trackerProcessorStatus}); initialise it or open with ?initialize=1")
            self._exchange(es.InitializeCT(), timeout_s=self.init_timeout_s)
        units = es.SetUnitsCT()
        u = units.unitsSettings
        u.lenUnitType, u.angUnitType = es.ES_LU_Meter, es.ES_AU_Radian
        u.tempUnitType, u.pressUnitType, u.humUnitType = es.ES_TU_Celsius, es.ES_PU_HPascal, es.ES_HU_RH
        self._exchange(units)
        cs = es.SetCoordinateSystemTypeCT()
        cs.coordSysType = es.ES_CS_RHR
        self._exchange(cs)
        mode = es.SetMeasurementModeCT()
        mode.measMode = es.ES_MM_Stationary
        self._exchange(mode)
        info, _ = self._exchange(es.GetTrackerInfoCT())
        self._info.update({"tracker": _text(info.cTrackerName), "serial": str(info.lSerialNumber),
                           "max data rate": f"{info.iMaxDataRate} Hz",
                           "range": f"{info.dMinDistance:g}..{info.dMaxDistance:g} m",
                           "version": f"{status.esVersionNumber.iMajorVersionNumber}."
                                      f"{status.esVersionNumber.iMinorVersionNumber}."
                                      f"{status.esVersionNumber.iBuildNumber}"})
        self.max_rate_hz = float(info.iMaxDataRate) if info.iMaxDataRate > 0 else math.inf
        first, rest = self._exchange(es.GetReflectorsCT(), results=0)
        answers = [first]
        total = first.iTotalReflectors
        while len(answers) < total:
            p = self._sock.receive(self.timeout_s)
            if p is None:
                self._resync = True
                raise expect_timeout("GetReflectors", self.timeout_s)
            if packet_command(p) == es.ES_C_GetReflectors:
                answers.append(p)
        self._reflectors = tuple(Reflector(a.iInternalReflectorId, _text(a.cReflectorName), a.targetType,
                                           a.dSurfaceOffset) for a in answers)
        self._marker_reflector = {m: self._reflector_for(m) for m in self.markers}
        self._read_environment()

    def _reflector_for(self, marker: str) -> Reflector:
        url = self.config.url
        wanted = url.settings.reflector_for(marker)
        names = ", ".join(f"{r.id} {r.name!r}" for r in self._reflectors) or "none"
        if wanted is None:
            for r in self._reflectors:
                if r.name == marker:
                    return r
            raise InputError(f"no reflector for marker {marker}: give ?reflector.{marker}=<name or id> or "
                             f"?reflector=<name or id> in {url.text}; the tracker has {names}",
                             source="tracker.url")
        for r in self._reflectors:
            if r.name == wanted or str(r.id) == wanted:
                return r
        raise InputError(f"the tracker has no reflector {wanted!r} (for marker {marker}); it has {names}",
                         source="tracker.url")

    def _read_environment(self) -> None:
        env, _ = self._exchange(es.GetEnvironmentParamsCT())
        e = env.environmentData
        self._environment = (("temperature_c", float(e.dTemperature)), ("pressure_hpa", float(e.dPressure)),
                             ("humidity_pct", float(e.dHumidity)))
        refr, _ = self._exchange(es.GetRefractionParamsCT())
        r = refr.refractionData
        self._refraction = (("ifm_refraction_index", float(r.dIfmRefractionIndex)),
                            ("adm_refraction_index", float(r.dAdmRefractionIndex)))
        self._env_stale = False

    def _reconnect(self) -> None:
        self._connect()

    # ------------------------------------------------------------- API
    @property
    def reflectors(self) -> tuple[Reflector, ...]:
        """The tracker's reflector table."""
        return self._reflectors

    def environment(self) -> dict[str, float]:
        """The latest weather and refraction values (°C, hPa, %RH, indices)."""
        return dict(self._environment + self._refraction)

    def _identify(self) -> DeviceInfo:
        with self._lock:
            if self._sock is None or self._resync:
                self._connect()
        env = ", ".join(f"{k}={v:g}" for k, v in self._environment + self._refraction)
        refl = ", ".join(f"{m}: {r.name}" for m, r in self._marker_reflector.items())
        return DeviceInfo(kind="tracker", url=self.url.text, vendor="Leica Geosystems (emScon)",
                          model=str(self._info.get("tracker", "")), serial=str(self._info.get("serial", "")),
                          revision=str(self._info.get("version", "")),
                          details=(("markers", ", ".join(self.markers)), ("target", self._marker),
                                   ("reflectors", refl), ("environment", env),
                                   ("max data rate", str(self._info.get("max data rate", "")))))

    def _select(self, marker: str) -> None:
        with self._lock:
            if self._stream_state is not None:
                raise DeviceError("tracker: a stream is running; close it before selecting another marker")
            if self._sock is None or self._resync:
                self._connect()
            self._set_reflector(marker)

    def _set_reflector(self, marker: str) -> None:
        cmd = es.SetReflectorCT()
        cmd.iInternalReflectorId = self._marker_reflector[marker].id
        self._exchange(cmd)

    def _measure_once(self) -> tuple[tuple[float, float, float], tuple[tuple[str, float], ...]]:
        """One stationary measurement (with the lock held): position [m] and environment."""
        if self._sock is None or self._resync:
            self._connect()
            self._set_reflector(self._marker)
        self._take_status_changes()
        if self._env_stale:
            self._read_environment()
        _, results = self._exchange(es.StartMeasurementCT(), results=1)
        r = results[0]
        env = (("temperature_c", float(r.dTemperature)), ("pressure_hpa", float(r.dPressure)),
               ("humidity_pct", float(r.dHumidity))) + self._refraction
        return (float(r.dVal1), float(r.dVal2), float(r.dVal3)), env

    def _measure(self) -> TrackerSample:
        with self._lock:
            if self._stream_state is not None:
                raise DeviceError("tracker: a stream is running; read it or close it first")
            t0 = time.monotonic_ns()
            try:
                p, env = self._measure_once()
            except _Blocked as exc:
                raise DeviceFault(str(exc)) from None
            t1 = time.monotonic_ns()
            t = (t0 + t1) // 2
            self._seq_single += 1
            return TrackerSample(t, self._seq_single, (t - self._t0_ns) / 1e9, self._marker, p, env)

    def _stream(self, rate_hz: float) -> Stream[TrackerSample]:
        if rate_hz > self.max_rate_hz:
            raise InputError(f"tracker: {rate_hz:g} Hz is above the tracker's maximum data rate "
                             f"{self.max_rate_hz:g} Hz")
        with self._lock:
            if self._stream_state is not None:
                raise DeviceError("tracker: a stream is already running")
            state = _EmsconStream(self, rate_hz)
            self._stream_state = state
        state.start()
        return state.stream

    def _close(self) -> None:
        state = self._stream_state
        if state is not None:
            state.stop()
        with self._lock:
            self._drop_socket()


class _Blocked(BeamBroken):
    """A measurement the beam could not make (beam broken, no target): a gap in a stream."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class _EmsconStream:
    """Host-clocked repeated stationary measurements (see the module docstring)."""

    def __init__(self, tracker: EmsconTracker, rate_hz: float) -> None:
        self.tracker = tracker
        self.rate_hz = rate_hz
        self.period_ns = int(round(1e9 / rate_hz))
        self.catch_up_ns = max(int(CATCH_UP_S * 1e9), self.period_ns)
        self.stream: Stream[TrackerSample] = Stream("tracker", rate_hz, stop=self.stop)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="emscon-stream", daemon=True)
        self._pending = 0
        self._pending_reason = ""
        self._pending_start: int | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=self.tracker.timeout_s * (self.tracker.retries + 2) + 1.0)
        self._flush(time.monotonic_ns())
        if self.tracker._stream_state is self:
            self.tracker._stream_state = None

    def _hold(self, count: int, reason: str, t_ns: int) -> None:
        if self._pending and reason != self._pending_reason:
            self._flush(t_ns)
        self._pending += count
        self._pending_reason = reason

    def _flush(self, t_ns: int) -> None:
        if self._pending:
            self.stream.gap(self._pending, self._pending_reason, end_ns=t_ns)
            self._pending = 0

    def _run(self) -> None:
        t = self.tracker
        start = time.monotonic_ns()
        k = 0
        last_answer = time.monotonic()
        late_reason = "request could not be sent on time"
        bad = 0
        while not self._stop.is_set():
            due = start + k * self.period_ns
            now = time.monotonic_ns()
            if now < due:
                self._stop.wait((due - now) / 1e9)
                continue
            late = 0
            while due + late * self.period_ns < now - self.catch_up_ns:
                late += 1
            if late:
                self._hold(int(late), late_reason, now)
                k += int(late)
                continue
            late_reason = "request could not be sent on time"
            try:
                with t._lock:
                    t0 = time.monotonic_ns()
                    p, env = t._measure_once()
                    t1 = time.monotonic_ns()
            except _Blocked as exc:
                self._hold(1, exc.reason, time.monotonic_ns())
                last_answer = time.monotonic()
                k += 1
                continue
            except DeviceDisconnected as exc:
                if not self._resume(exc):
                    return
                last_answer = time.monotonic()
                late_reason = "reconnected"     # the slots missed meanwhile
                self._hold(1, late_reason, time.monotonic_ns())
                k += 1
                continue
            except DeviceTimeout as exc:
                if time.monotonic() - last_answer >= t.timeout_s:
                    self._flush(time.monotonic_ns())
                    self.stream.fail(DeviceTimeout(f"tracker: no result for {t.timeout_s:g} s while streaming "
                                                   f"({exc})"))
                    return
                k += 1
                continue
            except ProtocolError as exc:
                bad += 1            # the connection is re-opened before the next request
                if bad > MAX_BAD_PACKETS:
                    self._flush(time.monotonic_ns())
                    self.stream.fail(ProtocolError(f"{exc} ({bad} bad packets in a row)"))
                    return
                self._hold(1, "malformed packet", time.monotonic_ns())
                k += 1
                continue
            except DeviceError as exc:
                self._flush(time.monotonic_ns())
                self.stream.fail(exc)
                return
            bad = 0
            last_answer = time.monotonic()
            stamp = (t0 + t1) // 2
            try:
                sample = t.check_sample(TrackerSample(stamp, k, (due - t._t0_ns) / 1e9, t._marker, p, env))
            except ProtocolError as exc:
                self._flush(stamp)
                self.stream.fail(exc)
                return
            self._flush(stamp)
            self.stream.emit(sample, stamp)
            k += 1
        self._flush(time.monotonic_ns())

    def _resume(self, cause: DeviceDisconnected) -> bool:
        """Reconnect after a lost connection; the slots lost meanwhile are a gap ``reconnected``."""
        t = self.tracker
        last: DeviceError = cause
        for attempt in range(t.retries + 1):
            if self._stop.is_set():
                return False
            try:
                with t._lock:
                    t._connect()
                    t._set_reflector(t._marker)
                return True
            except DeviceError as exc:
                last = exc
                time.sleep(min(0.05 * (attempt + 1), t.timeout_s))
        self._flush(time.monotonic_ns())
        self.stream.fail(DeviceDisconnected(f"{last} (stream could not be resumed after {t.retries + 1} attempts)"))
        return False
