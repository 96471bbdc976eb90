"""Contract suite: CiA 402 drives over CANopen against simulated LocalNodes on a virtual bus."""

from __future__ import annotations

import random
import time
import uuid

import numpy as np
import pytest

from elastocal.drivers import open_drive
from elastocal.drivers.base import SharedLinks
from elastocal.drivers.canframes import frame_bits, worst_frame_bits
from elastocal.drivers.canopen_link import MIN_INTERVAL
from elastocal.drivers.canopen_drive import state_name
from elastocal.drivers.config import DriveConfig
from elastocal.drivers.urls import parse_device_url
from elastocal.sims.config import SimConfig
from elastocal.errors import DeviceFault, DeviceTimeout, InputError
from elastocal.sims.canopen_drive import SimCanopenDrive, SimCanopenNetwork
from elastocal.sims.world import SimWorld

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

GEARS = SimConfig().gear_ratios


@pytest.fixture
def world(robot):
    sim = SimConfig(current_noise_a=0.0, tracker_noise_m=0.0, move_speed_rad_s=2.0, seed=3)
    return SimWorld.from_config(robot, sim)


class Bench:
    """Simulated drives on a fresh virtual channel and the drivers talking to them."""

    # 2 s: an SDO reply that a loaded machine delivers after the timeout arrives during the retry
    # and is taken for the wrong answer (canopen's SdoCommunicationError), so no test but the
    # timeout's own may count on a fast answer
    def __init__(self, world, joints=(1, 2), *, tpdo2=False, timeout_s=2.0, retries=1):
        self.channel = f"test-{uuid.uuid4().hex[:8]}"
        self.sims = {j: SimCanopenDrive(j + 10, j, world, gear_ratio=GEARS[j - 1], serial=100 + j, tpdo2=tpdo2)
                     for j in joints}
        self.net = SimCanopenNetwork("virtual", self.channel, list(self.sims.values()))
        self.links = SharedLinks()
        self.drives = {}
        try:
            for j in joints:
                cfg = DriveConfig(joint=j, url=parse_device_url(f"canopen://virtual/{self.channel}?node={j + 10}"),
                                  timeout_s=timeout_s, retries=retries)
                self.drives[j] = open_drive(cfg, links=self.links)
        except BaseException:
            self.close()
            raise

    def close(self):
        for d in self.drives.values():
            d.close()
        self.links.close()
        self.net.close()


@pytest.fixture
def bench(world):
    b = Bench(world)
    yield b
    b.close()


# ----------------------------------------------------------------- frames
def reference_frame_bits(can_id: int, data: bytes) -> int:
    """Bit by bit, as the CAN 2.0A specification writes it."""
    bits = [0] + [(can_id >> (10 - i)) & 1 for i in range(11)] + [0, 0, 0]
    bits += [(len(data) >> (3 - i)) & 1 for i in range(4)]
    for byte in data:
        bits += [(byte >> (7 - i)) & 1 for i in range(8)]
    crc = 0
    for b in bits:
        crc, feedback = (crc << 1) & 0x7FFF, b ^ ((crc >> 14) & 1)
        crc ^= 0x4599 if feedback else 0
    bits += [(crc >> (14 - i)) & 1 for i in range(15)]
    stuffed, value, run = 0, bits[0], 1
    for b in bits[1:]:
        if b == value:
            run += 1
            if run == 5:
                stuffed, value, run = stuffed + 1, 1 - b, 1
        else:
            value, run = b, 1
    return len(bits) + stuffed + 13


def test_frame_bits_match_the_specification():
    rng = random.Random(0)
    for _ in range(500):
        n = rng.randrange(9)
        data = bytes(rng.choice((0, 0xFF, rng.randrange(256))) for _ in range(n))
        can_id = rng.randrange(0x800)
        assert frame_bits(can_id, n, data) == reference_frame_bits(can_id, data)


def test_frame_lengths_give_the_1_mbit_budget():
    rng = random.Random(1)
    lengths = [frame_bits(rng.randrange(0x180, 0x200), 8, bytes(rng.randrange(256) for _ in range(8)))
               for _ in range(2000)]
    assert all(111 <= n <= worst_frame_bits(8) for n in lengths)      # 111 = 8-byte frame without stuffing
    assert 8200 < 1e6 / np.mean(lengths) < 9000                        # ≈8,500 frames/s at 1 Mbit/s
    # all-zero data stuffs a bit after every five equal bits
    assert frame_bits(0x000, 8, bytes(8)) > frame_bits(0x555, 8, bytes([0x55] * 8))
    assert worst_frame_bits(8) == 135 and worst_frame_bits(0) == 34 + 8 + 13


