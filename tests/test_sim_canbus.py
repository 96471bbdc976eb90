"""The simulated 1 Mbit/s bus: frame timing, reply delays, the SYNC window, and
the SYNC producer's punctuality figures."""

from __future__ import annotations

import time
import uuid

import can
import pytest

from elastocal.drivers.canframes import frame_bits, message_bits
from elastocal.sims.canbus import SimCanBus

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

BITRATE = 1_000_000


class Pair:
    """A SimCanBus (device side) and a plain virtual bus (the other nodes) on one channel."""

    def __init__(self, **kwargs):
        channel = f"canbus-{uuid.uuid4().hex[:8]}"
        # the other nodes stamp what they send with the time they send it, as a driver's bus does
        self.other = can.Bus(interface="virtual", channel=channel)
        inner = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.sim = SimCanBus(inner, bitrate=BITRATE, **kwargs)

    def close(self):
        self.sim.shutdown()
        self.other.shutdown()

    def sync(self) -> float:
        """The other side sends a SYNC; returns when it ended on the bus (monotonic-based wall time)."""
        self.other.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        rx = self.sim.recv(1.0)
        assert rx is not None and rx.arbitration_id == 0x80
        return rx.timestamp + frame_bits(0x80, 0) / BITRATE

    def drain(self, timeout_s=0.3):
        out = []
        while (m := self.other.recv(timeout_s)) is not None:
            out.append(m)
        return out


@pytest.fixture
def pair():
    p = Pair()
    yield p
    p.close()


def tpdo(node: int, data: bytes = bytes(8)) -> can.Message:
    return can.Message(arbitration_id=0x180 + node, data=data, is_extended_id=False)


def test_frames_queue_on_the_bus_timeline_by_their_exact_length(pair):
    msgs = [tpdo(n, bytes([n] * 8)) for n in (1, 2, 3, 4)]
    pair.sync()
    for m in msgs:
        pair.sim.send(m)
    got = pair.drain()
    assert [m.arbitration_id for m in got] == [0x181, 0x182, 0x183, 0x184]   # bus order
    starts = [m.timestamp for m in got]
    lengths = [frame_bits(0x180 + n, 8, bytes([n] * 8)) / BITRATE for n in (1, 2, 3, 4)]
    for k in range(3):                              # each starts when the one before ended
        assert starts[k + 1] - starts[k] == pytest.approx(lengths[k], abs=5e-7)   # wall-time float resolution
    st = pair.sim.stats()
    assert st.frames == 5 and st.sent == 4           # the SYNC and the four TPDOs
    assert st.bits == frame_bits(0x80, 0) + sum(message_bits(m) for m in msgs)
    assert st.dropped_window == 0 and st.dropped_overrun == 0


def test_frames_never_reach_the_other_nodes_before_they_ended(pair):
    sync_end = pair.sync()
    for n in range(1, 41):                          # 40 frames: ≈5 ms of bus time
        pair.sim.send(tpdo(n % 120 + 1))
    got = pair.drain()
    assert len(got) == 40
    arrived = time.time()
    last_end = got[-1].timestamp + message_bits(got[-1]) / BITRATE
    assert last_end - sync_end > 40 * 111 / BITRATE * 0.99    # the bus carried them one after another
    assert arrived >= last_end


def test_replies_come_the_nodes_delay_after_the_frame_that_triggered_them():
    p = Pair(reply_delay_s=lambda node: 200e-6 * node)
    try:
        sync_end = p.sync()
        p.sim.send(tpdo(3))
        p.sim.send(tpdo(1))                        # node 1 answers sooner, but the bus is taken
        got = p.drain()
        t3 = next(m.timestamp for m in got if m.arbitration_id == 0x183)
        t1 = next(m.timestamp for m in got if m.arbitration_id == 0x181)
        assert t3 == pytest.approx(sync_end + 600e-6, abs=1e-6)
        assert t1 == pytest.approx(t3 + frame_bits(0x183, 8, bytes(8)) / BITRATE, abs=1e-6)
    finally:
        p.close()


