"""Simulated Modbus devices: joint drives and the cell controller.

Each endpoint (a TCP port on 127.0.0.1, or a serial line) is one pymodbus
server (``SimDevice`` / ``SimData`` model) built inside its own asyncio event
loop running in a thread (:class:`ModbusServerThread`); several units may
share an endpoint, as drives on one RS-485 line do. Register values are filled
from the :class:`~elastocal.sims.world.SimWorld` whenever they are read, with
the register map of the cell config, so the simulated device and the driver
agree by construction on nothing but the config.

Serial lines are pairs of pseudo-terminals bridged by a thread
(:class:`PtyPair`, a null modem): the server opens one end, the driver the
other, both through pyserial.

Fault injection (tests): ``SimModbusDrive.fault``, ``.fail_with``,
``.delay_replies``; ``ModbusServerThread.corrupt_replies``,
``.drop_connections``.
"""

from __future__ import annotations

import asyncio
import os
import select
import threading
import tty
from typing import Sequence

from pymodbus.constants import ExcCodes
from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from elastocal.drivers.base import (
    COMMAND_MOVE_JOINTS,
    COMMAND_MOVE_POSE,
    COMMAND_RUN_UV,
    COMMAND_RUN_VU,
    STATUS_BUSY,
    STATUS_FAULT,
    STATUS_IN_POSITION,
    STATUS_RUN_DONE,
)
from elastocal.drivers.config import ControllerConfig, DriveConfig
from elastocal.drivers.registers import RegisterSpec
from elastocal.drivers.modbus import decode, encode
from elastocal.errors import InputError
from elastocal.sims.world import SimWorld

#: controller error codes (``error`` register)
ERROR_UNKNOWN_COMMAND = 1
ERROR_UNKNOWN_POSE = 2
ERROR_UNKNOWN_PATH = 3
ERROR_BAD_TARGET = 4
ERROR_BUSY = 5
ERROR_NOT_DECLARED = 6


def _simdata(specs: Sequence[RegisterSpec]) -> list[SimData]:
    seen: dict[int, str] = {}
    out = []
    for s in specs:
        for a in range(s.address, s.address + s.n_registers):
            if a in seen:
                raise InputError(f"the simulated device keeps holding and input registers in one address "
                                 f"space; {seen[a]} and {s.name} overlap at {a}")
            seen[a] = s.name
        out.append(SimData(s.address, count=s.n_registers, values=0, datatype=DataType.REGISTERS,
                           readonly=s.access != "write"))
    return out


def _put(registers: list[int], start_address: int, spec: RegisterSpec, values: Sequence[float]) -> None:
    regs = encode(spec, values)
    i = spec.address - start_address
    registers[i:i + len(regs)] = regs


def identity() -> ModbusDeviceIdentification:
    return ModbusDeviceIdentification(info_name={"VendorName": "elastocal", "ProductCode": "SIM-MODBUS",
                                                 "MajorMinorRevision": "0.1.0"})


# ------------------------------------------------------------------ drives
class SimModbusDrive:
    """A drive exposing its joint's current, position (velocity, torque, status) in registers."""

    STATUS_READY = 0x0001
    STATUS_FAULT = 0x0008

    def __init__(self, config: DriveConfig, world: SimWorld, *, reply_delay_s: float = 0.0) -> None:
        self.config = config
        self.world = world
        self.joint = config.joint
        self.unit = config.url.settings.unit       # the backend's parameters, parsed with the URL
        self.reply_delay_s = float(reply_delay_s)
        self._faulted = False
        self._exceptions: list[int] = []
        self._delays: list[float] = []
        self._lock = threading.Lock()
        self.device = SimDevice(id=self.unit, simdata=_simdata(config.registers), action=self._action)

    # faults
    def fault(self, on: bool = True) -> None:
        """Set (or clear) the fault bit of the status register."""
        with self._lock:
            self._faulted = on

    def fail_with(self, code: int = 4, count: int = 1) -> None:
        """Answer the next ``count`` requests with Modbus exception ``code`` (4: device failure)."""
        with self._lock:
            self._exceptions += [code] * count

    def delay_replies(self, seconds: float, count: int = 1) -> None:
        """Answer the next ``count`` requests ``seconds`` late."""
        with self._lock:
            self._delays += [seconds] * count

    def status_word(self) -> int:
        with self._lock:
            return self.STATUS_FAULT if self._faulted else self.STATUS_READY

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        with self._lock:
            code = self._exceptions.pop(0) if self._exceptions else None
            delay = self._delays.pop(0) if self._delays else self.reply_delay_s
        if delay:
            await asyncio.sleep(delay)
        if code is not None:
            return ExcCodes(code)
        if set_values is not None:
            return None
        s = self.world.sample()
        j = self.joint - 1
        current = float(s.currents_a[j])
        values = {"current": current, "position": float(s.q[j]), "velocity": float(s.dq[j]),
                  "torque": float(self.world.robot.torque_constants[j]) * current,
                  "status": float(self.status_word())}
        for spec in self.config.registers:
            v = values[spec.name]
            if spec.name == "status":
                v = v * spec.si_factor
            _put(registers, start_address, spec, [v])
        return None


