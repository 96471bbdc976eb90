"""Modbus register maps of cell.toml: one value per :class:`RegisterSpec`, its type,
scale, unit and access (docs/cell-config.md). Validated here so that errors name the
file and the key; nothing here does I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from elastocal.errors import InputError, check_known_keys


#: register value types and their size in 16-bit registers
REGISTER_TYPES = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2, "float64": 4}


#: unit -> (quantity, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "A": ("current", 1.0), "mA": ("current", 1e-3),
    "rad": ("angle", 1.0), "mrad": ("angle", 1e-3), "urad": ("angle", 1e-6),
    "deg": ("angle", math.pi / 180.0),
    "rad/s": ("angular_velocity", 1.0), "mrad/s": ("angular_velocity", 1e-3),
    "deg/s": ("angular_velocity", math.pi / 180.0),
    "N*m": ("torque", 1.0), "1": ("count", 1.0),
}


#: quantity each named drive register must have
DRIVE_REGISTER_QUANTITY = {"current": "current", "position": "angle", "velocity": "angular_velocity",
                           "torque": "torque", "status": "count"}


#: registers of the cell-controller handshake (docs/cell-config.md)
CONTROLLER_REGISTERS = {
    # name: (quantity, may elastocal write it, count: None for one per joint of the robot); every
    # register is read unless the config declares it `access = "write"` (the app writes only what a
    # person declared writable)
    "command": ("count", True, 1), "sequence": ("count", True, 1), "pose": ("count", True, 1),
    "path": ("count", True, 1), "speed": ("angular_velocity", True, 1), "target": ("angle", True, None),
    "ack": ("count", False, 1), "status": ("count", False, 1), "error": ("count", False, 1),
    "q": ("angle", False, None),
}


CONTROLLER_REQUIRED = ("command", "sequence", "ack", "status")


# -------------------------------------------------------------- registers
@dataclass(frozen=True)
class RegisterSpec:
    """One Modbus value: ``value_SI = raw * scale * unit_factor``."""

    name: str
    address: int
    type: str = "uint16"
    count: int = 1
    scale: float = 1.0
    unit: str = "1"
    table: str = "holding"          # "holding" or "input"
    access: str = "read"            # "read" or "write"
    word_order: str = "big"
    fault_mask: int = 0             # status registers: bits meaning "fault"
    ready_mask: int = 0             # status registers: bits that must be set for valid data

    @property
    def n_registers(self) -> int:
        return REGISTER_TYPES[self.type] * self.count

    @property
    def si_factor(self) -> float:
        return self.scale * UNITS[self.unit][1]

    @property
    def quantity(self) -> str:
        return UNITS[self.unit][0]


def _register(name: str, table: Mapping[str, Any], *, source: str, where: str,
              default_access: str = "read", default_count: int = 1) -> RegisterSpec:
    col = f"{where}.{name}"
    if not isinstance(table, Mapping):
        raise InputError("expected an inline table {address = ..., type = ...}", source=source, column=col)
    check_known_keys(table, ("address", "type", "count", "scale", "unit", "table", "access", "word_order",
                             "fault_mask", "ready_mask"), source=source, where=col)
    address = table.get("address")
    if isinstance(address, bool) or not isinstance(address, int) or not 0 <= address <= 65535:
        raise InputError(f"address must be an integer 0..65535, got {address!r}", source=source, column=col)
    rtype = table.get("type", "uint16")
    if rtype not in REGISTER_TYPES:
        raise InputError(f"type must be one of {', '.join(REGISTER_TYPES)}, got {rtype!r}", source=source, column=col)
    count = table.get("count", default_count)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise InputError(f"count must be a positive integer, got {count!r}", source=source, column=col)
    scale = table.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale == 0:
        raise InputError(f"scale must be a finite non-zero number, got {scale!r}", source=source, column=col)
    unit = table.get("unit", "1")
    if unit not in UNITS:
        raise InputError(f"unit must be one of {', '.join(UNITS)}, got {unit!r}", source=source, column=col)
    kind = table.get("table", "holding")
    if kind not in ("holding", "input"):
        raise InputError(f"table must be 'holding' or 'input', got {kind!r}", source=source, column=col)
    access = table.get("access", default_access)
    if access not in ("read", "write"):
        raise InputError(f"access must be 'read' or 'write', got {access!r}", source=source, column=col)
    if access == "write" and kind != "holding":
        raise InputError("only holding registers can be written", source=source, column=col)
    word_order = table.get("word_order", "big")
    if word_order not in ("big", "little"):
        raise InputError(f"word_order must be 'big' or 'little', got {word_order!r}", source=source, column=col)
    masks = {}
    for key in ("fault_mask", "ready_mask"):
        m = table.get(key, 0)
        if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= 0xFFFF:
            raise InputError(f"{key} must be an integer 0..0xFFFF", source=source, column=col)
        masks[key] = m
    if address + REGISTER_TYPES[rtype] * count - 1 > 65535:
        raise InputError("register block runs past address 65535", source=source, column=col)
    return RegisterSpec(name=name, address=address, type=rtype, count=count, scale=float(scale), unit=unit,
                        table=kind, access=access, word_order=word_order, **masks)


def _check_overlaps(specs: tuple[RegisterSpec, ...], *, source: str, where: str) -> None:
    taken: dict[tuple[str, int], str] = {}
    for spec in specs:
        for a in range(spec.address, spec.address + spec.n_registers):
            key = (spec.table, a)
            if key in taken:
                raise InputError(f"register {a} is used by both {taken[key]} and {spec.name}",
                                 source=source, column=f"{where}.{spec.name}")
            taken[key] = spec.name
