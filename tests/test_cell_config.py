"""cell.toml: device URLs and the frozen, validated configuration."""

from __future__ import annotations

import dataclasses

import pytest

from elastocal.drivers.config import load_cell_config, parse_cell_config
from elastocal.drivers.urls import parse_device_url
from elastocal.errors import InputError
from elastocal.sims.config import sim_config
from elastocal.sims.serve import example_cell_config, example_cell_path

MINIMAL = """
[cell]
name = "c"
robot = "hh150"
"""


def test_the_urls_of_the_architecture():
    u = parse_device_url("canopen://virtual/cell?node=5")
    assert (u.scheme, u.can_interface, u.can_channel, u.param("node")) == ("canopen", "virtual", "cell", "5")
    u = parse_device_url("modbus+tcp://127.0.0.1:1502?unit=1")
    assert (u.host, u.port, u.int_param("unit", 0)) == ("127.0.0.1", 1502, 1)
    u = parse_device_url("modbus+rtu:///dev/pts/3?baud=115200&unit=1")
    assert (u.path, u.int_param("baud", 0), u.int_param("unit", 0)) == ("/dev/pts/3", 115200, 1)
    u = parse_device_url("tracker+tcp://127.0.0.1:7000")
    assert (u.host, u.port) == ("127.0.0.1", 7000)
    u = parse_device_url("tracker+serial:///dev/ttyUSB0?baud=115200")
    assert u.path == "/dev/ttyUSB0"
    assert parse_device_url("modbus+tcp://127.0.0.1:0?unit=2").with_port(1503).text == \
        "modbus+tcp://127.0.0.1:1503?unit=2"


@pytest.mark.parametrize("url,message", [
    ("http://x", "unknown device scheme 'http'"),
    ("canopen://virtual/cell", "node id is missing"),
    ("canopen://virtual/cell?node=200", "outside 1..127"),
    ("canopen://virtual?node=1", "give the CAN channel"),
    ("modbus+tcp://127.0.0.1?unit=1", "give host and port"),
    ("modbus+tcp://127.0.0.1:502?unit=x", "not an integer"),
    ("tracker+serial://?baud=9600", "give the serial device"),
    ("127.0.0.1:502", "expected a device URL"),
])
def test_bad_urls_are_named(url, message):
    with pytest.raises(InputError, match=message):
        parse_device_url(url)


def test_packaged_simulated_cell_round_trips():
    c = example_cell_config()
    assert [d.joint for d in c.drives] == [1, 2, 3, 4, 5, 6]
    assert c.drive(3).url.text == "canopen://virtual/elastocal-sim?node=3"
    assert c.tracker.markers == ("R1", "R2", "R3") and c.controller.pose(2)[0] == 0.5
    assert c.controller.path(2).u[1] == -0.3 and sim_config(c).seed == 7
    again = parse_cell_config(c.to_toml(), source="again.toml")
    for field in ("name", "robot", "drives", "tracker", "controller", "sim"):
        assert getattr(again, field) == getattr(c, field), field
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.name = "x"
    assert c.load_robot().name == "HH-150"
    assert load_cell_config(example_cell_path()).drives == c.drives


def test_the_packaged_track_cell_has_a_drive_per_joint_and_other_ns_are_refused():
    """The seven-joint cell (the HH-150 on a track): seven drives, seven-value poses; a drive or a
    taught pose that does not fit the robot's N is refused naming its key."""
    c = example_cell_config(robot="hh150_track")
    assert [d.joint for d in c.drives] == list(range(1, 8)) and c.load_robot().n_joints == 7
    assert len(c.controller.pose(1)) == 7 and sim_config(c).start_q[0] == 3.0
    six = dataclasses.replace(c, robot="hh150")
    with pytest.raises(InputError, match=r"joint 7: the robot 'HH-150' has joints 1\.\.6") as err:
        six.load_robot()
    assert err.value.column == "drive[7].joint"
    six = dataclasses.replace(six, drives=c.drives[:6])
    with pytest.raises(InputError, match=r"7 joint values; the robot 'HH-150' has 6 joints"):
        six.load_robot()


def test_relative_paths_resolve_next_to_the_file(tmp_path):
    robot = tmp_path / "robots" / "r.toml"
    robot.parent.mkdir()
    robot.write_text(example_cell_config().robot_path().read_text())
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nname = "c"\nrobot = "robots/r.toml"\nhistory = "hist.sqlite"\n')
    c = load_cell_config(cell)
    assert c.robot_path() == robot and c.history == tmp_path / "hist.sqlite"
    assert parse_cell_config(c.to_toml()).robot_path() == robot.resolve()


