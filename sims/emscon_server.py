"""A simulated Leica emScon server on CESAPI's packet classes, TCP on 127.0.0.1.

It answers the commands the emScon driver (and a typical emScon client)
sends — system status, initialise, units, coordinate system, measurement
mode, tracker info, reflectors, environment and refraction, stationary
measurement — with CESAPI's ``...RT`` and result packets; commands it does
not simulate are answered with ``ES_RS_NotImplemented``.

Positions come from :meth:`elastocal.sims.world.SimWorld.read_tracker` at
the instant the measurement is taken, in the length unit the client set
(metres or millimetres). The reflector table has one reflector per marker,
named after it, plus a generic ``CCR-1.5in``: the beam is on the marker the
last marker-named reflector chosen names (a real tracker measures whatever
its beam is on).

Fault injection (tests): :meth:`SimEmscon.break_beam`, :meth:`lose_target`,
:meth:`uninitialise`, :meth:`stall`, :meth:`corrupt_packets`,
:meth:`disconnect_all`, :meth:`set_environment` (sends the status change
"environment params changed").
"""

from __future__ import annotations

import math
import socket
import threading
import time

from CESAPI import packet as es

from elastocal.drivers.emscon_packets import PacketSocket, packet_command
from elastocal.errors import DeviceError
from elastocal.sims.tcp_listener import TcpListener
from elastocal.sims.world import SimWorld

LENGTH_FACTOR = {es.ES_LU_Meter: 1.0, es.ES_LU_Millimeter: 1e3, es.ES_LU_Micron: 1e6}


def refraction_index(temperature_c: float, pressure_hpa: float, humidity_pct: float) -> float:
    """Group refraction index of air for the red laser, a simple Barrel–Sears form (simulation only)."""
    t = 273.15 + temperature_c
    e = humidity_pct / 100.0 * 6.1078 * 10 ** (7.5 * temperature_c / (237.3 + temperature_c))  # vapour [hPa]
    return 1.0 + (287.6e-6 * (pressure_hpa / 1013.25) * (273.15 / t)) - 5.5e-8 * e


