"""The emScon backend's own behaviour: CESAPI packets on the wire, units, reflectors per
marker, no target, initialisation, garbled packets, the weather (the interface's contract
is tests/test_drivers_tracker.py, run against both backends)."""

import socket
import subprocess
import sys

import numpy as np
import pytest
from CESAPI import packet as es

from elastocal.drivers import open_tracker
from elastocal.drivers.config import TrackerConfig
from elastocal.drivers.urls import parse_device_url
from elastocal.sims.config import SimConfig
from elastocal.drivers.emscon_packets import PacketSocket, decode
from elastocal.errors import DeviceFault, InputError, ProtocolError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.emscon_server import SimEmscon
from elastocal.sims.world import SimWorld

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

MARKERS = ("R1", "R2", "R3")


@pytest.fixture(scope="module")
def world():
    return SimWorld.from_config(bundled_robot(), SimConfig(tracker_noise_m=0.0, seed=2), MARKERS)


@pytest.fixture
def sim(world):
    s = SimEmscon(world)
    s.serve_tcp()
    yield s
    s.close()


def open_emscon(sim, query="", **kw):
    url = parse_device_url(f"tracker+emscon://127.0.0.1:{sim.tcp_port}{query}")
    return open_tracker(TrackerConfig(url=url, markers=MARKERS, timeout_s=kw.pop("timeout_s", 0.3),
                                      retries=kw.pop("retries", 2)))


def test_importing_the_backend_leaves_logging_alone():
    code = ("import logging, sys; import elastocal.drivers.emscon, elastocal.sims.emscon_server; "
            "assert not logging.getLogger().handlers, logging.getLogger().handlers; "
            "assert 'CESAPI.connection' not in sys.modules and 'CESAPI.command' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_cesapi_packets_on_the_wire(sim, world):
    # a command as emScon defines it: lPacketSize, type (ES_DT_Command), command (ES_C_StartMeasurement)
    assert es.StartMeasurementCT().pack() == bytes.fromhex("0c000000" "00000000" "31000000")
    with socket.create_connection(("127.0.0.1", sim.tcp_port), timeout=2.0) as raw:
        link = PacketSocket(raw, "test", answers=True)
        link.send(es.GetSystemStatusCT())
        status = link.receive(2.0)
        assert isinstance(status, es.GetSystemStatusRT) and status.trackerProcessorStatus == es.ES_TPS_Initialized
        units = es.SetUnitsCT()
        units.unitsSettings.lenUnitType = es.ES_LU_Millimeter
        link.send(units)
        assert link.receive(2.0).packetInfo.status == es.ES_RS_AllOK
        link.send(es.StartMeasurementCT())
        answer, result = link.receive(2.0), link.receive(2.0)
        assert isinstance(answer, es.StartMeasurementRT) and isinstance(result, es.SingleMeasResultT)
        truth = world.cell.tracker_positions(world.equilibrium_at(), ["R1"])[0]
        np.testing.assert_allclose([result.dVal1, result.dVal2, result.dVal3], truth * 1e3, atol=1e-6)
        assert (result.dTemperature, result.dPressure, result.dHumidity) == (20.5, 1013.25, 45.0)
    with pytest.raises(ProtocolError, match="says 99 bytes"):
        decode(bytes.fromhex("63000000" "00000000" "31000000"), answers=False)


def test_units_reflectors_and_weather(sim, world):
    t = open_emscon(sim, "?reflector.R3=CCR-1.5in")
    try:
        info = t.identify()
        assert dict(info.details)["reflectors"] == "R1: R1, R2: R2, R3: CCR-1.5in"
        t.select("R2")
        s = t.measure()
        truth = world.cell.tracker_positions(world.equilibrium_at(), ["R2"])[0]
        np.testing.assert_allclose(s.tracker_p_marker, truth, atol=1e-9)        # metres, whatever was set before
        env = dict(s.environment)
        assert env["temperature_c"] == 20.5 and env["humidity_pct"] == 45.0
        n_before = env["ifm_refraction_index"]
        sim.set_environment(26.0, 990.0, 60.0)          # the weather station reports new values
        env = dict(t.measure().environment)
        assert (env["temperature_c"], env["pressure_hpa"]) == (26.0, 990.0)
        assert env["ifm_refraction_index"] < n_before                 # warmer, lower pressure: thinner air
        assert t.environment()["pressure_hpa"] == 990.0
    finally:
        t.close()
    with pytest.raises(InputError, match="no reflector 'RRR-9'.*1 'R1'"):
        open_emscon(sim, "?reflector=RRR-9")


def test_no_target_is_a_gap_and_a_fault(sim):
    t = open_emscon(sim)
    try:
        sim.lose_target(None)
        with pytest.raises(DeviceFault, match="no target.*ES_RS_NoStationaryResult"):
            t.measure()
        sim.restore_beam()
        with t.stream(100.0) as stream:
            before = stream.read_for(0.1)
            sim.lose_target(0.1)
            after = stream.read_for(0.3)
        gaps = before.gaps + after.gaps
        assert [g.reason for g in gaps if g.reason != "request could not be sent on time"] == ["no target"]
        assert sum(g.missing for g in gaps if g.reason == "no target") == pytest.approx(10, abs=3)
    finally:
        t.close()


def test_initialisation(world):
    sim = SimEmscon(world, initialized=False)
    sim.serve_tcp()
    try:
        with pytest.raises(DeviceFault, match="not initialised"):
            open_emscon(sim, "?initialize=0")
        assert not sim.initialized
        t = open_emscon(sim)                    # initialises it
        try:
            assert sim.initialized
            t.measure()
            sim.uninitialise()                  # e.g. the sensor was power-cycled
            with pytest.raises(DeviceFault, match="not initialised.*ES_RS_TrackerNotInitialized"):
                t.measure()
        finally:
            t.close()
    finally:
        sim.close()


def test_garbled_packets_reconnect(sim):
    t = open_emscon(sim, timeout_s=1.0)     # no timeout (and its reconnect) on a loaded machine
    try:
        sim.corrupt_packets(1)
        t.measure()                                     # retried on a fresh connection
        assert sim.connections == 2
        with t.stream(100.0) as stream:
            stream.read_for(0.05)
            sim.corrupt_packets(2)
            batch = stream.read_for(0.2)
        assert sum(g.missing for g in batch.gaps if g.reason == "malformed packet") == 2
        assert sim.connections == 4
        with pytest.raises(InputError, match="maximum data rate 1000 Hz"):
            t.stream(2000.0)
    finally:
        t.close()