@pytest.mark.parametrize("extra,column,message", [
    ('[[drive]]\njoint = 0\nurl = "canopen://virtual/c?node=1"', "drive[1].joint", "joint must be 1..N"),
    ('[[drive]]\njoint = 1\nurl = "tracker+tcp://127.0.0.1:1"', None, "cannot be used here"),
    ('[[drive]]\njoint = 1\nurl = "canopen://virtual/c?node=1"\n[[drive]]\njoint = 1\n'
     'url = "canopen://virtual/c?node=2"', "drive", "joints repeat"),
    ('[[drive]]\njoint = 1\nurl = "canopen://virtual/c?node=1"\n[[drive]]\njoint = 2\n'
     'url = "canopen://virtual/c?node=1"', "drive", "same CAN node 1"),
    ('[[drive]]\njoint = 1\nurl = "modbus+tcp://127.0.0.1:1502"', "drive[1].registers", "needs a"),
    ('[[drive]]\njoint = 1\nurl = "modbus+tcp://127.0.0.1:1502"\n[drive.registers]\n'
     'current = { address = 0, unit = "rad" }\nposition = { address = 1, unit = "rad" }',
     "drive[1].registers.current", "not a unit of current"),
    ('[[drive]]\njoint = 1\nurl = "modbus+tcp://127.0.0.1:1502"\n[drive.registers]\n'
     'current = { address = 0, type = "int32", unit = "A" }\nposition = { address = 1, unit = "rad" }',
     "drive[1].registers.position", "register 1 is used by both current and position"),
    ('[[drive]]\njoint = 1\nurl = "modbus+tcp://127.0.0.1:1502"\n[drive.registers]\n'
     'current = { address = 0, unit = "A" }', "drive[1].registers", "missing the position register"),
    ('[tracker]\nurl = "tracker+tcp://127.0.0.1:7000"', "tracker.markers", "non-empty list"),
    ('[controller]\nurl = "modbus+tcp://127.0.0.1:1503"\n[controller.registers]\n'
     'command = { address = 0, access = "write" }', "controller.registers", "missing the sequence register"),
    ('[controller]\nurl = "modbus+tcp://127.0.0.1:1503"\n[controller.registers]\n'
     'status = { address = 0, access = "write" }', "controller.registers.status", "elastocal only reads it"),
])
def test_config_errors_name_the_file_and_key(extra, column, message):
    with pytest.raises(InputError, match=message) as err:
        parse_cell_config(MINIMAL + extra, source="cell.toml")
    assert "cell.toml" in str(err.value)
    if column is not None:
        assert err.value.column == column


@pytest.mark.parametrize("extra,column,message", [
    ('[sim]\nhidden = "gremlins"', "sim.hidden", "hidden must be one of"),
    ('[sim]\nstart_q = []', "sim.start_q", "expected one per joint: finite numbers"),
    ('[sim]\nseeed = 1', "sim.seeed", "unknown key seeed \\(did you mean seed\\?\\)"),
])
def test_sim_section_errors_name_the_file_and_key(extra, column, message):
    """The [sim] table belongs to the simulated cell: it is validated when the cell is simulated."""
    config = parse_cell_config(MINIMAL + extra, source="cell.toml")
    with pytest.raises(InputError, match=message) as err:
        sim_config(config)
    assert "cell.toml" in str(err.value) and err.value.column == column


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        load_cell_config(tmp_path / "none.toml")
    with pytest.raises(InputError, match="not valid TOML"):
        parse_cell_config("[cell", source="x.toml")
    with pytest.raises(InputError, match="missing robot"):
        parse_cell_config("[cell]\nname = 'x'\n")


def test_tracker_position_is_optional_validated_and_round_trips():
    text = example_cell_path().read_text()
    assert example_cell_config().tracker.base_p_tracker is None
    placed = text.replace('rate_hz = 100.0', 'rate_hz = 100.0\nbase_p_tracker = [3.5, 0.0, 1.2]', 1)
    cfg = parse_cell_config(placed, source="cell.toml", base_dir=example_cell_path().parent)
    assert cfg.tracker.base_p_tracker == (3.5, 0.0, 1.2)
    again = parse_cell_config(cfg.to_toml(), source="again.toml", base_dir=example_cell_path().parent)
    assert again.tracker.base_p_tracker == (3.5, 0.0, 1.2)
    bad = text.replace('rate_hz = 100.0', 'rate_hz = 100.0\nbase_p_tracker = [3.5, 0.0]', 1)
    with pytest.raises(InputError, match=r"cell.toml, column tracker.base_p_tracker: expected 3 finite numbers"):
        parse_cell_config(bad, source="cell.toml", base_dir=example_cell_path().parent)


def test_the_cells_plan_is_optional_resolves_next_to_the_file_and_round_trips(tmp_path):
    text = example_cell_path().read_text()
    assert parse_cell_config(text).plan is None
    cfg = parse_cell_config(text.replace("[cell]\n", '[cell]\nplan = "plans/cal.toml"\n', 1),
                            source="cell.toml", base_dir=tmp_path)
    assert cfg.plan == tmp_path / "plans" / "cal.toml"
    assert parse_cell_config(cfg.to_toml()).plan == (tmp_path / "plans" / "cal.toml").resolve()
    with pytest.raises(InputError, match=r"cell\.plan.*path of a plan\.toml"):
        parse_cell_config(text.replace("[cell]\n", "[cell]\nplan = 3\n", 1), source="cell.toml")
