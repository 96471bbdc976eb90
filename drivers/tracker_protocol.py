"""The tracker line protocol (docs/tracker-protocol.md), shared by the driver
and the simulated tracker.

Every line is ASCII, ``BODY*HH\\n``: ``HH`` is the XOR of the bytes of
``BODY`` in two upper-case hex digits. A measurement line is::

    M <seq> <t_us> <target> <x> <y> <z> <status>

``seq`` counts measurements (+1 each, single and streamed alike), ``t_us`` is
the tracker's clock [µs], ``x y z`` the target position in the tracker frame
[m] (``nan`` when there is no measurement), ``status`` one of :data:`STATUSES`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from elastocal.errors import ProtocolError

STATUS_OK = "OK"
STATUS_BEAM_BROKEN = "BEAM_BROKEN"
STATUS_NO_TARGET = "NO_TARGET"
STATUSES = (STATUS_OK, STATUS_BEAM_BROKEN, STATUS_NO_TARGET)
MAX_LINE = 256
_LINE = re.compile(rb"^([\x20-\x29\x2b-\x7e]*)\*([0-9A-F]{2})\r?\n?$")
_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,32}$")


def checksum(body: str) -> str:
    value = 0
    for b in body.encode("ascii"):
        value ^= b
    return f"{value:02X}"


def encode_line(body: str) -> bytes:
    """``body`` framed as one protocol line."""
    if "*" in body or "\n" in body or "\r" in body:
        raise ValueError(f"a line body cannot contain '*', CR or LF: {body!r}")
    return f"{body}*{checksum(body)}\n".encode("ascii")


def decode_line(raw: bytes) -> str:
    """The body of one received line; ProtocolError when malformed or its checksum is wrong."""
    if len(raw) > MAX_LINE:
        raise ProtocolError(f"tracker: line of {len(raw)} bytes is too long")
    m = _LINE.match(raw)
    if m is None:
        raise ProtocolError(f"tracker: malformed line {raw[:60]!r}")
    body = m.group(1).decode("ascii")
    if checksum(body) != m.group(2).decode("ascii"):
        raise ProtocolError(f"tracker: checksum mismatch in line {raw[:60]!r}")
    return body


def valid_name(name: str) -> bool:
    return bool(_NAME.match(name))


@dataclass(frozen=True)
class Measurement:
    seq: int
    t_us: int
    target: str
    xyz_m: tuple[float, float, float]
    status: str

    def body(self) -> str:
        coords = " ".join("nan" if not math.isfinite(v) else f"{v:.9f}" for v in self.xyz_m)
        return f"M {self.seq} {self.t_us} {self.target} {coords} {self.status}"


def parse_measurement(body: str) -> Measurement:
    parts = body.split(" ")
    if len(parts) != 8 or parts[0] != "M":
        raise ProtocolError(f"tracker: not a measurement line: {body[:60]!r}")
    try:
        seq = int(parts[1])
        t_us = int(parts[2])
        xyz = (float(parts[4]), float(parts[5]), float(parts[6]))
    except ValueError:
        raise ProtocolError(f"tracker: bad number in measurement line {body[:60]!r}") from None
    status = parts[7]
    if status not in STATUSES:
        raise ProtocolError(f"tracker: unknown status {status!r}")
    if seq < 0 or t_us < 0:
        raise ProtocolError(f"tracker: negative counter in {body[:60]!r}")
    if status == STATUS_OK and not all(math.isfinite(v) for v in xyz):
        raise ProtocolError(f"tracker: status OK without a position in {body[:60]!r}")
    return Measurement(seq, t_us, parts[3], xyz, status)
