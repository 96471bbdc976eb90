"""The cell controller over Modbus (``modbus+tcp://`` or ``modbus+rtu://``).

The handshake itself lives in :class:`~elastocal.drivers.base.CellController`;
this backend maps it onto the registers of ``[controller.registers]``. It
writes only registers the config declares with ``access = "write"`` and reads
the rest; a request that needs an undeclared register is refused before
anything is written.
"""

from __future__ import annotations

from elastocal.drivers.base import CellController, ControllerStatus, SharedLinks
from elastocal.drivers.samples import DeviceInfo
from elastocal.drivers.config import ControllerConfig
from elastocal.drivers.modbus import encode
from elastocal.drivers.modbus_drive import acquire_link
from elastocal.errors import InputError, ProtocolError


class ModbusCellController(CellController):
    def __init__(self, config: ControllerConfig, *, links: SharedLinks | None = None) -> None:
        super().__init__(config.url, timeout_s=config.timeout_s, retries=config.retries,
                         move_timeout_s=config.move_timeout_s)
        self.config = config
        self.unit = config.url.settings.unit
        self.link, self._release_link = acquire_link(config.url, config.timeout_s, links)
        self._read_specs = tuple(r for r in config.registers if r.access == "read")

    def _reconnect(self) -> None:
        self.link.connect()

    def _identify(self) -> DeviceInfo:
        info = self.link.identify(unit=self.unit)
        st = self._status()
        return DeviceInfo(kind="controller", url=self.url.text, vendor=info.get(0, "unknown"),
                          model=info.get(1, "Modbus cell controller (no device identification)"),
                          revision=info.get(2, ""),
                          details=(("unit", str(self.unit)), ("status", f"0x{st.status:04X}"),
                                   ("ack", str(st.ack)),
                                   ("writes", ", ".join(r.name for r in self.config.registers
                                                        if r.access == "write"))))

    def _status(self) -> ControllerStatus:
        values = self.link.read_specs(self._read_specs, unit=self.unit)

        def as_int(name: str) -> int:
            spec = self.config.register(name)
            v = values[name][0] / spec.si_factor
            if v != int(v) or v < 0:
                raise ProtocolError(f"controller: register {name} holds {v!r}, not a count")
            return int(v)

        q = tuple(values["q"]) if "q" in values else None
        return ControllerStatus(ack=as_int("ack"), status=as_int("status"),
                                error=as_int("error") if "error" in values else 0, q=q)

    def _writable(self, name: str):
        spec = self.config.register(name)
        if spec is None:
            raise InputError(f"controller: this request needs the {name!r} register; declare it in "
                             "[controller.registers]")
        if spec.access != "write":
            raise InputError(f"controller: register {name!r} is not declared writable (access = 'write')")
        return spec

    def _request(self, command: int, params: dict[str, object], sequence: int) -> None:
        writes = []
        for name, value in params.items():
            spec = self._writable(name)
            values = list(value) if isinstance(value, tuple) else [value]
            encode(spec, values)            # a value that does not fit is refused before anything is written
            writes.append((spec, values))
        writes.append((self._writable("command"), [command]))
        writes.append((self._writable("sequence"), [sequence]))
        for spec, values in writes:   # the sequence number goes last: it is the strobe
            self.link.write_spec(spec, values, unit=self.unit)

    def _close(self) -> None:
        self._release_link()
