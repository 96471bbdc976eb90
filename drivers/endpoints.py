"""Where devices listen, and what devices sharing an endpoint must not share.

Checked when cell.toml is read (:func:`elastocal.drivers.config.parse_cell_config`) and
for a simulated cell's load rig (:func:`elastocal.sims.config.sim_config`): devices on one
TCP endpoint or serial line speak one protocol, and Modbus devices on one unit of it
never share a register.
"""

from __future__ import annotations

from elastocal.drivers.registers import RegisterSpec
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import InputError


def endpoint(url: DeviceUrl) -> tuple | None:
    """Where a device listens: ("tcp", host, port) or ("serial", path); None for CAN (its node
    ids are checked apart). An ephemeral port (0, a simulated device's) is its own endpoint per URL,
    as the simulated cell serves it."""
    if url.scheme in ("modbus+tcp", "tracker+tcp", "tracker+emscon"):
        host = "127.0.0.1" if url.host.lower() == "localhost" else url.host.lower()
        port = url.port if url.port is not None else (700 if url.scheme == "tracker+emscon" else None)
        return ("tcp", host, port) if port != 0 else ("tcp", host, 0, url.text)
    if url.scheme in ("modbus+rtu", "tracker+serial"):
        return ("serial", url.path)
    return None


def modbus_unit(url: DeviceUrl) -> int:
    return url.settings.unit


def check_endpoints(devices: list[tuple[str, DeviceUrl, tuple[RegisterSpec, ...]]], *, source: str) -> None:
    """Devices (name, URL, register map) that share an endpoint must speak one protocol, and
    Modbus devices on one unit must not share a register: one device's write would change
    another's reading (a command aliasing a drive's current)."""
    by_endpoint: dict[tuple, list[tuple[str, DeviceUrl, tuple[RegisterSpec, ...]]]] = {}
    for name, url, regs in devices:
        key = endpoint(url)
        if key is not None:
            by_endpoint.setdefault(key, []).append((name, url, regs))
    for members in by_endpoint.values():
        protocols = {url.scheme.split("+")[0] for _, url, _ in members}
        if len(protocols) > 1:
            names = " and ".join(f"{n} ({u.text})" for n, u, _ in members)
            raise InputError(f"{names} are on one endpoint but speak different protocols; give each its own "
                             "address", source=source)
        taken: dict[tuple[int, str, int], tuple[str, str]] = {}
        for name, url, regs in members:
            if not url.scheme.startswith("modbus"):
                if len(members) > 1:
                    raise InputError(f"{' and '.join(n for n, _, _ in members)} share the endpoint of {url.text}",
                                     source=source)
                continue
            unit = modbus_unit(url)
            for spec in regs:
                for a in range(spec.address, spec.address + spec.n_registers):
                    key = (unit, spec.table, a)
                    if key in taken and taken[key][0] != name:
                        other, other_reg = taken[key]
                        raise InputError(f"{name}'s register {spec.name} and {other}'s register {other_reg} are "
                                         f"both {spec.table} register {a} of unit {unit} on {url.text}: one "
                                         "device's value would be read or written as the other's",
                                         source=source)
                    taken[key] = (name, spec.name)
