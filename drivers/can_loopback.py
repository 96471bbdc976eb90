"""A CAN bus across processes that never leaves the machine: python-can's
``udp_multicast`` kept on the loopback interface (python-can interface
``udp_loopback``).

python-can's ``udp_multicast`` binds its socket to every interface
(0.0.0.0) and joins its multicast group on the default (external)
interface, on a port all its users share: simulated CAN traffic then reaches
the network, and any host on it can inject frames. :class:`LoopbackUdpBus`
is the same bus — python-can's framing (msgpack), receive path and
timestamps, unchanged — with its socket

* bound to the group address (so unicast datagrams to the port, from
  anywhere, are never delivered), joined on ``lo`` (127.0.0.1) only, sending
  through ``lo`` with a multicast TTL of 0 (never forwarded off the host);
* on a port of its own: ``port=0`` lets the kernel choose a free port (the
  first bus of a simulated cell does; :attr:`LoopbackUdpBus.port` gives it,
  and the others join with it).

It is registered as a python-can interface (entry point ``can.interface``,
name ``udp_loopback``), and :func:`open_can_bus` opens it — or any other
python-can interface — from a device URL's interface and channel.
"""

from __future__ import annotations

import socket
import struct
from typing import Any

import can
from can.interfaces.udp_multicast.bus import SO_TIMESTAMPNS, GeneralPurposeUdpMulticastBus, UdpMulticastBus

from elastocal.errors import InputError

INTERFACE = "udp_loopback"
#: the default group (organisation-local scope; not python-can's default group, which other
#: programs use off the machine)
DEFAULT_GROUP = "239.255.74.163"
LOOPBACK_ADDRESS = "127.0.0.1"


class _LoopbackMulticast(GeneralPurposeUdpMulticastBus):
    """python-can's multicast socket handler with the socket on loopback (IPv4)."""

    def _create_socket(self, address_family: socket.AddressFamily) -> socket.socket:
        if address_family != socket.AF_INET:
            raise OSError(f"{INTERFACE} is IPv4 only (a 239.x.y.z group), got {self.group!r}")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 0))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOPBACK_ADDRESS))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
                self.timestamp_nanosecond = True
            except OSError:
                self.timestamp_nanosecond = False
            sock.bind((self.group, self.port))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                            socket.inet_aton(self.group) + socket.inet_aton(LOOPBACK_ADDRESS))
        except OSError:
            sock.close()
            raise
        self.port = sock.getsockname()[1]      # the kernel's choice for port 0
        return sock


class LoopbackUdpBus(UdpMulticastBus):
    """python-can's ``udp_multicast`` on the loopback interface only (see the module docstring).

    ``channel``: an IPv4 multicast group (default :data:`DEFAULT_GROUP`);
    ``port``: the UDP port, 0 for a free one (then read :attr:`port`).
    """

    def __init__(self, channel: str = DEFAULT_GROUP, port: int = 0, receive_own_messages: bool = False,
                 fd: bool = True, **kwargs: Any) -> None:
        if receive_own_messages:
            raise can.CanInterfaceNotImplementedError("receiving own messages is not implemented")
        can.BusABC.__init__(self, channel, **kwargs)
        self._multicast = _LoopbackMulticast(channel, int(port), 0)   # CanInitializationError if it cannot
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self.channel_info = f"{INTERFACE} {channel}:{self.port} (127.0.0.1 only)"

    @property
    def port(self) -> int:
        """The UDP port the bus uses (the kernel's choice when opened with ``port=0``)."""
        return self._multicast.port

    def local_address(self) -> tuple[str, int]:
        """The address the socket is bound to (group, port)."""
        return self._multicast._socket.getsockname()

    @staticmethod
    def _detect_available_configs() -> list:
        return [{"interface": INTERFACE, "channel": DEFAULT_GROUP}]


def open_can_bus(interface: str, channel: str, **kwargs: Any) -> can.BusABC:
    """A python-can bus; ``udp_loopback`` is opened from this module directly (it
    need not be installed as an entry point to work), every other interface
    through python-can's registry."""
    try:
        if interface == INTERFACE:
            return LoopbackUdpBus(channel=channel, **kwargs)
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        # no such interface or channel on this machine: the URL is wrong (or the adapter is not plugged in)
        reason = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        raise InputError(f"cannot open CAN interface {interface!r}, channel {channel!r}: {reason}; check the "
                         "device URL (canopen://INTERFACE/CHANNEL?node=N) and that the adapter is there") from None