class _Session:
    def __init__(self, server: "SimEmscon", conn: socket.socket, name: str) -> None:
        self.server = server
        self.sock = PacketSocket(conn, name, answers=False, poll_s=0.1)
        self.name = name
        self.units = es.SystemUnitsDataT()
        self.reflector_id = 1
        self.marker = server.markers[0]
        self._send_lock = threading.Lock()
        self.closed = threading.Event()
        self.thread = threading.Thread(target=self._loop, name=f"sim-emscon-{name}", daemon=True)

    def send(self, p, *, corrupt: bool = False) -> None:
        data = p.pack()
        if corrupt:      # a packet type emScon does not have: the client cannot trust the stream after it
            data = data[:4] + (77).to_bytes(4, "little") + data[8:]
        with self._send_lock:
            try:
                self.sock.send_bytes(data)
            except DeviceError:
                self.closed.set()

    def _loop(self) -> None:
        while not self.closed.is_set():
            try:
                p = self.sock.receive(0.1)
            except DeviceError:      # closed, or bytes that are not emScon packets
                break
            if p is None:
                continue
            self.server.wait_if_stalled()
            if self.closed.is_set():
                break
            self._handle(p)
        self.closed.set()
        self.sock.close()

    def answer(self, command_cls, status: int = es.ES_RS_AllOK, **fields) -> None:
        rt = getattr(es, command_cls.__name__[:-2] + "RT")()
        rt.packetInfo.status = status
        for k, v in fields.items():
            setattr(rt, k, v)
        self.send(rt)

    def _handle(self, p) -> None:
        s = self.server
        cmd = packet_command(p)
        if isinstance(p, es.GetSystemStatusCT):
            rt = es.GetSystemStatusRT()
            rt.trackerProcessorStatus = es.ES_TPS_Initialized if s.initialized else es.ES_TPS_CompensationSet
            rt.laserStatus, rt.admStatus = es.ES_LPS_LaserReady, es.ES_AS_ADMReady
            rt.esVersionNumber.iMajorVersionNumber, rt.esVersionNumber.iMinorVersionNumber = 3, 8
            rt.esVersionNumber.iBuildNumber = 1
            rt.weatherMonitorStatus = es.ES_WMS_ReadAndCalculateRefractions
            rt.lTrackerSerialNumber = s.serial
            self.send(rt)
        elif isinstance(p, es.InitializeCT):
            time.sleep(s.init_time_s)
            s.initialized = True
            self.answer(es.InitializeCT)
        elif isinstance(p, es.SetUnitsCT):
            u = p.unitsSettings
            if u.lenUnitType not in LENGTH_FACTOR or u.angUnitType != es.ES_AU_Radian:
                self.answer(es.SetUnitsCT, es.ES_RS_NotImplemented)
                return
            self.units = u
            self.answer(es.SetUnitsCT)
        elif isinstance(p, es.SetCoordinateSystemTypeCT):
            ok = p.coordSysType == es.ES_CS_RHR
            self.answer(es.SetCoordinateSystemTypeCT, es.ES_RS_AllOK if ok else es.ES_RS_NotImplemented)
        elif isinstance(p, es.SetMeasurementModeCT):
            ok = p.measMode == es.ES_MM_Stationary
            self.answer(es.SetMeasurementModeCT, es.ES_RS_AllOK if ok else es.ES_RS_WrongParameter1)
        elif isinstance(p, es.GetTrackerInfoCT):
            rt = es.GetTrackerInfoRT()
            rt.trackerType = es.ES_LTS_AT401
            rt.cTrackerName = b"SimAT401"
            rt.lSerialNumber = s.serial
            rt.bHasADM = 1
            rt.dMaxDistance, rt.dMinDistance = 160.0, 0.8
            rt.iMaxDataRate = s.max_rate_hz
            rt.iNumberOfFaces = 2
            rt.dHzAngleRange, rt.dVtAngleRange = 2 * math.pi, math.radians(290)
            self.send(rt)
        elif isinstance(p, es.GetReflectorsCT):
            for rid, name, ttype, offset in s.reflectors:
                rt = es.GetReflectorsRT()
                rt.iTotalReflectors = len(s.reflectors)
                rt.iInternalReflectorId, rt.targetType, rt.dSurfaceOffset = rid, ttype, offset
                rt.cReflectorName = name.encode()
                self.send(rt)
        elif isinstance(p, es.SetReflectorCT):
            match = [r for r in s.reflectors if r[0] == p.iInternalReflectorId]
            if not match:
                self.answer(es.SetReflectorCT, es.ES_RS_WrongParameter1)
                return
            self.reflector_id = match[0][0]
            if match[0][1] in s.markers:
                self.marker = match[0][1]
                s.world.select_marker(self.marker)     # a new reading begins (sims/world.py)
            self.answer(es.SetReflectorCT)
        elif isinstance(p, es.GetEnvironmentParamsCT):
            rt = es.GetEnvironmentParamsRT()
            e = rt.environmentData
            e.dTemperature, e.dPressure, e.dHumidity = s.environment
            self.send(rt)
        elif isinstance(p, es.GetRefractionParamsCT):
            rt = es.GetRefractionParamsRT()
            n = refraction_index(*s.environment)
            rt.refractionData.dIfmRefractionIndex = n
            rt.refractionData.dAdmRefractionIndex = n
            self.send(rt)
        elif isinstance(p, es.StartMeasurementCT):
            self._measure()
        elif isinstance(p, es.StopMeasurementCT):
            self.answer(es.StopMeasurementCT)
        elif isinstance(p, es.GetSystemSoftwareVersionCT):
            self.answer(es.GetSystemSoftwareVersionCT, cSoftwareVersion=b"emScon 3.8 (elastocal simulation)")
        elif cmd is not None:
            rt = es.BasicCommandRT()
            rt.packetHeader.lPacketSize, rt.packetHeader.type = 16, es.ES_DT_Command
            rt.command, rt.status = cmd, es.ES_RS_NotImplemented
            self.send(rt)

    def _measure(self) -> None:
        s = self.server
        status = s.measurement_status()
        if status != es.ES_RS_AllOK:
            self.answer(es.StartMeasurementCT, status)
            return
        t_ns = s.world.now_ns()
        pos = s.world.read_tracker(self.marker, t_ns)
        s.count_measurement()
        self.answer(es.StartMeasurementCT)
        r = es.SingleMeasResultT()
        r.measMode = es.ES_MM_Stationary
        f = LENGTH_FACTOR[self.units.lenUnitType]
        r.dVal1, r.dVal2, r.dVal3 = (float(v) * f for v in pos)
        r.dStd1 = r.dStd2 = r.dStd3 = float(s.world.cell.truth.tracker_noise_m) * f
        r.dStdTotal = math.sqrt(3) * r.dStd1
        r.dTemperature, r.dPressure, r.dHumidity = s.environment
        self.send(r, corrupt=s.take_corrupt())

    def close(self) -> None:
        self.closed.set()
        self.sock.close()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout=2.0)


