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

import collections
import math
import pathlib
import struct
import threading
import time
from dataclasses import dataclass, field
from importlib import resources

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from elastocal.drivers.base import DeviceInfo, Drive, DriveSample, SharedLinks, Stream
from elastocal.drivers.can_loopback import INTERFACE as CAN_LOOPBACK, open_can_bus
from elastocal.drivers.canframes import worst_frame_bits
from elastocal.drivers.config import DriveConfig
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import DeviceError, DeviceFault, DeviceTimeout, InputError, ProtocolError

#: the largest share of the bus time streams may plan to use
MAX_BUS_LOAD = 0.9
#: SYNC counter overflow (CiA 301 0x1019)
SYNC_OVERFLOW = 240
#: how long after its SYNC a cycle stays open for TPDOs still in the receive queue
CLOSE_DELAY_S = 0.05
#: the SYNC producer never sends two SYNCs closer than this fraction of the period, nor before
#: the last TPDO of the previous cycle has started on the bus (worst-case frame lengths, the
#: drives answering within :data:`REPLY_MARGIN_S`): a frame on the bus finishes before the SYNC
MIN_INTERVAL = 0.85
#: how soon after a SYNC the drives start answering, at most (for the spacing of SYNCs)
REPLY_MARGIN_S = 100e-6

STATUS_OBJECT = 0x6041
POSITION_OBJECT = 0x6064
VELOCITY_OBJECT = 0x606C
TORQUE_OBJECT = 0x6077
CURRENT_OBJECT = 0x6078


def state_name(statusword: int) -> str:
    """The CiA 402 state a statusword shows."""
    sw = statusword
    if sw & 0x4F == 0x08:
        return "fault"
    if sw & 0x4F == 0x0F:
        return "fault reaction active"
    if sw & 0x4F == 0x00:
        return "not ready to switch on"
    if sw & 0x4F == 0x40:
        return "switch on disabled"
    if sw & 0x6F == 0x21:
        return "ready to switch on"
    if sw & 0x6F == 0x23:
        return "switched on"
    if sw & 0x6F == 0x27:
        return "operation enabled"
    if sw & 0x6F == 0x07:
        return "quick stop active"
    return f"unknown (statusword 0x{sw:04X})"


def default_eds() -> pathlib.Path:
    return pathlib.Path(str(resources.files("elastocal.sims") / "elastocal_drive.eds"))


# ---------------------------------------------------------------- the link
@dataclass
class _Cycle:
    index: int
    counter: int
    t_ns: int
    wall_s: float
    sent: bool = True                              # False: the producer was too late to send it
    replies: dict = field(default_factory=dict)   # (node, cob_id) -> values dict or str (malformed)


@dataclass(frozen=True)
class SyncStats:
    """How punctually the SYNC producer of a link sent its SYNCs (since streaming started).

    ``lateness`` is the time a SYNC went out after its nominal instant on the
    ``start + k / rate`` schedule; a SYNC more than a period late is not sent
    (``not_sent``; its cycle is a gap of every streaming drive)."""

    rate_hz: float
    sent: int
    not_sent: int
    late: int                  # sent more than a tenth of a period after the nominal instant
    max_lateness_s: float      # of the SYNCs sent
    mean_lateness_s: float


class _Member:
    """A streaming drive on a link."""

    def __init__(self, drive: "CanopenDrive", cob_ids: tuple[int, ...], frame_bytes: tuple[int, ...],
                 stream: Stream, first_cycle: int) -> None:
        self.drive = drive
        self.node_id = drive.node_id
        self.cob_ids = cob_ids
        self.frame_bytes = frame_bytes
        self.stream = stream
        self.first_cycle = first_cycle
        self.last_good_ns = time.monotonic_ns()
        self.last_cycle = 2**62       # the last cycle it is streamed in (set when it leaves)
        self.settled = first_cycle    # the last cycle delivered or recorded missing
        self.pending = 0
        self.pending_reason = ""

    def flush_gap(self, end_ns: int) -> None:
        if self.pending:
            self.stream.gap(self.pending, self.pending_reason, start_ns=self.last_good_ns, end_ns=end_ns)
            self.pending = 0

    def missed(self, t_ns: int, reason: str) -> bool:
        """Record a missing cycle; False when the silence has lasted past the timeout."""
        if self.pending and self.pending_reason != reason:
            self.flush_gap(t_ns)
        self.pending += 1
        self.pending_reason = reason
        if (t_ns - self.last_good_ns) / 1e9 > self.drive.timeout_s:
            self.flush_gap(t_ns)
            self.stream.fail(DeviceTimeout(
                f"{self.drive.name} (node {self.node_id}): no valid TPDO for {self.drive.timeout_s:g} s"))
            return False
        return True


