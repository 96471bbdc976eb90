"""The guidance drivers (EGM, RSI) and the Net F/T driver against their simulated peers on 127.0.0.1.

Units and signs from first principles: a joint target sent in radians reaches the simulated
robot as the same angle (the wire carries degrees), RSI's correction is the target minus the
reference ASPos, the Net F/T's counts over counts-per-unit are newtons in the sensor's axes,
the currents the controller reports are the gear torques over the torque constants. Nothing
here asserts on wall-clock speed: the peers' own counts say what happened.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from elastocal.drivers import open_force_sensor, open_guidance
from elastocal.drivers.force import RDT_RECORD, NetFtSensor, SensorFault, rdt_request, RdtCommand
from elastocal.drivers.guidance import ControllerLost
from elastocal.drivers.rsi import sen_message
from elastocal.drivers.urls import parse_device_url
from elastocal.errors import InputError, ProtocolError
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.egm_controller import SimEgmController
from elastocal.sims.guided import Faults, GuidedRobot, ProcessLoad, SensorPlacement, statics
from elastocal.sims.netft_sensor import NetFtNoise, SimNetFt
from elastocal.sims.rsi_controller import SimRsiController

Q0 = np.array([0.1, 0.5, -0.5, 0.2, -1.2, 0.3])
WRENCH = np.array([120.0, -80.0, 900.0, 4.0, -6.0, 2.0])


@pytest.fixture(scope="module")
def quiet_cell(robot):
    """The default simulated cell without current noise (exact comparisons)."""
    return SimCell(robot, replace(CellTruth(), current_noise_a=0.0))


def _guided(cell, load=None):
    return GuidedRobot(cell, start_q=Q0, load=load)


def _drive(guidance, steps, target_of):
    """Answer ``steps`` state messages with ``target_of(k, state)``; returns the states."""
    states = []
    for k in range(steps):
        s = guidance.receive(timeout_s=2.0)
        states.append(s)
        guidance.send(target_of(k, s))
    return states


@pytest.mark.parametrize("scheme,peer", [("egm", SimEgmController), ("rsi", SimRsiController)])
def test_a_target_in_radians_reaches_the_simulated_robot_as_that_angle(quiet_cell, scheme, peer):
    robot = _guided(quiet_cell, ProcessLoad(WRENCH, WRENCH, 1.0))
    step = np.array([1e-4, -2e-4, 1.5e-4, 3e-4, -1e-4, 2e-4])
    targets = [Q0 + step * k / 60 for k in range(61)]
    with open_guidance(parse_device_url(f"{scheme}://127.0.0.1:0"), n_joints=6) as g:
        with peer(robot, g.address) as sim:
            states = _drive(g, 60, lambda k, s: targets[k + 1])
        stats = sim.stats()
    # every answer the controller took moved the robot exactly to a target sent (late ones it held)
    tol = 1e-12 if scheme == "egm" else 2e-8          # EGM carries doubles, RSI six decimals of a degree
    moved = [h.q for h in robot.history() if np.any(h.q != Q0)]
    assert stats.answered >= 1 and len(moved) >= stats.answered
    for q in moved:
        assert min(np.max(np.abs(q - t)) for t in targets[1:]) < tol
    # the controller reports the joints in radians through the driver
    assert np.max(np.abs(states[0].q - Q0)) < tol
    # its currents are the simulated gear torques over the torque constants (xi i = gear torque)
    last = states[-1]
    expected = statics(quiet_cell, last.q, WRENCH).gear_torque / quiet_cell.robot.torque_constants
    assert np.max(np.abs(last.currents_a - expected)) < 1e-6 * np.max(np.abs(expected)) + 1e-9


def test_rsi_sends_the_axis_correction_from_the_reference_setpoint():
    correction_deg = np.array([0.01, -0.02, 0.0, 0.5, 0.0, -0.25])
    root = sen_message("ImFree", correction_deg, 1234)
    assert b'<Sen Type="ImFree">' in root and b"<IPOC>1234</IPOC>" in root
    assert b'A4="0.500000"' in root and b'A6="-0.250000"' in root


def test_rsi_ignores_an_answer_to_another_cycle(quiet_cell):
    """An answer echoing the wrong IPOC is late: the robot holds, the controller counts it."""
    robot = _guided(quiet_cell)
    with open_guidance(parse_device_url("rsi://127.0.0.1:0"), n_joints=6) as g:
        with SimRsiController(robot, g.address) as sim:
            try:
                for _ in range(20):
                    s = g.receive(timeout_s=2.0)
                    g._sock.sendto(sen_message("ImFree", np.full(6, 0.05), s.sequence + 1), g._peer)
            except ControllerLost:
                pass          # on a loaded machine the controller may reach its late-answer limit first
        stats = sim.stats()
    assert stats.answered == 0 and stats.late == stats.cycles > 0
    assert np.max(np.abs(robot.q - Q0)) == 0.0


def test_the_controller_s_lost_messages_and_silence_are_typed(quiet_cell):
    robot = _guided(quiet_cell)
    faults = Faults(lost_cycles=frozenset({5, 6}), silent_from_cycle=30)
    url = parse_device_url("egm://127.0.0.1:0?timeout_s=0.3")
    with open_guidance(url, n_joints=6) as g, SimEgmController(robot, g.address, faults=faults):
        times = []
        with pytest.raises(ControllerLost):
            while True:
                s = g.receive()
                times.append(s.controller_time_ms)
                g.send(Q0)
    assert 20 not in times and 24 not in times        # cycles 5 and 6 (4 ms each) never came
    assert max(times) <= 29 * 4 and times == sorted(times)


def test_a_malformed_state_message_is_a_protocol_error(quiet_cell):
    import socket

    with open_guidance(parse_device_url("rsi://127.0.0.1:0"), n_joints=6) as g:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.sendto(b"<Rob><AIPos A1='1'/><IPOC>4</IPOC></Rob>", g.address)
            with pytest.raises(ProtocolError, match="A2"):
                g.receive(timeout_s=2.0)
            peer.sendto(b"\x00\x01 not protobuf", g.address)
    with open_guidance(parse_device_url("egm://127.0.0.1:0"), n_joints=6) as g:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.sendto(b"\xff\xff\xff garbage", g.address)
            with pytest.raises(ProtocolError):
                g.receive(timeout_s=2.0)


@pytest.mark.parametrize("text,message", [
    ("rsi://127.0.0.1:0?cycle_ms=5", "4 ms"), ("egm://127.0.0.1", "UDP port"), ("netft://", "address"),
    ("rsi://127.0.0.1:0?current_scale_a=-1", "positive"),
])
def test_bad_guidance_and_sensor_urls_are_refused(text, message):
    with pytest.raises(InputError, match=message):
        url = parse_device_url(text)
        if url.scheme == "netft":
            NetFtSensor(url)
        else:
            open_guidance(url, n_joints=6).close()


def test_rsi_refuses_a_robot_it_cannot_guide():
    with pytest.raises(InputError, match="A1..A6"):
        open_guidance(parse_device_url("rsi://127.0.0.1:0"), n_joints=7)


def test_the_net_ft_counts_are_newtons_in_the_sensor_axes(quiet_cell):
    robot = _guided(quiet_cell, ProcessLoad(WRENCH, WRENCH, 1.0))
    robot.step(Q0, 0.5)
    want = robot.sensor_wrench(SensorPlacement())
    with SimNetFt(robot, noise=NetFtNoise(0.0, 0.0), counts_per_force=1e5, counts_per_torque=1e6) as ft:
        url = parse_device_url(ft.url() + "?counts_per_force=100000&counts_per_torque=1000000")
        with open_force_sensor(url) as sensor:
            sensor.start()
            s = sensor.wait_first(5.0)
    # counts are integers: the reading is the wrench to half a count
    assert np.max(np.abs(s.wrench[:3] - want[:3])) <= 0.5 / 1e5 + 1e-12
    assert np.max(np.abs(s.wrench[3:] - want[3:])) <= 0.5 / 1e6 + 1e-12
    # and the sensor's axes are the load point's: turned back into base axes it is the process wrench
    rot = quiet_cell.robot.model.createData()
    import pinocchio as pin

    pin.framesForwardKinematics(quiet_cell.robot.model, rot, statics(quiet_cell, Q0, WRENCH).theta)
    r = rot.oMf[quiet_cell.robot.frame_id("load_point")].rotation
    assert np.allclose(r @ s.wrench[:3], WRENCH[:3], atol=1e-4)


def test_a_sensor_fault_and_a_silent_sensor(quiet_cell):
    robot = _guided(quiet_cell, ProcessLoad(WRENCH, WRENCH, 1.0))
    with SimNetFt(robot, fault_after_s=0.0) as ft, open_force_sensor(parse_device_url(ft.url())) as sensor:
        sensor.start()
        deadline = time.monotonic() + 5.0
        with pytest.raises(SensorFault, match="status word"):
            while time.monotonic() < deadline:
                sensor.latest()
                time.sleep(0.002)
    with SimNetFt(robot, silent_after_s=0.05) as ft, open_force_sensor(parse_device_url(ft.url())) as sensor:
        sensor.start()
        first = sensor.wait_first(5.0)
        time.sleep(0.3)
        last = sensor.latest()
        time.sleep(0.2)
        assert sensor.latest() is last and last.sequence >= first.sequence   # nothing new: it went silent


def test_the_rdt_request_layout():
    assert rdt_request(RdtCommand.START_HIGH_SPEED, 0) == bytes.fromhex("1234 0002 00000000")
    assert RDT_RECORD.size == 36


def test_the_guidance_and_force_sensor_sections_of_cell_toml_round_trip():
    from elastocal.drivers.config import parse_cell_config

    text = ('[cell]\nname = "c"\nrobot = "hh150"\n[guidance]\nurl = "rsi://0.0.0.0:59152?cycle_ms=12"\n'
            'max_correction_deg = 0.1\n[force_sensor]\nurl = "netft://192.168.1.1"\nmax_age_s = 0.01\n')
    config = parse_cell_config(text)
    assert config.guidance.url.scheme == "rsi" and config.guidance.max_correction_deg == 0.1
    assert config.force_sensor.max_age_s == 0.01
    again = parse_cell_config(config.to_toml())
    assert again.guidance == config.guidance and again.force_sensor == config.force_sensor
    with pytest.raises(InputError, match="max_rate_deg_s"):
        parse_cell_config(text.replace("max_correction_deg", "max_rate_deg"))
    with pytest.raises(InputError, match="guidance.url"):
        parse_cell_config(text.replace("rsi://0.0.0.0:59152?cycle_ms=12", "modbus+tcp://127.0.0.1:502"))


@pytest.mark.parametrize("peer", [SimEgmController, SimRsiController])
def test_in_lockstep_a_slow_answer_is_waited_for_and_the_clock_advances_one_cycle(quiet_cell, peer):
    """Every answer comes after the 4 ms cycle has ended on the wall clock (the computer sleeps
    10 ms first): in lockstep the controller waits for it, applies it, and its clock advances by
    one cycle per message whatever the wall clock did; on the wall clock the same answers are late."""
    def drive(lockstep):
        robot = _guided(quiet_cell)
        with open_guidance(parse_device_url("egm://127.0.0.1:0" if peer is SimEgmController
                                            else "rsi://127.0.0.1:0"), n_joints=6) as g:
            with peer(robot, g.address, lockstep=lockstep) as sim:
                states = []
                for _ in range(12):
                    s = g.receive(timeout_s=2.0)
                    states.append(s)
                    time.sleep(0.010)
                    g.send(Q0)
                stats = sim.stats()
        return states, stats

    states, stats = drive(True)
    assert [s.controller_time_ms for s in states] == [4 * k for k in range(12)]
    assert stats.late == 0 and stats.answered >= 11
    _, stats = drive(False)
    assert stats.late > 0