# -------------------------------------------------------------- controller
class _Refused(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


class SimCellController:
    """The cell controller: poses and paths of ``config`` executed on ``world``."""

    def __init__(self, config: ControllerConfig, world: SimWorld, *, reply_delay_s: float = 0.0) -> None:
        self.config = config
        self.world = world
        self.unit = config.url.settings.unit
        self.reply_delay_s = float(reply_delay_s)
        self._lock = threading.Lock()
        self._ack = 0
        self._status = STATUS_IN_POSITION
        self._error = 0
        self._jobs: list = []
        #: (first address, register count) of every write request, in order
        self.writes: list[tuple[int, int]] = []
        self._wake = threading.Condition(self._lock)
        self._stop = False
        self._worker = threading.Thread(target=self._work, name="sim-controller", daemon=True)
        self._worker.start()
        self.device = SimDevice(id=self.unit, simdata=_simdata(config.registers), action=self._action)
        self._spec = {r.name: r for r in config.registers}

    def _value(self, registers: list[int], start: int, name: str, default: float | None = None) -> list[float]:
        spec = self._spec.get(name)
        if spec is None:
            if default is None:
                raise KeyError(name)
            return [default]
        i = spec.address - start
        return decode(spec, registers[i:i + spec.n_registers])

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        if self.reply_delay_s:
            await asyncio.sleep(self.reply_delay_s)
        if set_values is None:
            with self._lock:
                values = {"ack": self._ack, "status": self._status, "error": self._error}
            for name in ("ack", "status", "error"):
                if name in self._spec:
                    _put(registers, start_address, self._spec[name], [values[name]])
            if "q" in self._spec:
                _put(registers, start_address, self._spec["q"], list(self.world.q_now()))
            return None
        with self._lock:
            self.writes.append((address, len(set_values)))
        seq_spec = self._spec["sequence"]
        first = address
        last = address + len(set_values) - 1
        if not (first <= seq_spec.address and seq_spec.address + seq_spec.n_registers - 1 <= last):
            return None
        i = seq_spec.address - address
        sequence = int(decode(seq_spec, list(set_values[i:i + seq_spec.n_registers]))[0])
        # registers written by earlier requests hold the parameters; this request may hold some too
        merged = list(registers)
        merged[address - start_address:address - start_address + len(set_values)] = list(set_values)
        self._accept(sequence, merged, start_address)
        return None

    def _accept(self, sequence: int, registers: list[int], start: int) -> None:
        with self._lock:
            self._ack = sequence
            if self._status & STATUS_BUSY:
                self._status = STATUS_BUSY | STATUS_FAULT
                self._error = ERROR_BUSY
                return
            self._status = STATUS_BUSY
            self._error = 0
        try:
            command = int(self._value(registers, start, "command")[0])
            job = self._job(command, registers, start)
        except _Refused as exc:
            self._finish(0, exc.code)
            return
        except KeyError:
            self._finish(0, ERROR_NOT_DECLARED)
            return
        with self._lock:
            self._jobs.append(job)
            self._wake.notify()

    def _job(self, command: int, registers: list[int], start: int):
        cfg = self.config
        if command == COMMAND_MOVE_POSE:
            number = int(self._value(registers, start, "pose")[0])
            q = dict(cfg.poses).get(number)
            if q is None:
                raise _Refused(ERROR_UNKNOWN_POSE)
            return (STATUS_IN_POSITION, lambda: self.world.move_to(q))
        if command == COMMAND_MOVE_JOINTS:
            q = self._value(registers, start, "target")
            return (STATUS_IN_POSITION, lambda: self.world.move_to(q))
        if command in (COMMAND_RUN_UV, COMMAND_RUN_VU):
            number = int(self._value(registers, start, "path")[0])
            path = next((p for p in cfg.paths if p.id == number), None)
            if path is None:
                raise _Refused(ERROR_UNKNOWN_PATH)
            speed = self._value(registers, start, "speed", 0.0)[0]
            speed = speed if speed > 0 else path.speed_rad_s
            u, v = (path.u, path.v) if command == COMMAND_RUN_UV else (path.v, path.u)
            return (STATUS_RUN_DONE, lambda: self.world.run(u, v, speed))
        raise _Refused(ERROR_UNKNOWN_COMMAND)

    def _finish(self, done_bit: int, error: int) -> None:
        with self._lock:
            if error:
                self._status = STATUS_FAULT
                self._error = error
            else:
                self._status = done_bit
                self._error = 0

    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._jobs and not self._stop:
                    self._wake.wait()
                if self._stop:
                    return
                done_bit, start_motion = self._jobs.pop(0)
            try:
                duration = start_motion()
            except InputError:
                self._finish(0, ERROR_BAD_TARGET)
                continue
            while not self.world.wait_idle(min(duration + 1.0, 0.5)):
                with self._lock:
                    if self._stop:
                        return
            self._finish(done_bit, 0)

    def close(self) -> None:
        with self._lock:
            self._stop = True
            self._wake.notify_all()
        self._worker.join(timeout=5.0)


# ------------------------------------------------------------------ server
class ModbusServerThread:
    """A pymodbus server for ``devices`` in its own event-loop thread.

    ``tcp=(host, port)`` (port 0: ephemeral) or ``serial=path``."""

    def __init__(self, devices: Sequence[SimDevice], *, tcp: tuple[str, int] | None = None,
                 serial: str | None = None, baudrate: int = 115200,
                 identity: ModbusDeviceIdentification | None = None) -> None:
        if (tcp is None) == (serial is None):
            raise ValueError("give exactly one of tcp= and serial=")
        self._devices = list(devices)
        self._tcp = tcp
        self._serial = serial
        self._baudrate = baudrate
        self._identity = identity
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._corrupt = 0
        self._lock = threading.Lock()
        self.port: int | None = None
        #: every request received, decoded by pymodbus: (device id, function code, first address,
        #: registers or bits read or written)
        self.requests: list[tuple[int, int, int, int]] = []

    def corrupt_replies(self, count: int = 1) -> None:
        """Flip a bit in the next ``count`` replies (a TCP reply gets a wrong protocol id)."""
        with self._lock:
            self._corrupt += count

    def _trace_pdu(self, sending: bool, pdu):
        if not sending:
            with self._lock:
                count = len(pdu.registers) if pdu.registers else (len(pdu.bits) if pdu.bits else pdu.count)
                self.requests.append((pdu.dev_id, pdu.function_code, pdu.address, count))
        return pdu

    def _trace(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            return data
        with self._lock:
            if self._corrupt <= 0:
                return data
            self._corrupt -= 1
        i = 2 if self._tcp is not None else len(data) // 2
        return data[:i] + bytes([data[i] ^ 0x10]) + data[i + 1:]

    def start(self) -> "ModbusServerThread":
        self._thread = threading.Thread(target=self._run, name="sim-modbus", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise self._error
        if not self._ready.is_set():
            raise RuntimeError("the Modbus server did not start")
        return self

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._serve())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _serve(self) -> None:
        if self._tcp is not None:
            self._server = ModbusTcpServer(self._devices, address=self._tcp, identity=self._identity or identity(),
                                           trace_packet=self._trace, trace_pdu=self._trace_pdu)
        else:
            self._server = ModbusSerialServer(self._devices, port=self._serial, baudrate=self._baudrate,
                                              identity=self._identity or identity(), trace_packet=self._trace,
                                              trace_pdu=self._trace_pdu)
        await self._server.serve_forever(background=True)
        if self._tcp is not None:
            self.port = self._server.transport.sockets[0].getsockname()[1]

    async def _shutdown(self) -> None:
        await self._server.shutdown()
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in tasks:            # requests still waiting (delayed replies) end here
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    def drop_connections(self) -> None:
        """Close every client connection (the listener stays)."""
        done = threading.Event()

        def drop():
            for conn in list(self._server.active_connections.values()):
                conn.close()
            done.set()

        if self._loop is not None:
            self._loop.call_soon_threadsafe(drop)
            done.wait(5.0)

    def close(self) -> None:
        if self._loop is None or self._thread is None:
            return
        if self._server is not None and self._loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop)
            try:
                fut.result(5.0)
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)
        self._thread = None


# ------------------------------------------------------------------- ptys
class PtyPair:
    """Two pseudo-terminals joined by a thread, like a null-modem cable:
    bytes written to one end come out of the other."""

    def __init__(self) -> None:
        self._fds = []
        self.paths = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)
            self._fds.append((master, slave))
            self.paths.append(os.ttyname(slave))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="sim-null-modem", daemon=True)
        self._thread.start()

    @property
    def device_end(self) -> str:
        return self.paths[0]

    @property
    def host_end(self) -> str:
        return self.paths[1]

    def _pump(self) -> None:
        a, b = self._fds[0][0], self._fds[1][0]
        peer = {a: b, b: a}
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([a, b], [], [], 0.1)
            except (OSError, ValueError):
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                view = memoryview(data)
                while view:
                    try:
                        n = os.write(peer[fd], view)
                    except OSError:
                        break
                    view = view[n:]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for master, slave in self._fds:
            for fd in (master, slave):
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._fds = []
