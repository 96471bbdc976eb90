"""The drive contract: what every :class:`~elastocal.drivers.base.Drive` backend must do,
written once and run against each backend and its simulated device (python-can's
back-to-back test style). A new backend subclasses :class:`DriveContract` and gives the
``bench`` fixture; the protocol's own details stay in its own test file
(tests/test_drivers_canopen.py, tests/test_drivers_modbus.py).

The bench is a :class:`Bench`: the open driver, its joint, the resolution of its current
reading, and a way to put the simulated device into a fault.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import pytest

from elastocal.drivers import open_drive
from elastocal.drivers.base import Drive, SharedLinks
from elastocal.drivers.config import DriveConfig, parse_cell_config
from elastocal.drivers.urls import parse_device_url
from elastocal.errors import DeviceFault
from elastocal.sims.canopen_drive import SimCanopenDrive, SimCanopenNetwork
from elastocal.sims.config import SimConfig
from elastocal.sims.modbus_server import ModbusServerThread, SimModbusDrive
from elastocal.sims.world import SimWorld

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

SIM = SimConfig(current_noise_a=0.0, tracker_noise_m=0.0, move_speed_rad_s=3.0, seed=5)


@dataclass
class Bench:
    drive: Drive
    joint: int
    current_resolution_a: float        # the reading's quantisation of the current
    fault: Callable[[], None]          # puts the simulated device into a fault state


class DriveContract:
    """The tests every drive backend passes (subclasses provide ``bench``)."""

    rate_hz = 100.0

    @pytest.fixture
    def world(self, robot):
        return SimWorld.from_config(robot, SIM)

    def test_identify_names_a_drive(self, bench):
        info = bench.drive.identify()
        assert info.kind == "drive" and info.vendor and info.model

    def test_read_gives_the_si_values_of_the_world(self, bench, world):
        s = bench.drive.read()
        i_true = world.cell.currents(world.equilibrium_at())[bench.joint - 1]
        assert s.joint == bench.joint and s.t_ns > 0
        assert s.current_a == pytest.approx(i_true, abs=bench.current_resolution_a + 1e-9)
        assert s.position_rad == pytest.approx(SIM.start_q[bench.joint - 1], abs=1e-5)

    def test_stream_follows_motion_and_accounts_for_every_sample(self, bench, world):
        target = list(SIM.start_q)
        target[bench.joint - 1] += 0.3
        with bench.drive.stream(self.rate_hz) as stream:
            world.move_to(target)
            batch = stream.read_for(0.5)
            stats = stream.stats()
        # nothing is lost silently: every expected sample arrived or is in a gap with its reason
        # (how many arrive depends on the machine's load, not on the driver: not asserted)
        assert stats.expected == stats.received + stats.missing
        assert len(batch.samples) >= 3 and all(g.reason and g.missing >= 1 for g in batch.gaps)
        assert sum(g.missing for g in batch.gaps) <= stats.missing
        q = np.array([s.position_rad for s in batch.samples])
        t = np.array([s.t_ns for s in batch.samples])
        assert np.all(np.diff(t) > 0) and np.all(np.diff(q) >= -1e-5)
        assert q[-1] > q[0] and q[-1] <= target[bench.joint - 1] + 1e-5

    def test_a_fault_is_a_device_fault_never_data(self, bench):
        bench.fault()
        with pytest.raises(DeviceFault):
            bench.drive.read()


class TestCanopenDrive(DriveContract):
    """CiA 402 over CANopen: a canopen LocalNode on a fresh virtual channel."""

    @pytest.fixture
    def bench(self, world):
        channel = f"contract-{uuid.uuid4().hex[:8]}"
        sim = SimCanopenDrive(12, 2, world, gear_ratio=SIM.gear_ratios[1], serial=102)
        net = SimCanopenNetwork("virtual", channel, [sim])
        links = SharedLinks()
        cfg = DriveConfig(joint=2, url=parse_device_url(f"canopen://virtual/{channel}?node=12"), timeout_s=0.3,
                          retries=1)
        drive = open_drive(cfg, links=links)
        try:
            # the current is reported in per mille of the rated current (CiA 402 0x6078)
            yield Bench(drive, 2, 0.005, lambda: sim.fault(0x2310))
        finally:
            drive.close()
            links.close()
            net.close()


MODBUS_CELL = """
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
status   = { address = 12, type = "uint16", fault_mask = 8, ready_mask = 1 }
"""


class TestModbusDrive(DriveContract):
    """Modbus TCP: a pymodbus server on 127.0.0.1, port chosen by the OS."""

    @pytest.fixture
    def bench(self, world):
        config = parse_cell_config(MODBUS_CELL, source="cell.toml").drives[0]
        sim = SimModbusDrive(config, world)
        server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
        drive = open_drive(replace(config, url=config.url.with_port(server.port)))
        try:
            yield Bench(drive, 2, 0.0005, sim.fault)         # int32 in mA
        finally:
            drive.close()
            server.close()
