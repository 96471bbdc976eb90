"""The load rig of a simulated cell served in another process: the driver side.

``elastocal sim serve`` runs the simulated world in its own process; nobody can
hang a weight in it, so it serves a *load rig* (:mod:`elastocal.sims.load_rig`):
a Modbus TCP device on 127.0.0.1 whose one writable register block is the
wrench on the load point. When the operator confirms a load change, the
procedure writes the load's wrench there through this driver.

What the driver refuses, before anything is written:

* a URL that is not ``modbus+tcp://`` on 127.0.0.1 (a rig is a simulated device);
* a device whose Modbus device identification (FC 43/14) is not the simulated
  rig's (:data:`PRODUCT_CODE`): a ``load_url`` pointing at any other Modbus
  device on the machine is never written;
* a write outside its register map: the wrench is written with
  :meth:`~elastocal.drivers.modbus.ModbusLink.write_spec`, which checks the
  register's access.

A lost connection or a reply that does not come is retried (``retries`` times,
reconnecting first), like every device (:class:`~elastocal.drivers.base.Device`);
its errors name the load rig.
"""

from __future__ import annotations

from typing import Sequence

from elastocal.drivers.base import Device
from elastocal.drivers.registers import RegisterSpec
from elastocal.drivers.samples import DeviceInfo
from elastocal.drivers.urls import DeviceUrl, parse_device_url
from elastocal.errors import DeviceError, InputError

#: the rig's register map: one block, holding, float32 big-endian words: fx, fy, fz [N], mx, my, mz [N*m]
#: on the load point, written in one request (all zero removes the load)
WRENCH = RegisterSpec(name="wrench", address=0, type="float32", count=6, access="write")
#: its Modbus unit id
UNIT = 1
#: what the simulated rig answers to a device identification request (object 1, ProductCode)
PRODUCT_CODE = "SIM-LOAD-RIG"
LOOPBACK = ("127.0.0.1", "localhost")


class ModbusLoadRig(Device):
    """The served rig at ``url`` (see the module docstring); a
    :class:`~elastocal.acquisition.cellio.LoadWorld`: ``hang(wrench)``, ``hang(None)``."""

    kind = "load rig"

    def __init__(self, url: DeviceUrl, *, timeout_s: float = 1.0, retries: int = 2,
                 source: str = "cell.toml") -> None:
        from elastocal.drivers.modbus_drive import acquire_link

        if url.scheme != "modbus+tcp" or url.host not in LOOPBACK:
            raise InputError(f"{url.text}: a simulated cell's load rig is a modbus+tcp device on 127.0.0.1",
                             source=source, column="sim.load_url")
        super().__init__(url, name="load rig", timeout_s=timeout_s, retries=retries)
        self.unit = url.settings.unit if url.param("unit") is not None else UNIT
        try:
            self.link, self._release_link = acquire_link(url, timeout_s, None)
        except DeviceError as exc:
            raise type(exc)(f"load rig {url.text}: {exc}") from exc
        try:
            info = self.identify()
        except BaseException:
            self._release_link()
            raise
        if info.model != PRODUCT_CODE:
            self._release_link()
            raise InputError(f"{url.text} is not a simulated cell's load rig (its device identification says "
                             f"{info.vendor!r} {info.model!r}); nothing was written to it", source=source,
                             column="sim.load_url")

    def _reconnect(self) -> None:
        try:
            self.link.connect()
        except DeviceError as exc:
            raise type(exc)(f"load rig {self.url.text}: {exc}") from exc

    def _identify(self) -> DeviceInfo:
        try:
            info = self.link.identify(unit=self.unit)
        except DeviceError as exc:
            raise type(exc)(f"load rig {self.url.text}: {exc}") from exc
        return DeviceInfo(kind="load rig", url=self.url.text, vendor=info.get(0, "unknown"),
                          model=info.get(1, "no device identification"), revision=info.get(2, ""),
                          details=(("unit", str(self.unit)),))

    def _write(self, wrench: Sequence[float]) -> None:
        try:
            self.link.write_spec(WRENCH, [float(v) for v in wrench], unit=self.unit)
        except DeviceError as exc:
            raise type(exc)(f"load rig {self.url.text}: {exc}") from exc

    def hang(self, wrench: Sequence[float] | None) -> None:
        """Hang ``wrench`` on the load point (None: remove every load)."""
        values = [0.0] * WRENCH.count if wrench is None else list(wrench)
        if len(values) != WRENCH.count:
            raise InputError(f"load rig: a wrench has {WRENCH.count} components, got {len(values)}")
        self._call("hang the load" if wrench is not None else "remove the load", self._write, values)

    def _close(self) -> None:
        self._release_link()


def open_load_rig(text: str, *, source: str = "cell.toml") -> ModbusLoadRig:
    """The load rig named by ``[sim] load_url`` (checked: see the module docstring)."""
    url = parse_device_url(text, allowed=("modbus+tcp",), source=f"{source}, sim.load_url")
    return ModbusLoadRig(url, source=source)