class SimEmscon:
    """A simulated emScon server measuring the markers of ``world``."""

    def __init__(self, world: SimWorld, *, serial: int = 401042, max_rate_hz: int = 1000,
                 init_time_s: float = 0.05, initialized: bool = True) -> None:
        self.world = world
        self.markers = world.markers
        self.serial = int(serial)
        self.max_rate_hz = int(max_rate_hz)
        self.init_time_s = float(init_time_s)
        self.initialized = initialized
        #: (id, name, ES_TargetType, surface offset [m])
        self.reflectors = tuple((i, m, es.ES_TT_RRR15, 0.0191) for i, m in enumerate(self.markers, start=1)) + (
            (len(self.markers) + 1, "CCR-1.5in", es.ES_TT_CornerCube, 0.0191),)
        #: temperature [°C], pressure [hPa], humidity [%RH]
        self.environment = (20.5, 1013.25, 45.0)
        self._lock = threading.Lock()
        self._beam_broken_until = 0.0
        self._no_target_until = 0.0
        self._corrupt = 0
        self._stall_event = threading.Event()
        self._stall_event.set()
        self._stall_until = 0.0
        self._sessions: list[_Session] = []
        self._listener: TcpListener | None = None
        self.tcp_port: int | None = None
        #: TCP connections accepted so far
        self.connections = 0
        #: measurements taken so far
        self.measurements = 0

    # ---------------------------------------------------------- faults
    def break_beam(self, duration_s: float | None = None) -> None:
        """Interrupt the beam for ``duration_s`` (None: until :meth:`restore_beam`)."""
        with self._lock:
            self._beam_broken_until = math.inf if duration_s is None else time.monotonic() + duration_s

    def restore_beam(self) -> None:
        with self._lock:
            self._beam_broken_until = 0.0
            self._no_target_until = 0.0

    def lose_target(self, duration_s: float | None = None) -> None:
        """No reflector in the beam for ``duration_s`` (None: until :meth:`restore_beam`)."""
        with self._lock:
            self._no_target_until = math.inf if duration_s is None else time.monotonic() + duration_s

    def uninitialise(self) -> None:
        """The tracker loses its initialisation (as after a power cycle of the sensor)."""
        self.initialized = False

    def corrupt_packets(self, count: int) -> None:
        """Send the next ``count`` measurement results with a packet type emScon does not have."""
        with self._lock:
            self._corrupt += count

    def take_corrupt(self) -> bool:
        with self._lock:
            if self._corrupt > 0:
                self._corrupt -= 1
                return True
            return False

    def stall(self, duration_s: float) -> None:
        """Answer nothing for ``duration_s``."""
        with self._lock:
            self._stall_until = time.monotonic() + duration_s
            self._stall_event.clear()
        threading.Timer(duration_s, self._stall_event.set).start()

    def wait_if_stalled(self) -> None:
        self._stall_event.wait()

    def disconnect_all(self) -> None:
        with self._lock:
            sessions, self._sessions = self._sessions, []
        for s in sessions:
            s.close()

    def set_environment(self, temperature_c: float, pressure_hpa: float, humidity_pct: float) -> None:
        """New weather-station values; every client gets ES_SSC_EnvironmentParamsChanged."""
        self.environment = (float(temperature_c), float(pressure_hpa), float(humidity_pct))
        change = es.SystemStatusChangeT()
        change.systemStatusChange = es.ES_SSC_EnvironmentParamsChanged
        with self._lock:
            sessions = list(self._sessions)
        for s in sessions:
            s.send(change)

    # ------------------------------------------------------- measuring
    def measurement_status(self) -> int:
        now = time.monotonic()
        with self._lock:
            if not self.initialized:
                return es.ES_RS_TrackerNotInitialized
            if now < self._beam_broken_until:
                return es.ES_RS_MeasurementStatusNotReady
            if now < self._no_target_until:
                return es.ES_RS_NoStationaryResult
        return es.ES_RS_AllOK

    def count_measurement(self) -> None:
        with self._lock:
            self.measurements += 1

    # ------------------------------------------------------- transport
    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Listen on ``host:port`` (0: a port the OS chooses); returns the port."""
        self._listener = TcpListener(host, port, self._accept, name="sim-emscon-accept")
        self.tcp_port = self._listener.port
        return self.tcp_port

    def _accept(self, conn: socket.socket, addr: tuple) -> None:
        session = _Session(self, conn, f"tcp{addr[1]}")
        with self._lock:
            self._sessions = [s for s in self._sessions if not s.closed.is_set()]
            self._sessions.append(session)
            self.connections += 1
        session.thread.start()

    def close(self) -> None:
        self._stall_event.set()
        if self._listener is not None:
            self._listener.close()
        self.disconnect_all()

    def __enter__(self) -> "SimEmscon":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