def test_a_tpdo_not_started_when_the_next_sync_comes_is_dropped():
    # a long reply delay pushes the TPDO 50 ms into the future; the SYNC comes first
    p = Pair(reply_delay_s=lambda node: 0.05, delivery_interval_s=0.2)
    try:
        p.sync()
        p.sim.send(tpdo(5))
        p.sync()
        assert p.drain(0.3) == []
        st = p.sim.stats()
        assert st.dropped_window == 1
        assert st.frames == 2                      # only the two SYNCs occupied the bus
        assert st.bits == 2 * frame_bits(0x80, 0)
    finally:
        p.close()


def test_a_full_transmit_queue_drops_frames_as_overrun():
    p = Pair(tx_queue=4, reply_delay_s=lambda node: 0.5, delivery_interval_s=1.0)
    try:
        p.sync()
        for n in range(1, 8):
            p.sim.send(tpdo(n))
        st = p.sim.stats()
        assert st.dropped_overrun == 3
        assert st.frames == 5                      # the SYNC and the four queued
    finally:
        p.close()


def test_bus_load_is_bits_over_bitrate_times_elapsed(pair):
    pair.sync()
    pair.sim.reset_stats()
    for n in range(1, 11):
        pair.sim.send(tpdo(n))
    pair.drain()
    st = pair.sim.stats()
    assert st.load == pytest.approx(st.bits / (BITRATE * st.elapsed_s))
    assert 0 < st.load < 1


def test_an_emcy_goes_on_the_bus_when_it_is_sent(pair):
    pair.sync()
    time.sleep(0.05)
    t = time.time()
    pair.sim.send(can.Message(arbitration_id=0x80 + 7, data=bytes(8), is_extended_id=False))
    got = pair.drain()
    assert len(got) == 1
    assert got[0].timestamp >= t - 1e-3            # not back on the timeline at the last SYNC


# ------------------------------------------------------- SYNC punctuality
def test_sync_stats_account_for_every_cycle():
    from elastocal.drivers import open_drive
    from elastocal.drivers.base import SharedLinks
    from elastocal.drivers.config import DriveConfig
    from elastocal.drivers.urls import parse_device_url
    from elastocal.sims.config import SimConfig
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.canopen_drive import SimCanopenDrive, SimCanopenNetwork
    from elastocal.sims.world import SimWorld

    world = SimWorld.from_config(bundled_robot(), SimConfig(seed=1))
    channel = f"sync-{uuid.uuid4().hex[:8]}"
    net = SimCanopenNetwork("virtual", channel, [SimCanopenDrive(11, 1, world, gear_ratio=100.0, serial=1)])
    links = SharedLinks()
    try:
        drive = open_drive(DriveConfig(joint=1, url=parse_device_url(f"canopen://virtual/{channel}?node=11"),
                                       timeout_s=0.5), links=links)
        rate = 200.0
        t0 = time.monotonic()
        with drive.stream(rate) as s:
            s.read_for(1.0)
            link = drive.link
            stats = link.sync_stats()
        elapsed = time.monotonic() - t0
        assert stats.rate_hz == rate
        # every slot of the absolute schedule up to the producer's last wake-up is counted, sent or
        # not; how many of them a loaded machine let it send on time is its business, not this test's
        cycles = stats.sent + stats.not_sent
        assert 0 < stats.sent <= cycles <= elapsed * rate + 2
        assert 0.0 <= stats.mean_lateness_s <= stats.max_lateness_s
        assert stats.late <= stats.sent
        drive.close()
    finally:
        links.close()
        net.close()


def test_burst_delivery_hands_tpdos_over_as_they_end_not_at_the_next_sync():
    """Across processes (udp_multicast stamps arrival), delivery_interval_s=0:
    a cycle's TPDOs go out as soon as the burst ended; batching waits."""
    for interval, expect in ((0.0, 6), (0.5, 0)):
        p = Pair(delivery_interval_s=interval)
        try:
            p.sync()
            for n in range(1, 7):
                p.sim.send(tpdo(n))
            got = []
            end = time.monotonic() + 0.15
            while time.monotonic() < end:
                m = p.other.recv(0.01)
                if m is not None:
                    got.append(m)
            assert len(got) == expect, interval
        finally:
            p.close()
