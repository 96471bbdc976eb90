"""Contract suite: the cell-controller handshake over Modbus against the simulated controller."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from elastocal.drivers import open_controller
from elastocal.drivers.base import ControllerStatus
from elastocal.errors import DeviceFault, DeviceTimeout, InputError
from elastocal.sims.modbus_server import ModbusServerThread, SimCellController
from elastocal.sims.serve import example_cell_config
from elastocal.sims.world import SimWorld
from elastocal.sims.config import sim_config

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def config():
    return example_cell_config(move_speed_rad_s=4.0, seed=1)


@pytest.fixture(scope="module")
def robot(config):
    return config.load_robot()


@pytest.fixture
def bench(config, robot):
    world = SimWorld.from_config(robot, sim_config(config))
    sim = SimCellController(config.controller, world)
    server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
    cfg = replace(config.controller, url=config.controller.url.with_port(server.port), move_timeout_s=10.0)
    controller = open_controller(cfg)
    yield world, sim, controller
    controller.close()
    server.close()
    sim.close()


def writable(config):
    return {a for r in config.controller.registers if r.access == "write"
            for a in range(r.address, r.address + r.n_registers)}


def test_move_to_pose_waits_for_in_position(bench, config):
    world, sim, controller = bench
    st = controller.status()
    assert isinstance(st, ControllerStatus) and st.in_position and not st.busy
    target = config.controller.pose(4)
    t0 = time.monotonic()
    st = controller.move_to_pose(4)
    assert time.monotonic() - t0 >= np.max(np.abs(np.array(target) - sim_config(config).start_q)) / 4.0 - 0.01
    assert st.in_position and not st.busy and st.ack == 1
    np.testing.assert_allclose(world.q_now(), target, atol=1e-12)
    np.testing.assert_allclose(st.q, target, atol=1e-6)           # float32 registers
    assert all(a in writable(config) for first, n in sim.writes for a in range(first, first + n))
    assert sim.writes[-1] == (config.controller.register("sequence").address, 1)   # the strobe goes last


def test_move_joints_and_runs_both_ways(bench, config):
    world, sim, controller = bench
    q = [0.1, 0.3, -0.5, 0.2, 0.4, -0.2]
    controller.move_joints(q)
    np.testing.assert_allclose(world.q_now(), q, atol=1e-12)
    path = config.controller.path(1)
    st = controller.run(1, "UV", speed_rad_s=2.0)
    assert st.run_done and not st.in_position
    np.testing.assert_allclose(world.q_now(), path.v, atol=1e-12)
    controller.run(1, "VU", speed_rad_s=2.0)
    np.testing.assert_allclose(world.q_now(), path.u, atol=1e-12)
    assert controller.status().ack == 3


def test_refused_requests_are_faults(bench):
    world, sim, controller = bench
    with pytest.raises(DeviceFault, match="error code 2"):
        controller.move_to_pose(99)                      # not taught
    with pytest.raises(DeviceFault, match="error code 3"):
        controller.run(7, "UV")
    with pytest.raises(DeviceFault, match="error code 4"):
        controller.move_joints([0.0, 3.0, 0.0, 0.0, 0.0, 0.0])   # beyond the joint-2 limit
    assert controller.move_to_pose(1).in_position        # the controller still works


def test_a_slow_move_times_out(bench):
    world, sim, controller = bench
    with pytest.raises(DeviceTimeout, match="did not finish within 0.05 s"):
        controller.move_to_pose(5, timeout_s=0.05)
    assert world.wait_idle(10.0)


def test_only_declared_registers_are_written(config, robot):
    regs = tuple(r for r in config.controller.registers if r.name not in ("pose", "target"))
    world = SimWorld.from_config(robot, sim_config(config))
    sim = SimCellController(replace(config.controller, registers=regs), world)
    server = ModbusServerThread([sim.device], tcp=("127.0.0.1", 0)).start()
    cfg = replace(config.controller, url=config.controller.url.with_port(server.port), registers=regs)
    controller = open_controller(cfg)
    try:
        with pytest.raises(InputError, match="needs the 'pose' register"):
            controller.move_to_pose(2)
        with pytest.raises(InputError, match="needs the 'target' register"):
            controller.move_joints([0.0] * 6)
        assert sim.writes == []                           # refused before anything was written
        read_only = replace(cfg, registers=tuple(replace(r, access="read") if r.name == "path" else r
                                                 for r in regs))
        c2 = open_controller(read_only)
        try:
            with pytest.raises(InputError, match="'path' is not declared writable"):
                c2.run(1, "UV")
        finally:
            c2.close()
        assert sim.writes == []
    finally:
        controller.close()
        server.close()
        sim.close()
