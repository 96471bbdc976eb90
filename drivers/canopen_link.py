"""The CANopen link: one python-can bus and ``canopen.Network`` per channel, shared by
the drives on it, and the SYNC producer with cycle attribution (see
:mod:`elastocal.drivers.canopen_drive` for the whole story). The drive itself, its
objects and states, is in :mod:`elastocal.drivers.canopen_drive`."""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import can
import canopen

from elastocal.drivers.samples import Stream
from elastocal.drivers.can_loopback import INTERFACE as CAN_LOOPBACK, open_can_bus
from elastocal.drivers.canframes import worst_frame_bits
from elastocal.drivers.urls import DeviceUrl
from elastocal.errors import DeviceError, DeviceTimeout, InputError

if TYPE_CHECKING:  # the link delivers cycles to its drives
    from elastocal.drivers.canopen_drive import CanopenDrive


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
        settings = url.settings               # drivers.url_params.CanopenParams
        self.interface = settings.interface
        self.channel = settings.channel
        self.bitrate = settings.bitrate
        kwargs: dict = {}
        if self.interface in ("udp_multicast", CAN_LOOPBACK) and settings.port is not None:
            if settings.port == 0:           # a served cell's placeholder, never a bus to open
                raise InputError(f"port=0 is outside 1..65535 in {url.text}", source=url.text)
            kwargs["port"] = settings.port
        try:
            bus = open_can_bus(self.interface, self.channel, **kwargs)
        except InputError as exc:
            raise InputError(exc.detail, source=url.text) from None
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
