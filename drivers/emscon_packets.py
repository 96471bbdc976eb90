"""emScon packets on a socket: CESAPI's packet classes with elastocal's own I/O.

CESAPI (PyPI ``CESAPI``, MIT) generates one class per emScon packet from
Leica's ``ES_C_API_Def.h``: they pack and unpack commands (``...CT``) and
their answers (``...RT``), results and status changes. Only
``CESAPI.packet`` is imported here: CESAPI's ``connection`` and ``command``
modules call ``logging.basicConfig()`` at import and sleep 0.2 s in every
packet-header read, so the socket loop is ours (:class:`PacketSocket`), with
the timeouts of the driver that owns it.

Every emScon packet starts with ``lPacketSize`` (int32, the whole packet,
header included) and ``type`` (ES_DataType); commands and their answers add
the ES_Command; answers and results add an ES_ResultStatus.
"""

from __future__ import annotations

import contextlib
import select
import socket
import struct
import time

from CESAPI import packet as es

from elastocal.errors import DeviceDisconnected, DeviceTimeout, ProtocolError

HEADER = struct.Struct("<iI")
#: the largest packet of the emScon API CESAPI defines is well below this
MAX_PACKET_BYTES = 4096

#: ES_ResultStatus value -> CESAPI constant name (ES_RS_...)
RESULT_NAMES = {v: k for k, v in vars(es).items() if k.startswith("ES_RS_") and isinstance(v, int)}
#: ES_Command value -> name (ES_C_...)
COMMAND_NAMES = {v: k for k, v in vars(es).items() if k.startswith("ES_C_") and isinstance(v, int)}
#: ES_SystemStatusChange value -> name
STATUS_CHANGE_NAMES = {v: k for k, v in vars(es).items()
                       if (k.startswith("ES_SSC_") or k.startswith("ES_SCC_")) and isinstance(v, int)}


def result_name(status: int) -> str:
    return RESULT_NAMES.get(status, f"status {status}")


def command_name(command: int) -> str:
    return COMMAND_NAMES.get(command, f"command {command}")


def packet_type(p) -> int | None:
    return es.packetType(p)


def packet_command(p) -> int | None:
    """The ES_Command of a command or answer packet (None for results, errors, status changes)."""
    info = getattr(p, "packetInfo", None)
    return getattr(info, "command", None) if info is not None else None


def packet_status(p) -> int:
    """The ES_ResultStatus an answer, result or error packet carries (0 when it has none)."""
    if isinstance(p, es.ErrorResponseT):
        return p.status
    info = getattr(p, "packetInfo", None)
    return int(getattr(info, "status", 0)) if info is not None else 0


def decode(data: bytes, *, answers: bool) -> object:
    """One whole packet -> its CESAPI object (``answers``: RT classes, else CT classes).

    Raises ProtocolError when the bytes are not a packet CESAPI knows or the
    size field does not match the packet's layout."""
    if len(data) < HEADER.size:
        raise ProtocolError(f"emScon: packet of {len(data)} bytes is shorter than its header")
    size, kind = HEADER.unpack_from(data)
    try:
        p = es.PacketFactory().packet(data, return_type=answers)
    except (struct.error, AttributeError, TypeError):
        # CESAPI's own error text names its internals ('NoneType' object has no attribute 'unpack'): say
        # what the bytes are instead
        raise ProtocolError(f"emScon: a packet of type {kind}, {size} bytes, is not one CESAPI can decode (a "
                            "type or layout emScon does not send: corrupt bytes on the connection?)") from None
    if p is None:
        raise ProtocolError(f"emScon: unknown packet type {kind}")
    expected = len(p.pack())
    if expected != size or len(data) != size:
        raise ProtocolError(f"emScon: packet {type(p).__name__} says {size} bytes, its layout has {expected}")
    return p


class PacketSocket:
    """Length-prefixed emScon packets over one TCP connection (client or server side)."""

    def __init__(self, sock: socket.socket, where: str, *, answers: bool, poll_s: float = 0.05) -> None:
        self.sock = sock
        self.where = where
        self.answers = answers
        self._buffer = b""
        sock.settimeout(poll_s)

    @classmethod
    def connect(cls, host: str, port: int, timeout_s: float) -> "PacketSocket":
        where = f"{host}:{port}"
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise DeviceDisconnected(f"tracker {where}: cannot connect: {exc}") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return cls(sock, where, answers=True)

    def send(self, p) -> None:
        try:
            self.sock.sendall(p.pack())
        except OSError as exc:
            raise DeviceDisconnected(f"tracker {self.where}: send failed: {exc}") from exc

    def send_bytes(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise DeviceDisconnected(f"tracker {self.where}: send failed: {exc}") from exc

    def _fill(self, need: int, deadline: float | None) -> bool:
        """Read until ``need`` bytes are buffered; False when ``deadline`` passed first."""
        while len(self._buffer) < need:
            if deadline is not None and time.monotonic() >= deadline:
                return False
            try:
                chunk = self.sock.recv(max(4096, need - len(self._buffer)))
            except socket.timeout:
                continue
            except OSError as exc:
                raise DeviceDisconnected(f"tracker {self.where}: receive failed: {exc}") from exc
            if not chunk:
                raise DeviceDisconnected(f"tracker {self.where}: connection closed by the tracker")
            self._buffer += chunk
        return True

    def receive(self, timeout_s: float | None) -> object | None:
        """The next whole packet, decoded; None when none came within ``timeout_s``.

        A size field outside 8..MAX_PACKET_BYTES or bytes CESAPI cannot decode
        raise ProtocolError (the byte stream cannot be trusted after that:
        the owner reconnects)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        if not self._fill(HEADER.size, deadline):
            return None
        size, _ = HEADER.unpack_from(self._buffer)
        if not HEADER.size <= size <= MAX_PACKET_BYTES:
            self._buffer = b""
            raise ProtocolError(f"emScon: packet size field {size} is outside {HEADER.size}..{MAX_PACKET_BYTES}")
        if not self._fill(size, deadline):
            return None
        data, self._buffer = self._buffer[:size], self._buffer[size:]
        return decode(data, answers=self.answers)

    def readable(self) -> bool:
        """Bytes are waiting (buffered or on the socket)."""
        if self._buffer:
            return True
        try:
            ready, _, _ = select.select([self.sock], [], [], 0)
        except (OSError, ValueError):
            return True         # the next receive raises DeviceDisconnected
        return bool(ready)

    def close(self) -> None:
        with contextlib.suppress(OSError):    # the peer may have closed it already
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


def expect_timeout(what: str, timeout_s: float) -> DeviceTimeout:
    return DeviceTimeout(f"tracker: no reply to {what} within {timeout_s:g} s")