def test_state_names_follow_cia402():
    assert state_name(0x0237) == "operation enabled"
    assert state_name(0x0233) == "switched on"
    assert state_name(0x0218) == "fault"
    assert state_name(0x0250) == "switch on disabled"


# ---------------------------------------------------------------- on demand
def test_identify_reads_the_identity_object(bench):
    info = bench.drives[2].identify()
    assert info.kind == "drive" and info.serial == "102"
    assert dict(info.details)["state"] == "operation enabled"
    assert float(dict(info.details)["gear ratio"]) == pytest.approx(GEARS[1])


def test_sdo_read_converts_drive_units_to_si(bench, world):
    world.move_to([0.3, 0.5, -0.7, 0.2, 0.4, -0.1])
    assert world.wait_idle(5.0)
    s = bench.drives[2].read()
    eq = world.equilibrium_at()
    i_true = world.cell.currents(eq)[1]
    assert s.joint == 2
    assert s.position_rad == pytest.approx(0.5, abs=1.0 / bench.drives[2].counts_per_rad)
    assert s.current_a == pytest.approx(i_true, abs=0.005 + 1e-9)          # per-mille of 10 A
    xi = world.robot.torque_constants[1]
    assert s.torque_nm == pytest.approx(xi * i_true, abs=0.5 * 20.0 * GEARS[1] / 1000 + 1e-6)
    assert s.velocity_rad_s == 0.0
    assert s.status == 0x0237


# ------------------------------------------------------------------ streams
def test_stream_on_sync_matches_the_world(bench, world):
    rate = 200.0
    with bench.drives[1].stream(rate) as s1, bench.drives[2].stream(rate) as s2:
        b1 = s1.read_for(0.6)
        st1 = s1.stats()
        b2 = s2.read_for(0.6)
        st = s1.stats()
    # every SYNC cycle is accounted for, delivered or missing: counted against the cycles the
    # link ran by then (how many a loaded machine let the producer send on time is not this test's)
    assert st.expected == st.received + st.missing
    assert 0 < len(b1.samples) <= st1.received <= st1.expected
    # samples are stamped with their SYNC: in order, never closer than the producer's spacing
    t = np.array([s.t_ns for s in b1.samples])
    period_ns = 1e9 / rate
    assert np.all(np.diff(t) >= MIN_INTERVAL * period_ns - 1e3)
    i_true = world.cell.currents(world.equilibrium_at())
    for batch, j in ((b1, 1), (b2, 2)):
        cur = np.array([s.current_a for s in batch.samples])
        assert np.all(np.abs(cur - i_true[j - 1]) <= 0.005 + 1e-9)
        assert all(s.velocity_rad_s is None and s.torque_nm is None for s in batch.samples)
    # both drives answer the same SYNCs: they share acquisition times
    common = set(s.t_ns for s in b1.samples) & set(s.t_ns for s in b2.samples)
    assert len(common) > 0.8 * min(len(b1.samples), len(b2.samples))


def test_second_tpdo_streams_velocity_and_torque(world):
    bench = Bench(world, joints=(3,), tpdo2=True)
    try:
        u, v = [0.0, 0.2, -0.8, 0.0, 0.5, 0.0], [0.0, 0.2, 0.0, 0.0, 0.5, 0.0]
        world.move_to(u)
        assert world.wait_idle(5.0)
        world.run(u, v, speed_rad_s=0.8)
        with bench.drives[3].stream(200.0) as s:
            batch = s.read_for(0.5)
        moving = [x for x in batch.samples if x.velocity_rad_s and abs(x.velocity_rad_s) > 0]
        assert moving, "no sample during the run"
        assert all(x.velocity_rad_s == pytest.approx(0.8, abs=1e-6) for x in moving)
        assert all(x.torque_nm is not None for x in batch.samples)
    finally:
        bench.close()


def test_bus_budget_is_checked_before_streaming(world):
    bench = Bench(world, joints=(1, 2, 3, 4, 5, 6), tpdo2=True)
    streams = []
    try:
        with pytest.raises(InputError, match="Mbit/s"):
            for d in bench.drives.values():
                streams.append(d.stream(1000.0))
        assert 2 <= len(streams) < 6
    finally:
        for s in streams:
            s.close()
        bench.close()


def test_one_sync_rate_per_bus(bench):
    with bench.drives[1].stream(100.0):
        with pytest.raises(InputError, match="one SYNC"):
            bench.drives[2].stream(200.0)


