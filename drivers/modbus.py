"""Modbus TCP and RTU links (pymodbus sync clients) with typed errors.

``modbus+tcp://HOST:PORT?unit=N`` and ``modbus+rtu:///dev/ttyX?baud=B&unit=N``.
pymodbus does the framing; this module maps its failures onto elastocal's
errors (no reply: :class:`DeviceTimeout`; lost or refused connection:
:class:`DeviceDisconnected`; exception response:
:class:`~elastocal.drivers.base.ModbusExceptionError`; garbled reply:
:class:`ProtocolError`) and converts register values with the register map of
the cell config (:class:`~elastocal.drivers.registers.RegisterSpec`).
"""

from __future__ import annotations

import math
import threading
from typing import Sequence

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse

from elastocal.drivers.base import ModbusExceptionError
from elastocal.drivers.registers import RegisterSpec
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import DeviceDisconnected, DeviceTimeout, InputError, ProtocolError

#: the most registers one read request may ask for (Modbus limit)
MAX_READ = 125

_DATATYPES = {"int16": "INT16", "uint16": "UINT16", "int32": "INT32", "uint32": "UINT32",
              "float32": "FLOAT32", "float64": "FLOAT64"}


def register_runs(specs: Sequence[RegisterSpec]) -> list[tuple[str, int, int]]:
    """Contiguous (table, first address, count) blocks covering ``specs``."""
    runs: list[tuple[str, int, int]] = []
    for table in ("holding", "input"):
        spans = sorted((s.address, s.address + s.n_registers) for s in specs if s.table == table)
        for start, end in spans:
            if runs and runs[-1][0] == table and start <= runs[-1][1] + runs[-1][2] \
                    and max(end, runs[-1][1] + runs[-1][2]) - runs[-1][1] <= MAX_READ:
                t, a, n = runs[-1]
                runs[-1] = (t, a, max(end, a + n) - a)
            else:
                runs.append((table, start, end - start))
    return runs


def decode(spec: RegisterSpec, registers: Sequence[int]) -> list[float]:
    """Values of ``spec`` in SI units from its raw registers (always a list of ``spec.count``)."""
    if len(registers) != spec.n_registers:
        raise ProtocolError(f"{spec.name}: expected {spec.n_registers} registers, got {len(registers)}")
    dtype = ModbusTcpClient.DATATYPE[_DATATYPES[spec.type]]
    raw = ModbusTcpClient.convert_from_registers(list(registers), dtype, word_order=spec.word_order)
    values = raw if isinstance(raw, list) else [raw]
    return [float(v) * spec.si_factor for v in values]


def encode(spec: RegisterSpec, values: Sequence[float]) -> list[int]:
    """Registers for SI ``values`` of ``spec`` (inverse of :func:`decode`)."""
    if len(values) != spec.count:
        raise InputError(f"{spec.name}: expected {spec.count} value(s), got {len(values)}")
    dtype = ModbusTcpClient.DATATYPE[_DATATYPES[spec.type]]
    raws: list[float | int] = []
    for v in values:
        x = float(v) / spec.si_factor
        if not math.isfinite(x):
            raise InputError(f"{spec.name}: value {v!r} is not finite")
        if spec.type.startswith(("int", "uint")):
            xi = int(round(x))
            bits = 16 if spec.type.endswith("16") else 32
            low, high = (0, 2**bits - 1) if spec.type.startswith("u") else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
            if not low <= xi <= high:
                raise InputError(f"{spec.name}: {v!r} does not fit in {spec.type} with scale {spec.scale:g}")
            raws.append(xi)
        else:
            raws.append(x)
    return ModbusTcpClient.convert_to_registers(raws if len(raws) > 1 else raws[0], dtype,
                                               word_order=spec.word_order)


