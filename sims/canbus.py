"""A CAN bus with the timing of a real one, for the simulated drives.

python-can's ``virtual`` and ``udp_multicast`` (``udp_loopback``) interfaces deliver frames
instantly and without limit. :class:`SimCanBus` wraps one of them on the
device side and adds what a 1 Mbit/s bus imposes:

* every frame occupies the bus for its exact length in bits (CRC-15 and bit
  stuffing computed per frame, :func:`~elastocal.drivers.canframes.frame_bits`)
  on a bus timeline: frames the simulated nodes send queue behind each other
  and behind the frames other nodes send, so the bus carries at most ≈8,500
  eight-byte frames per second;
* each node answers a node-specific reply delay after the frame that
  triggered the reply ended on the bus (SDO replies, TPDOs after SYNC);
  frames a node sends of its own accord (EMCY, heartbeat) go on the bus
  when they are sent;
* a frame's place on the timeline is fixed when the node sends it, and the
  frame carries that bus time as timestamp (the inner ``virtual`` bus must
  preserve timestamps), so Python's scheduling delays do not move a frame
  on the timeline seen by the drivers;
* frames reach the other nodes in bus order and never before they ended on
  the bus, in batches as from a USB CAN adapter: whenever a frame from the
  other side arrives (the next SYNC hands over the TPDOs of the cycle before),
  else ``delivery_interval_s`` (5 ms) after a TPDO ended (other frames: when
  they ended) — a thread wake-up per batch, not per frame. The frames keep
  their bus time as timestamp on the virtual bus, so batching does not
  change what the drivers see. Over UDP (``udp_loopback``) frames are stamped with their
  arrival instead, so across processes ``delivery_interval_s=0`` hands each
  burst of TPDOs over as soon as its last frame ended on the bus, as a real
  bus delivers them: before the next SYNC;
* a SYNC wins arbitration: a TPDO that has not started on the bus when the
  next SYNC comes is discarded (the CiA 301 synchronous window), and a full
  transmit queue drops frames (overrun); both are counted, so a lossy bus
  shows up as gaps on the driver side, never as late data with a wrong time;
* with ``filter_own=True`` (UDP multicast loops our own frames back) the echo
  of every frame we sent is dropped.

:meth:`SimCanBus.stats` reports frames, bits and the bus load.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Callable

import can

from elastocal.drivers.canframes import message_bits

SYNC_COB_ID = 0x80
#: function codes (COB-ID >> 7) of the four TPDOs
TPDO_FUNCTIONS = (0x3, 0x5, 0x7, 0x9)
#: function codes of frames a node sends of its own accord (EMCY, heartbeat), not as a reply
UNSOLICITED_FUNCTIONS = (0x1, 0xE)


@dataclass(frozen=True)
class BusStats:
    frames: int            # frames on the bus (sent by the simulated nodes and by others)
    bits: int
    elapsed_s: float
    bitrate: int
    sent: int              # frames the simulated nodes sent
    dropped_window: int    # TPDOs discarded because the next SYNC came first
    dropped_overrun: int   # frames dropped because the transmit queue was full

    @property
    def load(self) -> float:
        """Fraction of the bus time used."""
        return self.bits / (self.bitrate * self.elapsed_s) if self.elapsed_s > 0 else 0.0

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else 0.0


class SimCanBus(can.BusABC):
    """Device-side bus with frame timing (see the module docstring).

    ``reply_delay_s(node_id)`` gives each node's reply delay; ``inner`` is the
    python-can bus that carries the frames (virtual or udp_loopback).
    """

    #: how long after it ended a TPDO waits, at most, for the next SYNC to hand it over with its cycle
    DELIVERY_INTERVAL_S = 5e-3

    def __init__(self, inner: can.BusABC, *, bitrate: int = 1_000_000,
                 reply_delay_s: Callable[[int], float] = lambda node: 0.0,
                 tx_queue: int = 256, filter_own: bool = False,
                 delivery_interval_s: float = DELIVERY_INTERVAL_S) -> None:
        self._inner = inner
        self.bitrate = int(bitrate)
        self._reply_delay = reply_delay_s
        self._tx_queue = int(tx_queue)
        self._filter_own = filter_own
        self._interval = float(delivery_interval_s)
        self.channel_info = f"simulated {bitrate // 1000} kbit/s bus on {inner.channel_info}"
        self._cond = threading.Condition()
        self._pending: collections.deque = collections.deque()   # (end, msg, is_tpdo, start, bits), bus order
        self._handing_over = threading.Lock()   # one batch at a time, so frames arrive in bus order
        self._bus_free_s = 0.0
        self._last_rx_end = 0.0
        self._wall_offset = time.time() - time.monotonic()
        self._delivered_end = 0.0
        self._own: collections.Counter = collections.Counter()
        self._frames = 0
        self._bits = 0
        self._sent = 0
        self._dropped_window = 0
        self._dropped_overrun = 0
        self._t0 = time.monotonic()
        self._stop = False
        super().__init__(channel=inner.channel_info)
        self._thread = threading.Thread(target=self._transmit_loop, name="sim-can-tx", daemon=True)
        self._thread.start()

    # -------------------------------------------------------------- stats
    def stats(self) -> BusStats:
        with self._cond:
            return BusStats(self._frames, self._bits, time.monotonic() - self._t0, self.bitrate, self._sent,
                            self._dropped_window, self._dropped_overrun)

    def reset_stats(self) -> None:
        with self._cond:
            self._frames = self._bits = self._sent = self._dropped_window = self._dropped_overrun = 0
            self._t0 = time.monotonic()

    # -------------------------------------------------------------- send
    @staticmethod
    def _node_of(can_id: int) -> int:
        return can_id & 0x7F

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Put ``msg`` on the bus timeline now; it reaches the other nodes after it ended."""
        is_tpdo = not msg.is_extended_id and msg.arbitration_id >> 7 in TPDO_FUNCTIONS
        bits = message_bits(msg)
        with self._cond:
            if len(self._pending) >= self._tx_queue:
                self._dropped_overrun += 1
                return
            # a reply is due a node's delay after the frame that triggered it ended on the bus
            due = self._last_rx_end + self._reply_delay(self._node_of(msg.arbitration_id))
            if not msg.is_extended_id and msg.arbitration_id >> 7 in UNSOLICITED_FUNCTIONS:
                due = max(due, time.monotonic())
            start = self._occupy(due, bits)
            msg.timestamp = start + self._wall_offset
            msg.data = bytes(msg.data)   # immutable: the inner bus's per-receiver deepcopy shares it
            self._pending.append((self._bus_free_s, msg, is_tpdo, start, bits))
            if len(self._pending) == 1:
                self._cond.notify()

    def _occupy(self, start_s: float, bits: int) -> float:
        start = max(start_s, self._bus_free_s)
        self._bus_free_s = start + bits / self.bitrate
        self._frames += 1
        self._bits += bits
        return start

    def _take_ended(self, now: float) -> list:
        """Pending frames that have ended on the bus by ``now`` (call with the lock held)."""
        batch = []
        pending = self._pending
        while pending and pending[0][0] <= now:
            end, msg, _, _, _ = pending.popleft()
            self._delivered_end = end
            self._sent += 1
            if self._filter_own:
                self._own[(msg.arbitration_id, bytes(msg.data))] += 1
            batch.append(msg)
        return batch

    def _hand_over(self) -> None:
        """Send the frames that have ended on the bus to the other nodes."""
        with self._handing_over:
            with self._cond:
                batch = self._take_ended(time.monotonic())
            for msg in batch:
                try:
                    self._inner.send(msg)
                except can.CanError:
                    with self._cond:
                        self._dropped_overrun += 1

    def _transmit_loop(self) -> None:
        """Hand over the frames no receive did: a TPDO ``delivery_interval_s`` after it
        ended, other frames when they ended."""
        while True:
            with self._cond:
                while not self._stop and not self._pending:
                    self._cond.wait()
                if self._stop:
                    return
                end, _, is_tpdo, _, _ = self._pending[0]
                now = time.monotonic()
                if not is_tpdo:
                    at = end
                elif self._interval > 0.0:
                    at = end + self._interval
                else:                          # the whole burst as soon as its last frame ended
                    at = self._pending[-1][0]
                if at > now:
                    self._cond.wait(at - now)
                    continue
            self._hand_over()

    # ----------------------------------------------------------- receive
    def _recv_internal(self, timeout: float | None):
        msg = self._inner.recv(timeout)
        if msg is None:
            return None, False
        with self._cond:
            if self._filter_own:
                key = (msg.arbitration_id, bytes(msg.data))
                if self._own.get(key):
                    self._own[key] -= 1
                    if not self._own[key]:
                        del self._own[key]
                    return None, False
            now = time.monotonic()
            on_bus = min(msg.timestamp - self._wall_offset, now)
            if msg.arbitration_id == SYNC_COB_ID and not msg.is_extended_id:
                self._close_window(on_bus)
            self._occupy(on_bus, message_bits(msg))
            self._last_rx_end = self._bus_free_s
            ended = bool(self._pending) and self._pending[0][0] <= now
        if ended:
            self._hand_over()
        return msg, False

    def _close_window(self, sync_s: float) -> None:
        """A SYNC wants the bus at ``sync_s``: the TPDOs queued behind that
        instant lose arbitration and fall outside their SYNC window (dropped);
        the frame on the bus at that instant finishes first."""
        late = [e for e in self._pending if e[2] and e[3] >= sync_s]
        if not late:
            return
        for *_, bits in late:
            self._dropped_window += 1
            self._frames -= 1
            self._bits -= bits
        self._pending = collections.deque(e for e in self._pending if not (e[2] and e[3] >= sync_s))
        self._bus_free_s = max([e[0] for e in self._pending] + [self._delivered_end, self._last_rx_end])

    def shutdown(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        try:
            self._inner.shutdown()
        finally:
            super().shutdown()
