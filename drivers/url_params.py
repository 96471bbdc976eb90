"""What each built-in backend reads from its device URL, as frozen parameters.

A device URL is parsed once (:func:`elastocal.drivers.urls.parse_device_url`): the
syntax there, then the backend's parameter class of its scheme (the table
:data:`elastocal.drivers.URL_PARAMS`) checks and converts the query and the
address into the fields below, kept on the URL as ``url.settings``. The backends
read those fields and parse nothing again. The classes live in this light module,
not in the backends' own, so that reading a cell.toml imports no device library
(canopen, pymodbus, the emScon packets); the guidance and force-sensor backends,
which import none, declare theirs in their own modules.
"""

from __future__ import annotations

from dataclasses import dataclass

from elastocal.errors import InputError

#: the emScon server's TCP port when the URL gives none
EMSCON_DEFAULT_PORT = 700


@dataclass(frozen=True)
class CanopenParams:
    """``canopen://INTERFACE/CHANNEL?node=N[&bitrate=B][&eds=FILE][&port=P]``"""

    interface: str
    channel: str
    node: int
    bitrate: int = 1_000_000
    eds: str | None = None
    #: the UDP port of a udp_multicast/udp_loopback bus (None: python-can's default; 0 in a cell
    #: the simulator serves: chosen when served)
    port: int | None = None

    @classmethod
    def from_url(cls, url, *, source: str = "url") -> "CanopenParams":
        if not url.host:
            raise InputError(f"{url.text}: give the python-can interface, e.g. canopen://virtual/cell?node=5",
                             source=source)
        channel = url.path.lstrip("/")
        if not channel:
            raise InputError(f"{url.text}: give the CAN channel after the interface, e.g. "
                             "canopen://virtual/cell?node=5", source=source)
        if url.param("node") is None:
            raise InputError(f"{url.text}: the node id is missing (?node=1..127)", source=source)
        port = url.int_param("port", 0, source=source, low=0, high=65535) if url.param("port") is not None else None
        return cls(interface=url.host, channel=channel, node=url.int_param("node", 0, source=source, low=1, high=127),
                   bitrate=url.int_param("bitrate", 1_000_000, source=source, low=10_000, high=1_000_000),
                   eds=url.param("eds") or None, port=port)


def _host_port(url, source: str, example: str) -> tuple[str, int]:
    if not url.host or url.port is None:
        raise InputError(f"{url.text}: give host and port, e.g. {example}", source=source)
    return url.host, int(url.port)


def _serial_device(url, source: str) -> str:
    if not url.path:
        raise InputError(f"{url.text}: give the serial device, e.g. {url.scheme}:///dev/ttyUSB0?baud=115200",
                         source=source)
    return url.path


@dataclass(frozen=True)
class ModbusTcpParams:
    """``modbus+tcp://HOST:PORT[?unit=U]`` (unit 0..247, default 1)"""

    host: str
    port: int
    unit: int = 1

    @classmethod
    def from_url(cls, url, *, source: str = "url") -> "ModbusTcpParams":
        host, port = _host_port(url, source, "modbus+tcp://127.0.0.1:1502")
        return cls(host=host, port=port, unit=url.int_param("unit", 1, source=source, low=0, high=247))


@dataclass(frozen=True)
class ModbusRtuParams:
    """``modbus+rtu:///dev/X?baud=B[&parity=N|E|O][&unit=U]`` (unit 1..247, default 1)"""

    device: str
    baud: int = 115200
    parity: str = "N"
    unit: int = 1

    @classmethod
    def from_url(cls, url, *, source: str = "url") -> "ModbusRtuParams":
        device = _serial_device(url, source)
        parity = (url.param("parity") or "N").upper()
        if parity not in ("N", "E", "O"):
            raise InputError(f"{url.text}: parity must be N, E or O", source=source)
        return cls(device=device, baud=url.int_param("baud", 115200, source=source, low=300, high=10_000_000),
                   parity=parity, unit=url.int_param("unit", 1, source=source, low=1, high=247))


@dataclass(frozen=True)
class TrackerTcpParams:
    """``tracker+tcp://HOST:PORT``"""

    host: str
    port: int

    @classmethod
    def from_url(cls, url, *, source: str = "url") -> "TrackerTcpParams":
        host, port = _host_port(url, source, "tracker+tcp://127.0.0.1:7000")
        return cls(host=host, port=port)


@dataclass(frozen=True)
class TrackerSerialParams:
    """``tracker+serial:///dev/X?baud=B``"""

    device: str
    baud: int = 115200

    @classmethod
    def from_url(cls, url, *, source: str = "url") -> "TrackerSerialParams":
        return cls(device=_serial_device(url, source),
                   baud=url.int_param("baud", 115200, source=source, low=300, high=10_000_000))


@dataclass(frozen=True)
class EmsconParams:
    """``tracker+emscon://HOST[:PORT][?initialize=0|1][&init_timeout_s=S][&reflector=R][&reflector.M=R]``"""

    host: str
    port: int = EMSCON_DEFAULT_PORT
    initialize: bool = True
    init_timeout_s: float = 120.0
    #: the reflector (name or id) for every marker, and per marker (marker, reflector)
    reflector: str | None = None
    marker_reflectors: tuple[tuple[str, str], ...] = ()

    def reflector_for(self, marker: str) -> str | None:
        return dict(self.marker_reflectors).get(marker, self.reflector)

    @classmethod
    def from_url(cls, url, *, source: str = "url") -> "EmsconParams":
        if not url.host:
            raise InputError(f"{url.text}: give the emScon server, e.g. tracker+emscon://192.168.0.1:700",
                             source=source)
        init = url.param("initialize", "1")
        if init not in ("0", "1"):
            raise InputError(f"initialize={init!r} must be 0 or 1 in {url.text}", source=source)
        return cls(host=url.host, port=EMSCON_DEFAULT_PORT if url.port is None else int(url.port),
                   initialize=init == "1",
                   init_timeout_s=url.float_param("init_timeout_s", 120.0, source=source),
                   reflector=url.param("reflector"),
                   marker_reflectors=tuple((k[len("reflector."):], v) for k, v in url.params
                                           if k.startswith("reflector.")))
