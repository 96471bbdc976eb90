"""The simulated cell as a whole: SimulatedCell, `elastocal devices`, `elastocal sim serve`."""

from __future__ import annotations

import json
import threading
import uuid

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.drivers import open_cell
from elastocal.drivers.config import load_cell_config, parse_cell_config
from elastocal.sims.serve import SimulatedCell, example_cell_config

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow

SERIAL_CELL = """
[cell]
name = "serial cell"
robot = "hh150"

[[drive]]
joint = 1
url = "modbus+rtu:///dev/simulated?baud=115200&unit=1"
[drive.registers]
current  = { address = 0, type = "float32", unit = "A" }
position = { address = 2, type = "int32", scale = 1e-6, unit = "rad" }

[[drive]]
joint = 2
url = "modbus+rtu:///dev/simulated?baud=115200&unit=2"
[drive.registers]
current  = { address = 0, type = "float32", unit = "A" }
position = { address = 2, type = "int32", scale = 1e-6, unit = "rad" }

[[drive]]
joint = 3
url = "canopen://virtual/CHANNEL?node=3"

[tracker]
url = "tracker+serial:///dev/simulated-tracker?baud=115200"
markers = ["R1"]

[sim]
current_noise_a = 0.0
tracker_noise_m = 0.0
"""


def channel() -> str:
    return f"test-{uuid.uuid4().hex[:8]}"


def test_simulated_cell_resolves_urls_and_stops_everything():
    before = set(threading.enumerate())
    with SimulatedCell(example_cell_config(can_channel=channel(), move_speed_rad_s=5.0)) as sim:
        urls = sim.urls
        assert ":0" not in urls["tracker"] and ":0?" not in urls["controller"]
        with open_cell(sim.config) as cell:
            assert [d.identify().kind for d in cell.devices()] == ["drive"] * 6 + ["tracker", "controller"]
            cell.controller.move_to_pose(2)
            q = np.array([cell.drives[j].read().position_rad for j in range(1, 7)])
            np.testing.assert_allclose(q, sim.config.controller.pose(2), atol=1e-7)
            sim.world.set_load([0.0, 0.0, -2000.0, 0.0, 0.0, 0.0])
            eq = sim.world.equilibrium_at()
            p = cell.tracker.measure().tracker_p_marker
            np.testing.assert_allclose(p, sim.world.cell.tracker_positions(eq, ["R1"])[0], atol=1e-4)
            with cell.drives[1].stream(500.0) as s:
                assert s.read_for(0.2).samples
        assert sim.can_stats()[f"virtual/{sim.config.drives[0].url.can_channel}"].frames > 0
    leaked = [t for t in set(threading.enumerate()) - before if t.is_alive()]
    assert not leaked, leaked


def test_serial_devices_get_pty_paths():
    cfg = parse_cell_config(SERIAL_CELL.replace("CHANNEL", channel()), source="serial.toml")
    with SimulatedCell(cfg) as sim:
        d1, d2 = sim.config.drive(1).url, sim.config.drive(2).url
        assert d1.path == d2.path and d1.path.startswith("/dev/pts/")     # one RS-485 line, two units
        assert sim.config.tracker.url.path.startswith("/dev/pts/")
        with open_cell(sim.config) as cell:
            assert cell.drives[2].read().position_rad == pytest.approx(0.2, abs=1e-6)
            assert cell.drives[1].read().position_rad == pytest.approx(0.0, abs=1e-6)
            assert cell.drives[3].read().position_rad == pytest.approx(-0.4, abs=1e-7)
            eq = sim.world.equilibrium_at()
            np.testing.assert_allclose(cell.tracker.measure().tracker_p_marker,
                                       sim.world.cell.tracker_positions(eq, ["R1"])[0], atol=1e-9)


def test_devices_command_identifies_and_streams(tmp_path, capsys):
    with SimulatedCell(example_cell_config(can_channel=channel())) as sim:
        cell = tmp_path / "cell.toml"
        cell.write_text(sim.config.to_toml())
        assert main(["devices", "--cell", str(cell), "--json", "--duration", "0.6"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert [d["name"] for d in out["devices"]] == [f"drive J{j}" for j in range(1, 7)] + ["tracker", "controller"]
        streams = {s["device"]: s for s in out["streams"]}
        assert streams["drive J2"]["received"] > 0.5 * 0.6 * sim.config.drive(2).rate_hz
        assert streams["tracker"]["received"] > 20
        assert streams["drive J2"]["expected"] == streams["drive J2"]["received"] + streams["drive J2"]["missing"]
        assert streams["drive J2"]["last"]["position_rad"] == pytest.approx(0.2, abs=1e-7)
        assert main(["devices", "--cell", str(cell), "--identify-only"]) == 0
        text = capsys.readouterr().out
        assert "elastocal SimTracker serial SIM0001" in text and "state: operation enabled" in text
        sim.tracker.close()                      # the tracker goes away
        assert main(["devices", "--cell", str(cell), "--identify-only"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "DeviceDisconnected" in err[0] and "cannot connect" in err[0]


def test_devices_command_bad_input(tmp_path, capsys):
    assert main(["devices", "--cell", str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml: cannot read" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('[cell]\nrobot = "hh150"\n[[drive]]\njoint = 1\nurl = "canopen://virtual/x"\n')
    assert main(["devices", "--cell", str(bad)]) == 2
    assert "node id is missing" in capsys.readouterr().err


def test_sim_serve_writes_the_resolved_cell(tmp_path, capsys):
    cfg = example_cell_config(can_channel=channel())
    src = tmp_path / "cell.toml"
    src.write_text(cfg.to_toml())
    out = tmp_path / "resolved.toml"
    assert main(["sim", "serve", "--cell", str(src), "--can", "as-configured", "--duration", "0.3",
                 "--write-cell", str(out), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    resolved = load_cell_config(out)
    assert printed["urls"]["tracker"] == resolved.tracker.url.text
    assert resolved.controller.url.port != 0 and resolved.drive(1).url.can_interface == "virtual"
