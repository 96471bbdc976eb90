"""The load rig of a served simulated cell: how a load is hung across processes.

``elastocal sim serve`` runs the simulated world in its own process; the
guided procedure (``elastocal calibrate``) runs in another and asks the
operator to hang each load. In the served cell nobody can: the load rig is
the operator's hands. It is a Modbus device of its own (a pymodbus server on
127.0.0.1, port chosen free) that ``sim serve --write-cell`` names in the
written config as ``[sim] load_url``; when the operator confirms a load
change, the procedure writes the load's wrench there and the served world
carries it.

Registers (holding, float32, big-endian words): ``wrench`` at 0..11, the
six components fx, fy, fz [N], mx, my, mz [N·m] at the load point, written
in one request; all zero removes the load.

Only a simulated cell has a load rig: the procedure writes to it only when
the config's ``[sim] load_url`` names a Modbus TCP device on 127.0.0.1.
"""

from __future__ import annotations

import threading
from typing import Sequence

from pymodbus.simulator import DataType, SimData, SimDevice

from elastocal.drivers.modbus import decode, encode
from elastocal.drivers.registers import RegisterSpec
from elastocal.drivers.urls import parse_device_url
from elastocal.errors import InputError
from elastocal.sims.world import SimWorld

#: the rig's one register block
WRENCH = RegisterSpec(name="wrench", address=0, type="float32", count=6, access="write")
#: its Modbus unit id
LOAD_RIG_UNIT = 1
LOOPBACK = ("127.0.0.1", "localhost")


class SimLoadRig:
    """Server side: the wrench written to the rig hangs in ``world``."""

    def __init__(self, world: SimWorld, unit: int = LOAD_RIG_UNIT) -> None:
        self.world = world
        self.unit = unit
        self._lock = threading.Lock()
        #: every wrench written, in order (None: removed)
        self.hung: list[tuple[float, ...] | None] = []
        self.device = SimDevice(id=unit, simdata=[SimData(WRENCH.address, count=WRENCH.n_registers, values=0,
                                                          datatype=DataType.REGISTERS, readonly=False)],
                                action=self._action)

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        if set_values is None:
            return None
        if address != WRENCH.address or len(set_values) != WRENCH.n_registers:
            return None      # only the whole wrench, in one request, changes the load
        wrench = tuple(float(v) for v in decode(WRENCH, list(set_values)))
        if any(wrench):
            self.world.set_load(list(wrench))
        else:
            self.world.remove_load()
        with self._lock:
            self.hung.append(wrench if any(wrench) else None)
        return None


class ServedLoads:
    """Client side: hangs loads in the served world through its rig at ``url``
    (``modbus+tcp://127.0.0.1:PORT?unit=1``); ``set_load(wrench)`` and
    ``remove_load()`` as a :class:`~elastocal.sims.world.SimWorld` has them."""

    def __init__(self, url: str, *, timeout_s: float = 1.0, source: str = "cell.toml") -> None:
        from elastocal.drivers.modbus import ModbusLink

        self.url = parse_device_url(url, allowed=("modbus+tcp",), source=f"{source}, sim.load_url")
        if self.url.host not in LOOPBACK:
            raise InputError(f"{url}: a simulated cell's load rig is on 127.0.0.1 only", source=source,
                             column="sim.load_url")
        self.unit = self.url.int_param("unit", LOAD_RIG_UNIT, low=0, high=247)
        self._link = ModbusLink(self.url, timeout_s=timeout_s)

    def set_load(self, wrench: Sequence[float]) -> None:
        self._link.write(WRENCH.address, encode(WRENCH, [float(v) for v in wrench]), unit=self.unit)

    def remove_load(self) -> None:
        self._link.write(WRENCH.address, encode(WRENCH, [0.0] * 6), unit=self.unit)

    def close(self) -> None:
        self._link.close()

    def __enter__(self) -> "ServedLoads":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def served_loads(config) -> ServedLoads | None:
    """The load rig of a served simulated cell (``[sim] load_url`` of ``config``), None for any other cell."""
    from elastocal.sims.config import sim_config

    if not config.sim:
        return None
    url = sim_config(config).load_url
    return ServedLoads(url, source=str(config.source)) if url else None
