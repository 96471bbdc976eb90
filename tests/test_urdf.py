"""URDF robots: the same robot described by a URDF gives the same kinematics,
gravity, link-spring model and identification as its modified-DH table; bad
URDF input is refused in one line naming the key."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from elastocal.model.kinds import JointKind, TorqueSource

from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path, load_robot, parse_robot
from elastocal.identify.static import identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import simulate_static

DH = bundled_robot()
URDF = bundled_robot("hh150_urdf")
#: the HH-150 as URDF with joint variable theta = q + offset (the offsets stay in the [[joint]] tables)
THETA_XML = DH.to_urdf(controller_angles=False)
POSES = np.random.default_rng(11).uniform(DH.lower, DH.upper, size=(6, 6))
FRAMES = ["load_point", "flange", *DH.marker_names]


def urdf_toml(urdf_line: str, *, names=("A1", "A2", "A3", "A4", "A5", "A6"), extra_joint: str = "",
              tool_extra: str = "", load_point=(0.10, 0.0, 0.35)) -> str:
    offsets = [j.offset for j in DH.joints]
    joints = "".join(f'[[joint]]\nname = "{n}"\noffset = {o!r}\ntorque_constant = {j.torque_constant!r}\n{extra_joint}\n'
                     for n, o, j in zip(names, offsets, DH.joints))
    return (f'name = "HH-150"\n{urdf_line}\n\n{joints}[tool]\n{tool_extra}load_point = {list(load_point)}\n'
            "[tool.markers]\nR1 = [0.0, 0.0, 0.30]\nR2 = [0.15, 0.0, 0.22]\nR3 = [0.0, 0.15, 0.18]\n")


def write_urdf(tmp_path: pathlib.Path, xml: str) -> str:
    (tmp_path / "r.urdf").write_text(xml, encoding="utf-8")
    return 'urdf = "r.urdf"'


# ------------------------------------------------------------ same robot
def test_bundled_urdf_robot_reads_limits_and_masses_from_the_urdf():
    for a, b in zip(DH.joints, URDF.joints):
        assert (b.name, b.offset, b.torque_constant) == (a.name, a.offset, a.torque_constant)
        assert b.lower == pytest.approx(a.lower, abs=1e-12) and b.upper == pytest.approx(a.upper, abs=1e-12)
        assert b.mass == a.mass
        np.testing.assert_allclose(b.com, a.com, atol=1e-12)
    assert URDF.urdf is not None and URDF.urdf.path.endswith("hh150.urdf")
    assert DH.urdf is None


@pytest.mark.parametrize("q", POSES)
def test_urdf_and_dh_give_the_same_frames_jacobians_and_torques(q):
    theta = DH.theta(q)
    np.testing.assert_allclose(URDF.positions(theta, FRAMES), DH.positions(theta, FRAMES), atol=1e-12)
    np.testing.assert_allclose(URDF.jacobians(theta, FRAMES), DH.jacobians(theta, FRAMES), atol=1e-12)
    np.testing.assert_allclose(URDF.gravity_torque(theta), DH.gravity_torque(theta), atol=1e-9)
    wrench = np.array([100.0, -300.0, -1500.0, 20.0, 0.0, -10.0])
    params = DH.compensator.nominal_parameters()
    np.testing.assert_allclose(URDF.load_torque(theta, wrench, params), DH.load_torque(theta, wrench, params),
                               atol=1e-9)


@pytest.mark.parametrize("q", POSES[:3])
def test_link_spring_models_agree(q):
    theta10 = DH.theta_links(DH.theta(q), np.array([1e-3, -2e-3, 3e-3, 5e-4]))
    np.testing.assert_allclose(URDF.positions(theta10, FRAMES, links=True),
                               DH.positions(theta10, FRAMES, links=True), atol=1e-12)
    np.testing.assert_allclose(URDF.jacobians(theta10, FRAMES, links=True),
                               DH.jacobians(theta10, FRAMES, links=True), atol=1e-12)
    np.testing.assert_allclose(URDF.gravity_torque(theta10, links=True),
                               DH.gravity_torque(theta10, links=True), atol=1e-9)


def test_identification_with_the_urdf_robot_equals_the_dh_robot():
    truth = CellTruth()
    data = simulate_static(DH, truth, seed=4)
    k = [f"k{j}" for j in range(1, 7)]
    for torque in TorqueSource:
        a = identify_static(DH, data, torque=torque)
        b = identify_static(URDF, data, torque=torque)
        np.testing.assert_allclose(b.values(k), a.values(k), rtol=1e-9)
        np.testing.assert_allclose(b.stds(k), a.stds(k), rtol=1e-6)
        assert b.rms == pytest.approx(a.rms, rel=1e-9)
    assert np.all(np.abs(a.values(k)[:3] / truth.stiffness[:3] - 1) < 0.02)     # and it is right


def test_to_toml_inlines_the_urdf_so_the_description_stands_alone(tmp_path):
    text = URDF.to_toml()
    assert "urdf_xml" in text and "convention" not in text
    assert "\nalpha = " not in text and "\nd = " not in text      # no DH geometry
    again = parse_robot(text, source="again.toml")                 # no base_dir: nothing to find on disk
    assert again.urdf.xml == URDF.urdf.xml
    theta = DH.theta(POSES[0])
    np.testing.assert_allclose(again.positions(theta, FRAMES), URDF.positions(theta, FRAMES), atol=0)
    assert [j.lower for j in again.joints] == [j.lower for j in URDF.joints]


def test_awkward_urdf_text_is_inlined_as_a_basic_string():
    from dataclasses import replace

    xml = URDF.urdf.xml.replace('<robot name="HH-150">', '<robot name="HH-150">\n<!-- \'\'\' a \\ b \x01 -->')
    awkward = replace(URDF, urdf=replace(URDF.urdf, xml=xml))
    text = awkward.to_toml()
    assert 'urdf_xml = "' in text                      # a one-line TOML basic string, escaped
    assert parse_robot(text, source="again.toml").urdf.xml == xml


def test_dh_robot_written_as_urdf_reads_back_the_same():
    xml = THETA_XML
    assert xml.count('type="revolute"') == 6 and 'name="A6"' in xml
    robot = parse_robot(urdf_toml(f"urdf_xml = '''\n{xml}'''"))
    theta = DH.theta(POSES[1])
    np.testing.assert_allclose(robot.positions(theta, FRAMES), DH.positions(theta, FRAMES), atol=1e-12)


# ------------------------------------------------- what URDFs really hold
def test_fixed_links_a_flange_frame_a_flipped_axis_and_extra_joints(tmp_path):
    """A URDF as vendors write them: a tool0 frame beyond the last joint, the
    first joint's axis along -z, and a gripper joint the tables do not name
    (locked at zero)."""
    xml = THETA_XML
    xml = xml.replace('<joint name="A1" type="revolute">', '<joint name="A1" type="revolute">', 1)
    head, rest = xml.split('<joint name="A1"', 1)
    first, tail = rest.split("</joint>", 1)
    first = first.replace('<axis xyz="0.0 0.0 1.0"/>', '<axis xyz="0 0 -1"/>')
    first = first.replace('lower="-3.2289" upper="3.2289"', 'lower="-3.2289" upper="3.2289"')
    xml = head + '<joint name="A1"' + first + "</joint>" + tail
    extra = ('  <link name="tool0"><inertial><origin xyz="0 0 0.05"/><mass value="5.0"/>'
             '<inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>\n'
             '  <joint name="flange_to_tool0" type="fixed"><parent link="link6"/><child link="tool0"/>'
             '<origin xyz="0 0 0.1" rpy="0 0 0"/></joint>\n'
             '  <link name="finger"/>\n'
             '  <joint name="gripper" type="prismatic"><parent link="tool0"/><child link="finger"/>'
             '<axis xyz="1 0 0"/><limit lower="0" upper="0.05" effort="1" velocity="1"/></joint>\n</robot>')
    xml = xml.replace("</robot>", extra)
    line = write_urdf(tmp_path, xml)
    toml = urdf_toml(line, tool_extra='flange = "tool0"\n', load_point=(0.10, 0.0, 0.25))
    toml = toml.replace("R1 = [0.0, 0.0, 0.30]", "R1 = [0.0, 0.0, 0.20]") \
               .replace("R2 = [0.15, 0.0, 0.22]", "R2 = [0.15, 0.0, 0.12]") \
               .replace("R3 = [0.0, 0.15, 0.18]", "R3 = [0.0, 0.15, 0.08]")
    (tmp_path / "robot.toml").write_text(toml, encoding="utf-8")
    robot = load_robot(tmp_path / "robot.toml")
    assert robot.joints[5].mass == pytest.approx(20.0)        # link6 and the merged tool0
    for q in POSES[:3]:
        theta = DH.theta(q)
        flipped = theta.copy()
        flipped[0] = -theta[0]                                 # -z axis: the same motion for -theta1
        frames = ["load_point", *DH.marker_names]
        np.testing.assert_allclose(robot.positions(flipped, frames), DH.positions(theta, frames), atol=1e-12)
        flange = robot.positions(flipped, ["flange"])[0] - DH.positions(theta, ["flange"])[0]
        assert np.linalg.norm(flange) == pytest.approx(0.1, abs=1e-12)


def test_continuous_joint_needs_limits_in_the_table(tmp_path):
    xml = THETA_XML.replace('<joint name="A4" type="revolute">', '<joint name="A4" type="continuous">')
    line = write_urdf(tmp_path, xml)
    with pytest.raises(InputError, match=r"joint\[4\]\.lower.*continuous"):
        parse_robot(urdf_toml(line), base_dir=tmp_path)
    text = urdf_toml(line).replace('name = "A4"\n', 'name = "A4"\nlower = -6.0\nupper = 6.0\n')
    robot = parse_robot(text, base_dir=tmp_path)
    assert (robot.joints[3].lower, robot.joints[3].upper) == (-6.0, 6.0)
    theta = DH.theta(POSES[2])
    np.testing.assert_allclose(robot.positions(theta, FRAMES), DH.positions(theta, FRAMES), atol=1e-12)


# ---------------------------------------------------------------- errors
@pytest.mark.parametrize("mutate, match", [
    (lambda t: t.replace('name = "A3"', 'name = "A9"'), r"joint\.name.*no joint 'A9'.*A1, A2, A3"),
    (lambda t: t.replace('name = "A3"', 'name = "A2"', 1).replace('name = "A2"', 'name = "A3"', 1),
     r"joint\.name.*serial chain"),
    (lambda t: t.replace('name = "A5"', 'name = "A5"\na = 0.1'), r"joint\[5\]\.a.*geometry from the URDF"),
    (lambda t: t.replace('name = "A5"\n', ''), r"joint\[5\]\.name.*name of its URDF joint"),
    (lambda t: "convention = \"modified-dh\"\n" + t, r"convention.*no DH convention"),
    (lambda t: t.replace("[tool]\n", '[tool]\nflange = "link3"\n'), r"tool\.flange.*does not move with"),
    (lambda t: t.replace("[tool]\n", '[tool]\nflange = "nowhere"\n'), r"tool\.flange.*no link or frame"),
    (lambda t: t.replace('urdf = "r.urdf"', 'urdf = "missing.urdf"'), r"urdf.*cannot read URDF"),
    (lambda t: t.replace('urdf = "r.urdf"', 'urdf = "r.urdf"\nurdf_xml = "<robot/>"'), r"urdf_xml.*not both"),
    (lambda t: t.replace('urdf = "r.urdf"', 'urdf_xml = "<robot name=\\"x\\"><link"'), r"urdf.*not a valid URDF"),
])
def test_bad_urdf_robots_are_one_line_errors_naming_the_key(tmp_path, mutate, match):
    text = mutate(urdf_toml(write_urdf(tmp_path, THETA_XML)))
    with pytest.raises(InputError, match=match) as err:
        parse_robot(text, source="robot.toml", base_dir=tmp_path)
    assert "\n" not in str(err.value) and "robot.toml" in str(err.value)


def test_a_prismatic_urdf_joint_slides_and_a_planar_one_is_refused(tmp_path):
    xml = THETA_XML.replace('<joint name="A6" type="revolute">', '<joint name="A6" type="prismatic">')
    robot = parse_robot(urdf_toml(write_urdf(tmp_path, xml)), base_dir=tmp_path)
    assert robot.joint_kinds[5] is JointKind.PRISMATIC and robot.joint_kinds[4] is JointKind.REVOLUTE
    theta = DH.theta(POSES[1])
    moved = theta.copy()
    moved[5] += 0.01          # metres now: every marker slides 1 cm along the last axis
    axis = robot.jacobians(theta, ["R1"])[0][:3, 5]
    np.testing.assert_allclose(robot.positions(moved, FRAMES) - robot.positions(theta, FRAMES),
                               np.tile(0.01 * axis, (len(FRAMES), 1)), atol=1e-12)
    assert np.linalg.norm(axis) == pytest.approx(1.0)
    planar = THETA_XML.replace('<joint name="A6" type="revolute">', '<joint name="A6" type="planar">')
    with pytest.raises(InputError, match=r"'A6'.*neither revolute nor prismatic"):
        parse_robot(urdf_toml(write_urdf(tmp_path, planar)), base_dir=tmp_path)


def test_a_dh_robot_cannot_name_a_flange():
    text = bundled_robot_path().read_text().replace("[tool]\n", '[tool]\nflange = "tool0"\n')
    with pytest.raises(InputError, match=r"tool\.flange.*only a URDF robot"):
        parse_robot(text)


def test_the_cli_identifies_with_a_urdf_robot(tmp_path, capsys):
    import json

    from elastocal.cli import main

    assert main(["sim", "static", "--seed", "2", "--out", str(tmp_path / "s")]) == 0
    capsys.readouterr()
    robot = bundled_robot_path("hh150_urdf")
    assert main(["identify", "--robot", str(robot), "--static", str(tmp_path / "s" / "static.csv"), "--json"]) == 0
    via_urdf = json.loads(capsys.readouterr().out)
    assert main(["identify", "--robot", str(tmp_path / "s" / "robot.toml"), "--static",
                 str(tmp_path / "s" / "static.csv"), "--json"]) == 0
    via_dh = json.loads(capsys.readouterr().out)
    assert via_urdf["parameters"].keys() == via_dh["parameters"].keys()
    for name, p in via_dh["parameters"].items():
        assert via_urdf["parameters"][name]["value"] == pytest.approx(p["value"], rel=1e-9)
        assert via_urdf["parameters"][name]["std"] == pytest.approx(p["std"], rel=1e-6)


def test_a_calibration_log_keeps_the_urdf_inline():
    from elastocal.acquisition.procedures import log_robot_text

    text = log_robot_text(URDF, bundled_robot_path("hh150_urdf"))
    again = parse_robot(text, source="log")               # read back with no file beside it
    assert again.urdf.xml == URDF.urdf.xml and not again.urdf.path
    # a DH robot's file goes into the log as written, comments and all
    assert log_robot_text(DH, bundled_robot_path()) == bundled_robot_path().read_text(encoding="utf-8")
