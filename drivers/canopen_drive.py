"""CiA 402 drives over CANopen (``canopen://INTERFACE/CHANNEL?node=N``).

The ``canopen`` library on python-can does the protocol: SDO for on-demand
reads and identification, TPDOs (as configured on the drive, read by SDO at
open) for streaming, EMCY for faults. This module adds what a measurement
needs:

* :class:`CanopenLink`: one python-can bus and ``canopen.Network`` per
  channel, shared by the drives on it, and the SYNC producer. Streams of all
  drives on a channel run on one SYNC; the bus budget (exact worst-case frame
  lengths, :mod:`elastocal.drivers.canframes`) is checked before a stream
  starts. The producer keeps an absolute schedule; a SYNC more than a period
  late is not sent (a gap of every drive), and the lateness of the others is
  counted (:meth:`CanopenLink.sync_stats`).
* Cycle attribution: a TPDO belongs to the SYNC cycle in which it was on the
  bus (the CiA 301 synchronous window, closed by the next SYNC), judged by the
  frame's bus timestamp against the wall-clock time each SYNC was sent, so
  the driver's own processing delays do not move a TPDO into the wrong cycle.
  A cycle is closed ``CLOSE_DELAY_S`` after its SYNC; if a drive sent two
  TPDOs with one COB-ID in a cycle the later one counts. Samples are stamped
  with the ``time.monotonic_ns()`` at which their SYNC was sent: the instant
  the drive latched them. A cycle without the TPDO(s) of a drive is a
  recorded :class:`~elastocal.drivers.base.Gap`; silence longer than
  ``timeout_s`` ends the stream with :class:`DeviceTimeout`.
* States: a statusword in Fault or not in "operation enabled", or an EMCY,
  ends the stream (or an on-demand read) with :class:`DeviceFault`; the
  values in that TPDO are never delivered as data.

URL parameters: ``node`` (1..127), ``bitrate`` (budget, default 1000000),
``eds`` (the drive's EDS file; default: the generic CiA 402 objects of the
packaged ``elastocal_drive.eds``), ``port`` (the UDP port of ``udp_loopback`` and
``udp_multicast``).
"""

from __future__ import annotations

import math
import pathlib
import queue
import struct
import time
from importlib import resources

from canopen.profiles.p402 import State402
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from elastocal.drivers.base import Drive, SharedLinks
from elastocal.drivers.samples import DeviceInfo, DriveSample, Stream
from elastocal.drivers.canopen_link import CanopenLink, _Member
from elastocal.drivers.config import DriveConfig
from elastocal.errors import DeviceError, DeviceFault, DeviceTimeout, InputError, ProtocolError

STATUS_OBJECT = 0x6041
POSITION_OBJECT = 0x6064
VELOCITY_OBJECT = 0x606C
TORQUE_OBJECT = 0x6077
CURRENT_OBJECT = 0x6078

#: CiA 402 "operation enabled", from canopen's statusword table
_ENABLED_MASK, _ENABLED_BITS = State402.SW_MASK["OPERATION ENABLED"]


def state_name(statusword: int) -> str:
    """The CiA 402 state a statusword shows, by canopen's own table (``State402.SW_MASK``)."""
    for name, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return name.lower()
    return f"unknown (statusword 0x{statusword:04X})"


def default_eds() -> pathlib.Path:
    return pathlib.Path(str(resources.files("elastocal.sims") / "elastocal_drive.eds"))


def _frame_struct(layout, nbytes: int) -> struct.Struct | None:
    """One little-endian ``struct`` decoding a whole TPDO of ``nbytes`` mapped as
    ``layout`` ((index, od variable, byte offset, byte length), in mapping order),
    built from the objects' own ``ODVariable.STRUCT_TYPES``; None when an object
    has no plain struct type or the mapping has overlaps."""
    fmt, at = "<", 0
    for _, od, offset, length in layout:
        st = od.STRUCT_TYPES.get(od.data_type)
        if not isinstance(st, struct.Struct) or st.size != length or offset < at:
            return None
        code = st.format.lstrip("<>=!@")
        if len(code) != 1:
            return None
        fmt += "x" * (offset - at) + code
        at = offset + length
    fmt += "x" * (nbytes - at)
    return struct.Struct(fmt) if at <= nbytes else None