class CanopenLink:
    """One CAN channel: bus, canopen Network, SYNC producer and cycle bookkeeping."""

    def __init__(self, url: DeviceUrl) -> None:
        self.interface = url.can_interface
        self.channel = url.can_channel
        self.bitrate = url.int_param("bitrate", 1_000_000, low=10_000, high=1_000_000)
        kwargs: dict = {}
        if self.interface in ("udp_multicast", CAN_LOOPBACK) and url.param("port") is not None:
            kwargs["port"] = url.int_param("port", 43113, low=1, high=65535)
        try:
            bus = open_can_bus(self.interface, self.channel, **kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise DeviceError(f"cannot open CAN {self.interface}/{self.channel}: {exc}") from exc
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.1     # so that closing does not wait a second
        self.network.connect()
        self._lock = threading.Lock()            # cycles, TPDOs, membership
        self._settle_lock = threading.Lock()     # delivering closed cycles (never held with _lock waiting)
        self._members: dict[int, _Member] = {}
        self._cycles: collections.deque[_Cycle] = collections.deque()
        self._cycle_index = 0
        self._counter = 0
        self._rate_hz: float | None = None
        self._thread: threading.Thread | None = None
        self._settler: threading.Thread | None = None
        self._stop = threading.Event()
        self._cycle_s = 0.0       # worst-case bus time from a SYNC to the start of its last TPDO
        self._sync_counts = [0, 0, 0, 0, 0]     # sent, not sent, late, max and sum of lateness [ns]

    # ------------------------------------------------------------- budget
    def _bits_per_cycle(self, frame_bytes: list[int]) -> int:
        return worst_frame_bits(1) + sum(worst_frame_bits(n) for n in frame_bytes)

    def check_budget(self, extra_frames: tuple[int, ...], rate_hz: float) -> float:
        """Planned bus load with ``extra_frames`` added; InputError above :data:`MAX_BUS_LOAD`."""
        with self._lock:
            frames = [n for m in self._members.values() for n in m.frame_bytes] + list(extra_frames)
            nodes = len(self._members) + 1
        bits = self._bits_per_cycle(frames)
        load = bits * rate_hz / self.bitrate
        if load > MAX_BUS_LOAD:
            max_rate = MAX_BUS_LOAD * self.bitrate / bits
            raise InputError(
                f"CAN {self.interface}/{self.channel}: {nodes} drive(s) with {len(frames)} TPDO(s) per SYNC at "
                f"{rate_hz:g} Hz need {bits * rate_hz / 1e6:.2f} Mbit/s, {load:.0%} of the "
                f"{self.bitrate / 1e6:g} Mbit/s bus (limit {MAX_BUS_LOAD:.0%}); at most {max_rate:.0f} Hz")
        return load

    # ------------------------------------------------------------ members
    def join(self, member_factory, frame_bytes: tuple[int, ...], rate_hz: float) -> _Member:
        self.check_budget(frame_bytes, rate_hz)
        producer, settler = self._thread, self._settler
        if producer is not None and not producer.is_alive() and settler is not None:
            settler.join(timeout=5.0)          # the previous streams' last cycles are delivered
        with self._lock:
            if self._rate_hz is not None and self._members and abs(self._rate_hz - rate_hz) > 1e-9:
                raise InputError(f"CAN {self.interface}/{self.channel}: drives on one bus stream at one SYNC "
                                 f"rate; {self._rate_hz:g} Hz is running, {rate_hz:g} Hz was asked")
            member = member_factory(self._cycle_index)
            if member.node_id in self._members:
                raise InputError(f"node {member.node_id} is already streaming")
            self._members[member.node_id] = member
            self._update_cycle_time()
            self._rate_hz = rate_hz
            start = self._thread is None or not self._thread.is_alive()
            if start:
                self._stop.clear()
                self._sync_counts = [0, 0, 0, 0, 0]
                self._thread = threading.Thread(target=self._sync_loop, args=(rate_hz,),
                                                name=f"canopen-sync-{self.channel}", daemon=True)
                self._settler = threading.Thread(target=self._settle_loop, args=(self._thread,),
                                                 name=f"canopen-cycles-{self.channel}", daemon=True)
        if start:
            self._thread.start()
            self._settler.start()
        return member

    def leave(self, node_id: int, *, settle: bool = True) -> None:
        """Stop streaming ``node_id``; with ``settle``, first deliver the cycles
        that were still open (waiting :data:`CLOSE_DELAY_S` for their TPDOs)."""
        with self._lock:
            member = self._members.get(node_id)
            if member is None:
                return
            member.last_cycle = self._cycle_index      # no SYNC after this one is expected of it
        if settle and threading.current_thread() not in (self._thread, self._settler):
            time.sleep(CLOSE_DELAY_S)
        with self._settle_lock:
            if settle:
                with self._lock:
                    still_open = list(self._cycles)
                for cycle in still_open:
                    if self._members.get(node_id) is member:
                        self._settle(member, cycle)
            with self._lock:
                self._members.pop(node_id, None)
                self._update_cycle_time()
                last = not self._members
        member.flush_gap(time.monotonic_ns())
        if last:
            self._stop_threads()

    def _stop_threads(self) -> None:
        self._stop.set()
        for thread in (self._thread, self._settler):
            if thread is not None and thread is not threading.current_thread():
                thread.join(timeout=5.0)

    def members(self) -> int:
        with self._lock:
            return len(self._members)

    def _update_cycle_time(self) -> None:
        """(with the lock held) the worst-case bus time from a SYNC to the start of its last TPDO."""
        frames = [n for m in self._members.values() for n in m.frame_bytes]
        last = max((worst_frame_bits(n) for n in frames), default=0)
        self._cycle_s = (self._bits_per_cycle(frames) - last) / self.bitrate

    def sync_stats(self) -> SyncStats:
        """Punctuality of the SYNCs of the current (or last) streams on this link."""
        with self._lock:
            sent, not_sent, late, max_ns, sum_ns = self._sync_counts
            rate = self._rate_hz or 0.0
        return SyncStats(rate, sent, not_sent, late, max_ns / 1e9, sum_ns / 1e9 / sent if sent else 0.0)

    # -------------------------------------------------------------- TPDOs
    def on_tpdo(self, node_id: int, cob_id: int, values: dict | str, timestamp: float) -> None:
        """Record a TPDO in the cycle whose SYNC preceded it on the bus."""
        with self._lock:
            for cycle in reversed(self._cycles):
                if cycle.sent and cycle.wall_s <= timestamp:
                    cycle.replies[(node_id, cob_id)] = values    # a second one in the cycle replaces the first
                    return
            # older than every open cycle: its cycle was already closed and recorded as a gap

    def _settle(self, member: _Member, cycle: _Cycle) -> None:
        """Deliver ``member``'s sample of a closed cycle, or record it missing."""
        if cycle.index <= member.first_cycle or cycle.index > member.last_cycle or cycle.index <= member.settled:
            return
        member.settled = cycle.index
        replies = [cycle.replies.get((member.node_id, cob)) for cob in member.cob_ids]
        if not cycle.sent:
            ok = member.missed(cycle.t_ns, "SYNC not sent (producer late)")
        elif any(r is None for r in replies):
            ok = member.missed(cycle.t_ns, "no TPDO in the SYNC cycle")
        elif any(isinstance(r, str) for r in replies):
            ok = member.missed(cycle.t_ns, next(r for r in replies if isinstance(r, str)))
        else:
            values: dict = {}
            for r in replies:
                values.update(r)
            ok = member.drive.deliver(member, cycle.t_ns, values)
        if not ok:
            self._members.pop(member.node_id, None)

    def _close_cycle(self, cycle: _Cycle) -> None:
        for member in list(self._members.values()):
            self._settle(member, cycle)

    def _sync_loop(self, rate_hz: float) -> None:
        """Send SYNC ``k`` at ``start + k / rate``: absolute deadlines on
        ``time.monotonic_ns``, the thread sleeps to the next one and wakes up
        early by its running estimate of the wake-up latency. A SYNC more than
        a period late is not sent (its cycle is recorded as missing for every
        member); the lateness of the others is counted (:meth:`sync_stats`).
        Two SYNCs are never closer than ``MIN_INTERVAL`` periods nor than the
        worst-case bus time up to the start of a cycle's last TPDO plus
        ``REPLY_MARGIN_S``, so that the TPDOs of a late cycle still fall in its
        window: after a late SYNC the next goes out exactly when that spacing
        allows (the thread wakes early and busy-waits the rest, at most the
        wake-up latency, instead of sleeping again), so the producer catches up with its
        schedule instead of drifting behind by the wake-up latency every cycle.
        This thread only sends: :meth:`_settle_loop` delivers the cycles."""
        period_ns = int(round(1e9 / rate_hz))
        tenth_ns = period_ns // 10
        next_ns = time.monotonic_ns()          # the nominal schedule
        last_sent = next_ns - period_ns
        oversleep_ns = 0.0                     # running estimate of how late time.sleep wakes up
        counts = self._sync_counts
        while not self._stop.is_set():
            gap_ns = min(period_ns, max(int(MIN_INTERVAL * period_ns), int((self._cycle_s + REPLY_MARGIN_S) * 1e9)))
            earliest = last_sent + gap_ns
            wake = max(next_ns, earliest) - oversleep_ns      # early by the usual wake-up latency
            now = time.monotonic_ns()
            if now < wake:
                time.sleep((wake - now) / 1e9)
                woke = time.monotonic_ns()
                oversleep_ns += 0.1 * ((woke - wake) - oversleep_ns)
                oversleep_ns = min(max(oversleep_ns, 0.0), 0.2 * period_ns)
                continue
            while now < earliest:              # woke before the spacing allows: at most the wake-up latency
                now = time.monotonic_ns()
            late = max(0, (now - next_ns) // period_ns)
            with self._lock:
                if not self._members:
                    break
                for k in range(late):          # the producer fell behind: these SYNCs are never sent
                    self._cycle_index += 1
                    self._cycles.append(_Cycle(self._cycle_index, 0, next_ns + k * period_ns, 0.0, sent=False))
                self._cycle_index += 1
                self._counter = self._counter % SYNC_OVERFLOW + 1
                t_ns = time.monotonic_ns()
                self._cycles.append(_Cycle(self._cycle_index, self._counter, t_ns, time.time()))
                counter = self._counter
                lateness_ns = max(0, t_ns - (next_ns + late * period_ns))
                counts[0] += 1
                counts[1] += late
                counts[2] += lateness_ns > tenth_ns
                counts[3] = max(counts[3], lateness_ns)
                counts[4] += lateness_ns
            try:
                self.network.sync.transmit(counter)
            except (can.CanError, RuntimeError) as exc:
                with self._lock:
                    for m in list(self._members.values()):
                        m.stream.fail(DeviceError(f"CAN {self.interface}/{self.channel}: cannot send SYNC: {exc}"))
                    self._members.clear()
                break
            last_sent = t_ns
            next_ns += period_ns * (late + 1)

    def _settle_loop(self, producer: threading.Thread) -> None:
        """Close the cycles whose SYNC is :data:`CLOSE_DELAY_S` old, in order."""
        delay_ns = int(CLOSE_DELAY_S * 1e9)
        while True:
            done = not producer.is_alive()
            if done:
                time.sleep(CLOSE_DELAY_S)      # the last windows close, then everything is delivered
            with self._lock:
                now = time.monotonic_ns()
                due = []
                while self._cycles and (done or now - self._cycles[0].t_ns >= delay_ns):
                    due.append(self._cycles.popleft())
            if due:
                with self._settle_lock:
                    for cycle in due:
                        self._close_cycle(cycle)
            if done:
                return
            time.sleep(0.01)

    def close(self) -> None:
        with self._lock:
            members = list(self._members)
        for node_id in members:
            self.leave(node_id)
        self._stop_threads()
        self.network.disconnect()


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


# --------------------------------------------------------------- the drive
class CanopenDrive(Drive):
    """A CiA 402 drive on a CANopen network (see the module docstring)."""

    def __init__(self, config: DriveConfig, *, links: SharedLinks | None = None) -> None:
        url = config.url
        super().__init__(url, joint=config.joint, timeout_s=config.timeout_s, retries=config.retries,
                         max_current_a=config.max_current_a, max_rate_hz=1000.0)
        self.node_id = url.int_param("node", 1, low=1, high=127)
        eds = url.param("eds")
        self._eds = pathlib.Path(eds) if eds else default_eds()
        if not self._eds.exists():
            raise InputError(f"{self.name}: EDS file {self._eds} not found", source=url.text)
        self._own_links = links is None
        self._links = SharedLinks() if links is None else links
        self._link_key = ("canopen", url.can_interface, url.can_channel)
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
            if "No SDO response" in str(exc):
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
        if statusword & 0x6F == 0x27:               # operation enabled
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
        indices = tuple(index for index, _, _, _ in layout)
        whole = _frame_struct(layout, nbytes)

        if whole is not None:               # one struct for the frame, from the objects' own types
            unpack = whole.unpack

            def on_pdo(pdo_map) -> None:
                data = pdo_map.data
                if len(data) != nbytes:
                    link.on_tpdo(node_id, cob_id, f"malformed TPDO 0x{cob_id:03X} ({len(data)} of "
                                                  f"{nbytes} bytes)", pdo_map.timestamp)
                    return
                link.on_tpdo(node_id, cob_id, dict(zip(indices, unpack(data))), pdo_map.timestamp)

            return on_pdo

        def on_pdo(pdo_map) -> None:        # objects without a fixed struct layout: the OD decodes
            data = bytes(pdo_map.data)
            if len(data) != nbytes:
                link.on_tpdo(node_id, cob_id, f"malformed TPDO 0x{cob_id:03X} ({len(data)} of "
                                              f"{nbytes} bytes)", pdo_map.timestamp)
                return
            link.on_tpdo(node_id, cob_id, {index: od.decode_raw(data[a:a + n]) for index, od, a, n in layout},
                         pdo_map.timestamp)

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
