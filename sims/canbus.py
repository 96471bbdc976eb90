"""A CAN bus with the timing of a real one, for the simulated drives.

python-can's ``virtual`` and ``udp_multicast`` interfaces deliver frames
instantly and without limit. :class:`SimCanBus` wraps one of them on the
device side and adds what a 1 Mbit/s bus imposes:

* every frame occupies the bus for its exact length in bits (CRC-15 and bit
  stuffing computed per frame, :func:`~elastocal.drivers.canframes.frame_bits`)
  on a bus timeline: frames the simulated nodes send queue behind each other
  and behind the frames other nodes send, so the bus carries at most ≈8,500
  eight-byte frames per second;
* each node answers a node-specific reply delay after the frame that
  triggered the reply ended on the bus (SDO replies, TPDOs after SYNC);
* frames carry their bus time as timestamp (the inner ``virtual`` bus must
  preserve timestamps), so Python's scheduling delays do not move a frame
  on the timeline seen by the drivers;
* a TPDO still queued when the next SYNC arrives is discarded (the CiA 301
  synchronous window), and a full transmit queue drops frames (overrun); both
  are counted, so a lossy bus shows up as gaps on the driver side, never as
  late data with a wrong time;
* with ``filter_own=True`` (udp_multicast loops our own frames back) the echo
  of every frame we sent is dropped.

:meth:`SimCanBus.stats` reports frames, bits and the bus load.
"""

from __future__ import annotations

import collections
import heapq
import itertools
import threading
import time
from dataclasses import dataclass
from typing import Callable

import can

from elastocal.drivers.canframes import message_bits

SYNC_COB_ID = 0x80
#: function codes (COB-ID >> 7) of the four TPDOs
TPDO_FUNCTIONS = (0x3, 0x5, 0x7, 0x9)


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
    python-can bus that carries the frames (virtual or udp_multicast).
    """

    #: frames sent at most this much ahead of their bus time (the scheduler's slack)
    SLACK_S = 200e-6

    def __init__(self, inner: can.BusABC, *, bitrate: int = 1_000_000,
                 reply_delay_s: Callable[[int], float] = lambda node: 0.0,
                 tx_queue: int = 256, filter_own: bool = False) -> None:
        self._inner = inner
        self.bitrate = int(bitrate)
        self._reply_delay = reply_delay_s
        self._tx_queue = int(tx_queue)
        self._filter_own = filter_own
        self.channel_info = f"simulated {bitrate // 1000} kbit/s bus on {inner.channel_info}"
        self._cond = threading.Condition()
        self._heap: list = []
        self._seq = itertools.count()
        self._bus_free_s = 0.0
        self._last_rx_end = 0.0
        self._wall_offset = time.time() - time.monotonic()
        self._sync_seen = 0
        self._sync_times: dict[int, float] = {}
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
        function = msg.arbitration_id >> 7
        is_tpdo = not msg.is_extended_id and function in TPDO_FUNCTIONS
        with self._cond:
            # a reply is due a node's delay after the frame that triggered it ended on the bus
            due = self._last_rx_end + self._reply_delay(self._node_of(msg.arbitration_id))
            if len(self._heap) >= self._tx_queue:
                self._dropped_overrun += 1
                return
            tag = self._sync_seen if is_tpdo else None
            heapq.heappush(self._heap, (due, msg.arbitration_id, next(self._seq), msg, tag))
            self._cond.notify()

    def _occupy(self, start_s: float, bits: int) -> float:
        start = max(start_s, self._bus_free_s)
        self._bus_free_s = start + bits / self.bitrate
        self._frames += 1
        self._bits += bits
        return start

    def _transmit_loop(self) -> None:
        while True:
            with self._cond:
                while not self._stop and not self._heap:
                    self._cond.wait()
                if self._stop:
                    return
                due, _, _, msg, tag = self._heap[0]
                now = time.monotonic()
                start = max(due, self._bus_free_s)
                if start > now + self.SLACK_S:
                    self._cond.wait(start - now)
                    continue
                heapq.heappop(self._heap)
                if tag is not None and tag + 1 in self._sync_times and self._sync_times[tag + 1] <= start:
                    self._dropped_window += 1   # the next SYNC came first: outside the window
                    continue
                start = self._occupy(due, message_bits(msg))
                msg.timestamp = start + self._wall_offset
                self._sent += 1
                if self._filter_own:
                    self._own[(msg.arbitration_id, bytes(msg.data))] += 1
            try:
                self._inner.send(msg)
            except can.CanError:
                with self._cond:
                    self._dropped_overrun += 1

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
            on_bus = min(msg.timestamp - self._wall_offset, time.monotonic())
            start = self._occupy(on_bus, message_bits(msg))
            self._last_rx_end = self._bus_free_s
            if msg.arbitration_id == SYNC_COB_ID and not msg.is_extended_id:
                self._sync_seen += 1
                self._sync_times[self._sync_seen] = start
                self._sync_times.pop(self._sync_seen - 64, None)
        return msg, False

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