def tpdo_decoder(layout, nbytes: int):
    """The one decoder of a TPDO of ``nbytes`` mapped as ``layout``: a function from
    the frame's bytes to {object index: value}. One ``struct`` for the whole frame
    when every object has a plain type (:func:`_frame_struct`), else each object
    decoded by its own ``ODVariable.decode_raw``."""
    indices = tuple(index for index, _, _, _ in layout)
    whole = _frame_struct(layout, nbytes)
    if whole is not None:
        unpack = whole.unpack
        return lambda data: dict(zip(indices, unpack(data)))
    return lambda data: {index: od.decode_raw(bytes(data[a:a + n])) for index, od, a, n in layout}


# --------------------------------------------------------------- the drive
class CanopenDrive(Drive):
    """A CiA 402 drive on a CANopen network (see the module docstring)."""

    def __init__(self, config: DriveConfig, *, links: SharedLinks | None = None) -> None:
        url = config.url
        super().__init__(url, joint=config.joint, timeout_s=config.timeout_s, retries=config.retries,
                         max_current_a=config.max_current_a, max_rate_hz=1000.0)
        settings = url.settings               # parsed once with the URL (drivers.url_params.CanopenParams)
        self.node_id = settings.node
        self._eds = pathlib.Path(settings.eds) if settings.eds else default_eds()
        if not self._eds.exists():
            raise InputError(f"{self.name}: EDS file {self._eds} not found", source=url.text)
        self._own_links = links is None
        self._links = SharedLinks() if links is None else links
        self._link_key = ("canopen", settings.interface, settings.channel)
        self.link: CanopenLink = self._links.acquire(self._link_key, lambda: CanopenLink(url), CanopenLink.close)
        self._streaming = False
        self._emcy: list = []
        try:
            self.node = self.link.network.add_node(self.node_id, str(self._eds))
            self.node.sdo.RESPONSE_TIMEOUT = self.timeout_s
            self.node.sdo.MAX_RETRIES = 1     # one attempt; the base class retries
            self.node.emcy.add_callback(self._on_emcy)
            self._read_factors()
        except BaseException:
            self._release()
            raise

    def _release(self) -> None:
        try:
            if self.node_id in self.link.network:
                del self.link.network[self.node_id]
        except KeyError:
            pass
        if self._own_links:
            self._links.close()
        else:
            self._links.release(self._link_key)

    # ---------------------------------------------------------------- SDO
    def _sdo(self, index: int, subindex: int | None = None):
        try:
            var = self.node.sdo[index] if subindex is None else self.node.sdo[index][subindex]
            return var.raw
        except SdoCommunicationError as exc:
            where = f"0x{index:04X}" + (f":{subindex}" if subindex is not None else "")
            # canopen raises it from the empty response queue when no reply came in time
            if isinstance(exc.__context__, queue.Empty):
                raise DeviceTimeout(f"{self.name} (node {self.node_id}): no SDO reply reading {where} "
                                    f"within {self.timeout_s:g} s") from exc
            raise ProtocolError(f"{self.name} (node {self.node_id}): bad SDO reply reading {where}: {exc}") from exc
        except SdoAbortedError as exc:
            raise DeviceError(f"{self.name} (node {self.node_id}): SDO abort reading 0x{index:04X}: {exc}") from exc
        except KeyError as exc:
            raise InputError(f"{self.name}: object 0x{index:04X} is not in the EDS {self._eds}") from exc

    def _read_factors(self) -> None:
        def get():
            device_type = self._sdo(0x1000)
            if device_type & 0xFFFF != 402:
                raise ProtocolError(f"{self.name}: node {self.node_id} is not a CiA 402 drive "
                                    f"(device type 0x{device_type:08X})")
            rated_ma = self._sdo(0x6075)
            rated_mnm = self._sdo(0x6076)
            increments = self._sdo(0x608F, 1)
            motor_revs = self._sdo(0x608F, 2)
            gear_motor = self._sdo(0x6091, 1)
            gear_shaft = self._sdo(0x6091, 2)
            return rated_ma, rated_mnm, increments, motor_revs, gear_motor, gear_shaft

        rated_ma, rated_mnm, increments, motor_revs, gear_motor, gear_shaft = self._call("open", get)
        for name, v in (("rated current 0x6075", rated_ma), ("rated torque 0x6076", rated_mnm),
                        ("encoder increments 0x608F:1", increments), ("motor revolutions 0x608F:2", motor_revs),
                        ("gear ratio 0x6091:1", gear_motor), ("gear ratio 0x6091:2", gear_shaft)):
            if v <= 0:
                raise ProtocolError(f"{self.name}: {name} is {v}; it must be > 0")
        self.rated_current_a = rated_ma / 1000.0
        self.rated_torque_nm = rated_mnm / 1000.0
        self.gear_ratio = gear_motor / gear_shaft
        self.counts_per_rad = increments / motor_revs * self.gear_ratio / (2 * math.pi)

    # ------------------------------------------------------------- decode
    def _sample(self, t_ns: int, values: dict) -> DriveSample:
        velocity = values.get(VELOCITY_OBJECT)
        torque = values.get(TORQUE_OBJECT)
        return DriveSample(
            t_ns=t_ns, joint=self.joint,
            position_rad=values[POSITION_OBJECT] / self.counts_per_rad,
            current_a=values[CURRENT_OBJECT] / 1000.0 * self.rated_current_a,
            velocity_rad_s=None if velocity is None else velocity / self.counts_per_rad,
            torque_nm=None if torque is None else torque / 1000.0 * self.rated_torque_nm * self.gear_ratio,
            status=values[STATUS_OBJECT])

    def _state_error(self, statusword: int) -> DeviceFault | None:
        if statusword & _ENABLED_MASK == _ENABLED_BITS:
            return None
        state = state_name(statusword)
        if state == "operation enabled":
            return None
        if state in ("fault", "fault reaction active"):
            try:
                code = self._sdo(0x603F) if not self._streaming else (self._emcy[-1].code if self._emcy else 0)
            except DeviceError:
                code = 0
            return DeviceFault(f"{self.name} (node {self.node_id}) is in {state}, error code 0x{code:04X}")
        return DeviceFault(f"{self.name} (node {self.node_id}) is in '{state}', not 'operation enabled'")

    # --------------------------------------------------------------- API
    def _identify(self) -> DeviceInfo:
        name = self._sdo(0x1008)
        vendor = self._sdo(0x1018, 1)
        product = self._sdo(0x1018, 2)
        revision = self._sdo(0x1018, 3)
        serial = self._sdo(0x1018, 4)
        software = self._sdo(0x100A)
        statusword = self._sdo(STATUS_OBJECT)
        return DeviceInfo(
            kind="drive", url=self.url.text, vendor=f"0x{vendor:08X}", model=f"{name} (0x{product:08X})",
            serial=str(serial), revision=f"0x{revision:08X} sw {software}",
            details=(("joint", str(self.joint)), ("node", str(self.node_id)),
                     ("state", state_name(statusword)),
                     ("rated current", f"{self.rated_current_a:g} A"),
                     ("gear ratio", f"{self.gear_ratio:g}"),
                     ("counts per rad", f"{self.counts_per_rad:.6g}")))

    def _read(self) -> DriveSample:
        sw = self._sdo(STATUS_OBJECT)
        err = self._state_error(sw)
        if err is not None:
            raise err
        t_ns = time.monotonic_ns()
        values = {STATUS_OBJECT: sw}
        for index in (POSITION_OBJECT, VELOCITY_OBJECT, TORQUE_OBJECT, CURRENT_OBJECT):
            values[index] = self._sdo(index)
        return self._sample(t_ns, values)

    def _on_emcy(self, entry) -> None:
        self._emcy.append(entry)
        if entry.code & 0xFF00 == 0:
            return
        member = self._member
        if member is not None:
            member.flush_gap(time.monotonic_ns())
            member.stream.fail(DeviceFault(
                f"{self.name} (node {self.node_id}): EMCY 0x{entry.code:04X} ({entry.get_desc() or 'no description'})"))
            self.link.leave(self.node_id, settle=False)

    _member: _Member | None = None

    def _stream(self, rate_hz: float) -> Stream[DriveSample]:
        if self._member is not None and not self._member.stream.closed:
            raise InputError(f"{self.name} is already streaming")

        def read_pdos():
            self.node.tpdo.read()
            return [p for p in self.node.tpdo.map.values()
                    if p.enabled and p.trans_type is not None and 1 <= p.trans_type <= 240]

        pdos = self._call("read TPDO configuration", self._translate_pdo, read_pdos)
        if any(p.trans_type != 1 for p in pdos):
            raise InputError(f"{self.name}: TPDOs must be sent on every SYNC (transmission type 1) for "
                             f"streaming; node {self.node_id} has {[p.trans_type for p in pdos]}")
        mapped = {v.index for p in pdos for v in p.map}
        for need, what in ((STATUS_OBJECT, "statusword 0x6041"), (POSITION_OBJECT, "position 0x6064"),
                           (CURRENT_OBJECT, "current 0x6078")):
            if need not in mapped:
                raise InputError(f"{self.name}: no synchronous TPDO of node {self.node_id} maps the {what}")
        frame_bytes = tuple(int(math.ceil(p.length / 8)) for p in pdos)
        cob_ids = tuple(p.cob_id for p in pdos)
        stream: Stream[DriveSample] = Stream(self.name, rate_hz, stop=lambda: self._stop_stream())

        for p, nbytes in zip(pdos, frame_bytes):
            p.callbacks.clear()
            p.add_callback(self._make_pdo_callback(p, nbytes))

        def factory(first_cycle: int) -> _Member:
            return _Member(self, cob_ids, frame_bytes, stream, first_cycle)

        self._streaming = True
        self._member = self.link.join(factory, frame_bytes, rate_hz)
        return stream

    @staticmethod
    def _translate_pdo(fn):
        try:
            return fn()
        except SdoCommunicationError as exc:
            raise DeviceTimeout(f"no SDO reply reading the TPDO configuration: {exc}") from exc
        except SdoAbortedError as exc:
            raise DeviceError(f"SDO abort reading the TPDO configuration: {exc}") from exc

    def _make_pdo_callback(self, pdo, nbytes: int):
        node_id = self.node_id
        link = self.link
        cob_id = pdo.cob_id

        layout = [(v.index, v.od, v.offset // 8, v.length // 8) for v in pdo.map if v.length]
        if any(v.offset % 8 or v.length % 8 for v in pdo.map if v.length):
            raise InputError(f"{self.name}: TPDO 0x{cob_id:03X} maps objects that are not byte-aligned")
        decode = tpdo_decoder(layout, nbytes)

        def on_pdo(pdo_map) -> None:
            data = pdo_map.data
            if len(data) != nbytes:
                link.on_tpdo(node_id, cob_id, f"malformed TPDO 0x{cob_id:03X} ({len(data)} of "
                                              f"{nbytes} bytes)", pdo_map.timestamp)
                return
            link.on_tpdo(node_id, cob_id, decode(data), pdo_map.timestamp)

        return on_pdo

    def deliver(self, member: _Member, t_ns: int, values: dict) -> bool:
        """Called by the link for a complete cycle: a sample, or the stream's end."""
        err = self._state_error(values[STATUS_OBJECT])
        if err is None:
            try:
                sample = self.check_sample(self._sample(t_ns, values))
            except ProtocolError as exc:
                err = exc
        if err is not None:
            member.flush_gap(t_ns)
            member.stream.fail(err)
            return False
        member.flush_gap(t_ns)
        member.last_good_ns = t_ns
        member.stream.emit(sample, t_ns)
        return True

    def _stop_stream(self) -> None:
        member, self._member = self._member, None
        self._streaming = False
        if member is not None:
            self.link.leave(self.node_id)
            for p in self.node.tpdo.map.values():
                p.callbacks.clear()

    def _close(self) -> None:
        self._stop_stream()
        self._release()
