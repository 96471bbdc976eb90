"""Contract suite: Modbus drives (TCP and RTU) against simulated pymodbus servers."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from elastocal.drivers import open_drive
from elastocal.drivers.base import ModbusExceptionError
from elastocal.drivers.config import parse_cell_config
from elastocal.drivers.registers import RegisterSpec
from elastocal.drivers.urls import parse_device_url
from elastocal.sims.config import SimConfig
from elastocal.drivers.modbus import decode, encode, register_runs
from elastocal.errors import DeviceFault, DeviceTimeout, InputError, ProtocolError
from elastocal.sims.modbus_server import ModbusServerThread, PtyPair, SimModbusDrive
from elastocal.sims.world import SimWorld
from stream_reading import read_samples

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

CELL = """
[cell]
robot = "hh150"
[[drive]]
joint = 2
url = "modbus+tcp://127.0.0.1:0?unit=3"
timeout_s = 0.2
retries = 1
[drive.registers]
current  = { address = 0, type = "int32", scale = 0.001, unit = "A" }
position = { address = 2, type = "float32", unit = "rad" }
torque   = { address = 4, type = "float32", unit = "N*m" }
velocity = { address = 10, type = "int16", scale = 0.1, unit = "mrad/s", table = "input" }
status   = { address = 12, type = "uint16", fault_mask = 8, ready_mask = 1 }
"""


@pytest.fixture
def world(robot):
    return SimWorld.from_config(robot, SimConfig(current_noise_a=0.0, move_speed_rad_s=3.0, seed=5))


@pytest.fixture
def drive_config():
    return parse_cell_config(CELL, source="cell.toml").drives[0]


@pytest.fixture
def tcp(world, drive_config):
    sim = SimModbusDrive(drive_config, world)
    server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
    drive = open_drive(replace(drive_config, url=drive_config.url.with_port(server.port)))
    yield sim, server, drive
    drive.close()
    server.close()


# ----------------------------------------------------------------- codec
@pytest.mark.parametrize("rtype,value,word_order", [
    ("int16", -1234, "big"), ("uint16", 54321, "big"), ("int32", -123456789, "big"),
    ("uint32", 4000000000, "little"), ("float32", 1.5, "big"), ("float64", -2.25e-3, "little")])
def test_register_codec_round_trips(rtype, value, word_order):
    spec = RegisterSpec("x", 0, type=rtype, word_order=word_order)
    regs = encode(spec, [value])
    assert len(regs) == spec.n_registers and all(0 <= r <= 0xFFFF for r in regs)
    assert decode(spec, regs) == [pytest.approx(value)]


def test_register_bytes_follow_the_word_order():
    spec = RegisterSpec("x", 0, type="int32", word_order="big")
    assert encode(spec, [0x12345678]) == [0x1234, 0x5678]
    assert encode(replace(spec, word_order="little"), [0x12345678]) == [0x5678, 0x1234]
    scaled = RegisterSpec("i", 0, type="int16", scale=0.01, unit="mA")
    assert encode(scaled, [0.005]) == [500]               # 0.005 A = 5 mA = 500 * 0.01 mA
    with pytest.raises(InputError, match="does not fit"):
        encode(scaled, [1.0])


def test_reads_are_grouped_into_contiguous_blocks(drive_config):
    assert register_runs(drive_config.registers) == [("holding", 0, 6), ("holding", 12, 1), ("input", 10, 1)]


# ------------------------------------------------------------------ reads
def test_tcp_read_gives_si_values_of_the_world(tcp, world):
    sim, server, drive = tcp
    info = drive.identify()
    assert info.vendor == "elastocal" and dict(info.details)["unit"] == "3"
    s = drive.read()
    i_true = world.cell.currents(world.equilibrium_at())[1]
    assert s.current_a == pytest.approx(i_true, abs=0.0005 + 1e-12)   # int32 in mA
    assert s.position_rad == pytest.approx(0.2, abs=1e-7)              # float32
    assert s.torque_nm == pytest.approx(world.robot.torque_constants[1] * s.current_a, rel=1e-3)
    assert s.velocity_rad_s == 0.0 and s.status == 1


def test_tcp_stream_polls_at_the_rate_and_follows_motion(tcp, world):
    sim, server, drive = tcp
    target = [0.0, 0.5, -0.4, 0.0, 0.5, 0.0]
    with drive.stream(100.0) as stream:
        world.move_to(target)
        batch = read_samples(stream, 40)          # a count: a loaded machine polls fewer in 0.5 s
        st = stream.stats()
    q = np.array([s.position_rad for s in batch.samples])
    assert st.expected == st.received + st.missing and st.received >= 35
    assert q[0] < q[-1] <= 0.5 + 1e-6 and np.all(np.diff(q) >= -1e-7)
    moving = [s for s in batch.samples if s.velocity_rad_s]
    assert moving and all(s.velocity_rad_s == pytest.approx(3.0, abs=1e-4) for s in moving)


def test_rtu_over_a_pty_pair(world, drive_config):
    sim = SimModbusDrive(drive_config, world)
    pair = PtyPair()
    server = ModbusServerThread([sim.device], serial=pair.device_end, baudrate=115200).start()
    url = parse_device_url(f"modbus+rtu://{pair.host_end}?baud=115200&unit=3")
    drive = open_drive(replace(drive_config, url=url))
    try:
        s = drive.read()
        assert s.position_rad == pytest.approx(0.2, abs=1e-7)
        with drive.stream(20.0) as stream:
            batch = read_samples(stream, 3)
        # a poll a loaded machine started late is a recorded gap of its own kind; no other gap
        assert len(batch.samples) >= 3
        assert all(g.reason.startswith("poll could not start on time") for g in batch.gaps), batch.gaps
        server.corrupt_replies(1)                 # bad CRC: discarded, the retry gets a good reply
        assert drive.read().position_rad == pytest.approx(0.2, abs=1e-7)
    finally:
        drive.close()
        server.close()
        pair.close()


# ----------------------------------------------------------------- faults
def test_exception_response_is_typed(tcp):
    sim, server, drive = tcp
    sim.fail_with(2)
    with pytest.raises(ModbusExceptionError, match=r"exception 2 \(illegal data address\)") as err:
        drive.read()
    assert err.value.code == 2
    assert drive.read().status == 1                 # the next request is answered


def test_one_transient_exception_mid_stream_is_a_gap_and_the_stream_goes_on(tcp):
    """Audit item 8: one Modbus exception response ended the run. A transient one (4, 5, 6, 10, 11)
    is now a recorded gap; it ends the stream only when it lasts timeout_s * (retries + 1)."""
    sim, server, drive = tcp
    with drive.stream(100.0) as stream:
        assert stream.read_for(0.1).samples
        sim.fail_with(4)                                  # one device-failure response
        batch = stream.read_for(0.3)
        assert batch.samples and [g.missing for g in batch.gaps] == [1], batch.gaps
        assert "Modbus exception 4" in batch.gaps[0].reason
        sim.fail_with(6, count=1000)                      # busy for good: gaps, then the stream ends
        with pytest.raises(ModbusExceptionError, match=r"device busy.*no valid reply for 0\.4 s"):
            for _ in range(50):
                stream.read(timeout_s=1.0)
    assert ModbusExceptionError("x", 6).transient and not ModbusExceptionError("x", 2).transient


def test_an_exception_that_says_the_map_is_wrong_ends_the_stream_at_once(tcp):
    sim, server, drive = tcp
    with drive.stream(100.0) as stream:
        assert stream.read_for(0.1).samples
        sim.fail_with(2)
        with pytest.raises(ModbusExceptionError, match="illegal data address"):
            for _ in range(20):
                stream.read(timeout_s=1.0)


def test_timeout_after_retries_then_recovers(tcp):
    sim, server, drive = tcp
    sim.delay_replies(0.35, count=2)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="after 2 attempts"):
        drive.read()
    # it waited for the delayed replies (no upper bound on wall-clock time: on a loaded
    # machine the attempts take longer; the message says how many there were)
    assert time.monotonic() - t0 > 0.35
    time.sleep(0.4)
    assert drive.read().status == 1


def test_disconnect_is_reconnected(tcp):
    sim, server, drive = tcp
    drive.read()
    server.drop_connections()
    time.sleep(0.05)
    assert drive.read().position_rad == pytest.approx(0.2, abs=1e-7)
    with drive.stream(100.0) as stream:
        stream.read_for(0.1)
        t_drop = time.monotonic_ns()
        server.drop_connections()             # the server closes our connection: every later
        batch = read_samples(stream, until=lambda got: sum(x.t_ns > t_drop for x in got) >= 15)
    after = [x for x in batch.samples if x.t_ns > t_drop]           # sample came over a new one
    assert len(after) >= 15
    assert all(abs(x.position_rad - 0.2) < 1e-7 for x in after)
    assert stream.stats().expected == stream.stats().received + stream.stats().missing


def test_garbled_reply_is_a_gap_in_a_stream(tcp):
    sim, server, drive = tcp
    with drive.stream(50.0) as stream:
        stream.read_for(0.1)
        server.corrupt_replies(1)
        batch = stream.read_for(0.6)
    # the failed poll waited out its timeout: the polls it delayed are a gap too
    assert batch.gaps[0].missing == 1 and batch.gaps[0].reason.startswith("poll failed")
    assert all(g.reason.startswith("poll could not start on time") for g in batch.gaps[1:])
    assert sum(g.missing for g in batch.gaps) <= 0.5 * 50
    assert batch.samples[-1].t_ns > batch.gaps[-1].end_ns


def test_fault_bit_is_a_device_fault(tcp):
    sim, server, drive = tcp
    sim.fault()
    with pytest.raises(DeviceFault, match="fault bit"):
        drive.read()
    sim.fault(False)
    with drive.stream(100.0) as stream:
        stream.read_for(0.05)
        sim.fault()
        with pytest.raises(DeviceFault):
            for _ in range(20):
                for s in stream.read(timeout_s=1.0).samples:
                    assert s.status == 1


def test_wrong_scale_is_caught_by_the_unit_checks(world, drive_config):
    bad = replace(drive_config, registers=tuple(replace(r, scale=1.0) if r.name == "current" else r
                                               for r in drive_config.registers))
    sim = SimModbusDrive(drive_config, world)          # the device counts mA
    server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
    drive = open_drive(replace(bad, url=bad.url.with_port(server.port)))
    try:
        with pytest.raises(ProtocolError, match="above max_current_a"):
            drive.read()
    finally:
        drive.close()
        server.close()