# ------------------------------------------------------------------- faults
def test_fault_mid_stream_ends_in_device_fault_not_data(bench):
    stream = bench.drives[2].stream(200.0)
    try:
        first = stream.read_for(0.2)
        assert first.samples
        t_fault = time.monotonic_ns()
        bench.sims[2].fault(0x2310)
        seen = []
        with pytest.raises(DeviceFault, match="0x2310"):
            for _ in range(50):
                seen.extend(stream.read(timeout_s=1.0).samples)
        assert all(s.status == 0x0237 for s in seen)
        assert all(s.t_ns < t_fault + 20_000_000 for s in seen)
    finally:
        stream.close()
    with pytest.raises(DeviceFault, match="fault, error code 0x2310"):
        bench.drives[2].read()


def test_drive_not_in_operation_enabled_is_reported(bench):
    bench.sims[1].disable()
    with pytest.raises(DeviceFault, match="'switched on', not 'operation enabled'"):
        bench.drives[1].read()
    with bench.drives[1].stream(100.0) as stream:
        with pytest.raises(DeviceFault, match="switched on"):
            for _ in range(20):
                assert not stream.read(timeout_s=1.0).samples


def test_short_silence_is_a_recorded_gap_then_the_stream_resumes(world):
    """A drive that leaves 20 SYNCs unanswered is a recorded silence of (at least) those 20
    cycles, then samples again. The silence is counted in SYNCs and the stream is read
    until it resumed, so nothing depends on how fast a loaded machine runs the threads;
    the bound on the reads only ends a hang."""
    rate, silent = 200.0, 20
    bench = Bench(world, joints=(1,), timeout_s=5.0)      # the timeout is not what this test is about
    try:
        with bench.drives[1].stream(rate) as stream:
            stream.read_for(0.15)
            bench.sims[1].go_silent(cycles=silent)
            samples, gaps = [], []
            for _ in range(200):
                batch = stream.read(timeout_s=1.0)
                samples, gaps = samples + list(batch.samples), gaps + list(batch.gaps)
                no_tpdo = [g for g in gaps if g.reason == "no TPDO in the SYNC cycle"]
                if no_tpdo and sum(s.t_ns > max(g.end_ns for g in no_tpdo) for s in samples) >= 3:
                    break
    finally:
        bench.close()
    # the gaps of one silence all start at the last sample before it; a loaded machine's
    # producer leaves some SYNCs unsent in between ("SYNC not sent", a reason of its own),
    # and a TPDO delivered after its cycle closed adds a missing cycle: so at least the
    # silent cycles, and each SYNC at least MIN_INTERVAL of a period after the one before
    silences: dict[int, list] = {}
    for g in gaps:
        silences.setdefault(g.start_ns, []).append(g)
    silence = max(silences.values(), key=lambda run: sum(g.missing for g in run if g.reason.startswith("no TPDO")))
    unanswered = sum(g.missing for g in silence if g.reason == "no TPDO in the SYNC cycle")
    assert unanswered >= silent, silence
    start_ns, end_ns = silence[0].start_ns, max(g.end_ns for g in silence)
    assert end_ns - start_ns >= silent * MIN_INTERVAL * 1e9 / rate
    # the stream resumes: samples after the silence, in order
    after = [s.t_ns for s in samples if s.t_ns > end_ns]
    assert len(after) >= 3 and after == sorted(after)
    assert not [s for s in samples if start_ns < s.t_ns < end_ns], "a sample inside the silence"


def test_long_silence_ends_in_timeout(bench):
    with bench.drives[1].stream(100.0) as other, bench.drives[2].stream(100.0) as stream:
        stream.read_for(0.1)
        bench.sims[2].go_silent(None)
        # the silent drive's stream delivers nothing until the link's 2 s timeout ends it: each read
        # waits longer than that, and the deadline only ends a hang
        deadline = time.monotonic() + 60.0
        with pytest.raises(DeviceTimeout, match="no valid TPDO for 2 s"):
            while time.monotonic() < deadline:
                stream.read(timeout_s=10.0)
        assert other.read_for(0.1).samples        # the other node on the bus is unaffected
    with pytest.raises(DeviceTimeout, match="no SDO reply"):
        bench.drives[2].read()


def test_malformed_tpdos_are_gaps(bench):
    with bench.drives[2].stream(200.0) as stream:
        stream.read_for(0.1)
        bench.sims[2].send_malformed(3)
        batch = stream.read_for(0.3)
    bad = [g for g in batch.gaps if g.reason.startswith("malformed TPDO")]
    assert sum(g.missing for g in bad) == 3
    assert "(3 of 8 bytes)" in bad[0].reason