class ModbusLink:
    """One Modbus connection (TCP socket or serial line), shared by the units on it."""

    def __init__(self, url: DeviceUrl, *, timeout_s: float) -> None:
        self.url = url
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        settings = url.settings               # drivers.url_params.ModbusTcpParams / ModbusRtuParams
        if url.scheme == "modbus+tcp":
            self.where = f"{settings.host}:{settings.port}"
            self.client = ModbusTcpClient(settings.host, port=settings.port, timeout=timeout_s, retries=0,
                                          reconnect_delay=0.0, reconnect_delay_max=0.0)
        else:
            self.where = settings.device
            self.client = ModbusSerialClient(settings.device, baudrate=settings.baud, parity=settings.parity,
                                             timeout=timeout_s,
                                             retries=0, reconnect_delay=0.0, reconnect_delay_max=0.0)
        self.client.set_max_no_responses(1_000_000)
        self.connect()

    def connect(self) -> None:
        with self._lock:
            try:
                ok = self.client.connect()
            except (OSError, ModbusException) as exc:
                raise DeviceDisconnected(f"modbus {self.where}: cannot connect: {exc}") from exc
            if not ok:
                raise DeviceDisconnected(f"modbus {self.where}: cannot connect")

    def _execute(self, what: str, fn, *args, **kwargs):
        with self._lock:
            try:
                rr = fn(*args, **kwargs)
            except ConnectionException as exc:
                self.client.close()
                raise DeviceDisconnected(f"modbus {self.where}: {what}: connection lost") from exc
            except ModbusIOException as exc:
                if not self.client.connected:
                    raise DeviceDisconnected(f"modbus {self.where}: {what}: connection lost") from exc
                # a late reply must not answer the next request: start the next one on a fresh connection
                self.client.close()
                raise DeviceTimeout(f"modbus {self.where}: {what}: no valid reply within "
                                    f"{self.timeout_s:g} s") from exc
            except (ModbusException, ValueError, IndexError) as exc:
                raise ProtocolError(f"modbus {self.where}: {what}: {exc}") from exc
            except OSError as exc:
                self.client.close()
                raise DeviceDisconnected(f"modbus {self.where}: {what}: {exc}") from exc
        if isinstance(rr, ExceptionResponse) or rr.isError():
            code = getattr(rr, "exception_code", 0)
            raise ModbusExceptionError(f"modbus {self.where}: {what}", code)
        return rr

    def read(self, table: str, address: int, count: int, *, unit: int) -> list[int]:
        fn = self.client.read_holding_registers if table == "holding" else self.client.read_input_registers
        rr = self._execute(f"read {table} {address}..{address + count - 1} (unit {unit})", fn, address,
                           count=count, device_id=unit)
        regs = list(rr.registers)
        if len(regs) != count:
            raise ProtocolError(f"modbus {self.where}: asked {count} registers at {address}, got {len(regs)}")
        return regs

    def read_specs(self, specs: Sequence[RegisterSpec], *, unit: int) -> dict[str, list[float]]:
        """SI values of every spec, read in as few requests as possible."""
        raw: dict[tuple[str, int], int] = {}
        for table, address, count in register_runs(specs):
            for i, v in enumerate(self.read(table, address, count, unit=unit)):
                raw[(table, address + i)] = v
        return {s.name: decode(s, [raw[(s.table, a)] for a in range(s.address, s.address + s.n_registers)])
                for s in specs}

    def write_spec(self, spec: RegisterSpec, values: Sequence[float], *, unit: int) -> None:
        """Write SI ``values`` to the register ``spec`` of the map; refused before anything is sent
        unless the map declares it writable (``access = "write"``): the one way elastocal writes."""
        if spec.access != "write":
            raise InputError(f"modbus {self.where}: register {spec.name!r} (unit {unit}) is not declared "
                             "writable (access = 'write'); nothing was written")
        self._write_registers(spec.address, encode(spec, values), unit=unit)

    def _write_registers(self, address: int, registers: Sequence[int], *, unit: int) -> None:
        regs = list(registers)
        if len(regs) == 1:
            self._execute(f"write register {address} (unit {unit})", self.client.write_register, address,
                          regs[0], device_id=unit)
        else:
            self._execute(f"write registers {address}..{address + len(regs) - 1} (unit {unit})",
                          self.client.write_registers, address, regs, device_id=unit)

    def identify(self, *, unit: int) -> dict[int, str]:
        """Read Device Identification (FC 43/14, basic objects); empty when unsupported."""
        try:
            rr = self._execute(f"read device identification (unit {unit})", self.client.read_device_information,
                               read_code=0x01, object_id=0x00, device_id=unit)
        except ModbusExceptionError as exc:
            if exc.code in (1, 2):
                return {}
            raise
        out = {}
        for key, value in rr.information.items():
            out[int(key)] = value.decode("ascii", "replace") if isinstance(value, bytes) else str(value)
        return out

    def close(self) -> None:
        with self._lock:
            self.client.close()
