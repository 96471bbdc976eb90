"""The load rig of a served simulated cell: how a load is hung across processes (the device side).

``elastocal sim serve`` runs the simulated world in its own process; the
guided procedure (``elastocal calibrate``) runs in another and asks the
operator to hang each load. In the served cell nobody can: the load rig is
the operator's hands. It is a Modbus device of its own (a pymodbus server on
127.0.0.1, port chosen free) that ``sim serve --write-cell`` names in the
written config as ``[sim] load_url``; when the operator confirms a load
change, the procedure writes the load's wrench there
(:class:`elastocal.drivers.load_rig.ModbusLoadRig`) and the served world
carries it.

Registers: the one block of :data:`elastocal.drivers.load_rig.WRENCH` (holding,
float32, big-endian words, at 0..11): fx, fy, fz [N], mx, my, mz [N*m] at the load
point, written in one request; all zero removes the load. The rig says what it is
in its device identification (ProductCode :data:`~elastocal.drivers.load_rig.PRODUCT_CODE`),
which the driver checks before it writes anything.
"""

from __future__ import annotations

import threading

from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.simulator import DataType, SimData, SimDevice

from elastocal.drivers.load_rig import PRODUCT_CODE, UNIT as LOAD_RIG_UNIT, WRENCH
from elastocal.drivers.modbus import decode
from elastocal.sims.world import SimWorld


def rig_identity() -> ModbusDeviceIdentification:
    return ModbusDeviceIdentification(info_name={"VendorName": "elastocal", "ProductCode": PRODUCT_CODE,
                                                 "MajorMinorRevision": "0.1.0"})


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
