"""The robot model of the bottom layer is any serial chain: N joints, revolute or prismatic,
from a modified-DH table or a URDF chain between base_link and tip_link (docs/formats.md §1).

Each check is against first principles (a prismatic joint moves its child along its axis by
exactly the change of q; a URDF read by Pinocchio's parser and by elastocal give the same
frames), not against elastocal's own earlier output.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pinocchio as pin
import pytest

from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path, parse_robot
from elastocal.model.effects import get_effect
from elastocal.model.kinds import JointKind
from jacobian_check import assert_jacobian_is_the_differences

#: the carriage of a floor track: a prismatic joint along the base's y axis (Rx(-90 deg) turns z onto y)
CARRIAGE = """[[joint]]
name = "T1"
type = "prismatic"
a = 0.0
alpha = -1.5707963267948966
theta = 0.0
lower = 0.0
upper = 6.0
torque_constant = 1200.0
mass = 300.0
com = [0.0, 0.0, 0.0]

"""


def track_robot_text() -> str:
    """The HH-150 of the bundled table on a floor track (seven joints): the carriage first,
    then the six-axis arm, its first axis turned back to vertical (alpha 90 deg), the
    compensator on what is now joint 3."""
    text = bundled_robot_path().read_text(encoding="utf-8").replace('name = "HH-150"', 'name = "HH-150 on a track"')
    first = text.index("[[joint]]")
    arm = text[first:].replace("alpha = 0.0", "alpha = 1.5707963267948966", 1)
    arm = re.sub(r"(\[compensator\][^\[]*?)joint = 2", r"\1joint = 3", arm)
    return text[:first] + CARRIAGE + arm


TRACK_ROBOT = track_robot_text()


@pytest.fixture(scope="module")
def track():
    return parse_robot(TRACK_ROBOT, source="track.toml")


def test_a_prismatic_joint_moves_the_tool_along_its_axis_by_the_change_of_q(track):
    assert track.n_joints == 7 and track.joint_kinds[0] is JointKind.PRISMATIC
    q = np.array([1.0, 0.3, 0.2, -0.4, 0.5, 0.6, -0.7])
    p0 = track.positions(track.theta(q), ["R1", "R2"])
    q1 = q.copy()
    q1[0] += 0.137
    p1 = track.positions(track.theta(q1), ["R1", "R2"])
    # the carriage's axis is the base's y axis (Rx(-90 deg) turns z onto y): every point moves by 0.137 m along y
    np.testing.assert_allclose(p1 - p0, np.tile([0.0, 0.137, 0.0], (2, 1)), atol=1e-12)
    jac = track.jacobians(track.theta(q), ["R1"])[0]
    np.testing.assert_allclose(jac[:, 0], [0.0, 1.0, 0.0, 0.0, 0.0, 0.0], atol=1e-12)


def test_the_arm_on_the_track_is_the_six_axis_arm_shifted(track):
    """With the carriage at 0, the track robot's arm is the HH-150 of the same table standing on it."""
    hh = bundled_robot()
    q6 = np.array([0.3, 0.2, -0.4, 0.5, 0.6, -0.7])
    p_track = track.positions(track.theta(np.r_[0.0, q6]), ["R1"])
    p_arm = hh.positions(hh.theta(q6), ["R1"])
    np.testing.assert_allclose(p_track, p_arm, atol=1e-12)


def test_gravity_loads_the_carriage_only_along_its_axis(track):
    """Gravity is vertical and the track horizontal: the carriage carries no weight along its axis."""
    g = track.gravity_torque(track.theta(np.array([2.0, 0.3, 0.2, -0.4, 0.5, 0.6, -0.7])))
    assert abs(g[0]) < 1e-9
    assert abs(g[2]) > 1.0          # the shoulder does carry the arm


def test_prismatic_and_revolute_units_follow_the_joint(track):
    k = get_effect("joint_stiffness", track)
    assert k.parameters == tuple(f"c{j}" for j in range(1, 8))
    assert k.report_units[0] == "N/m" and set(k.report_units[1:]) == {"N*m/rad"}
    fc = get_effect("coulomb_friction", track)
    assert fc.parameters[-1] == "fc7" and fc.units[:2] == ("N", "N*m")
    lc = get_effect("link_compliance", track)
    assert lc.parameters[-1] == "cl6y" and len(lc.parameters) == 14
    assert get_effect("joint_stiffness").parameters == tuple(f"c{j}" for j in range(1, 7))


def test_the_link_springs_sit_at_the_two_longest_links(track):
    assert bundled_robot().spring_links == (2, 3)
    # on the track, the HH-150's links 2 and 3 are links 3 and 4
    assert track.spring_links == (3, 4)
    assert track.link_spring_names == ("cl3x", "cl3y", "cl4x", "cl4y")
    assert track.link_model.nq == 11


def test_the_compensator_acts_on_the_joint_it_names(track):
    theta = track.theta(np.array([0.0, 0.0, 0.1, 0.0, 0.5, 0.0, 0.0]))
    with_comp = track.load_torque(theta, None, (4771.4, 0.9112), gravity=False)
    assert np.count_nonzero(with_comp) == 1 and with_comp[2] != 0.0


def test_the_description_round_trips(track):
    again = parse_robot(track.to_toml(), source="again.toml")
    q = np.array([0.5, 0.3, 0.2, -0.4, 0.5, 0.6, -0.7])
    np.testing.assert_allclose(again.positions(again.theta(q), ["R1", "R2"]),
                               track.positions(track.theta(q), ["R1", "R2"]), atol=1e-12)
    assert again.joint_kinds == track.joint_kinds and again.compensator.joint == 3


@pytest.mark.parametrize("change,message", [
    (lambda t: t.replace('type = "prismatic"', 'type = "helical"'), r"joint\[1\]\.type.*revolute.*prismatic"),
    (lambda t: t.replace("theta = 0.0\n", "theta = 0.0\nd = 0.1\n", 1), r"joint\[1\]\.d.*prismatic joint's d is its"),
    (lambda t: t.replace("upper = 6.0\n", "upper = 6000.0\n"), r"joint\[1\].*millimetres"),
    (lambda t: t.replace('alpha = 1.5707963267948966\n', 'alpha = 1.5707963267948966\ntheta = 0.2\n', 1),
     r"joint\[2\]\.theta.*revolute joint's theta is its variable"),
    (lambda t: t.replace("joint = 3\n", "joint = 1\n"), r"compensator.joint.*not a revolute joint"),
    (lambda t: t.replace("joint = 3\n", "joint = 9\n"), r"compensator.joint.*1\.\.7"),
])
def test_bad_chains_are_refused_by_key(change, message):
    with pytest.raises(InputError, match=message):
        parse_robot(change(TRACK_ROBOT), source="track.toml")


def test_currents_need_a_torque_constant_per_joint():
    robot = parse_robot(TRACK_ROBOT.replace("torque_constant = 1200.0\n", ""), source="track.toml")
    assert not robot.has_torque_constants
    with pytest.raises(InputError, match=r"joint\[1\]\.torque_constant.*joint 1"):
        robot.torque_constants   # noqa: B018 - the property raises


def test_robot_data_is_owned_by_the_caller(track):
    data = track.create_data()
    q = track.theta(np.array([0.5, 0.3, 0.2, -0.4, 0.5, 0.6, -0.7]))
    np.testing.assert_array_equal(track.positions(q, ["R1"], data=data), track.positions(q, ["R1"]))
    np.testing.assert_array_equal(track.jacobians(q, ["R1"], data=data), track.jacobians(q, ["R1"]))


# ------------------------------------------------------------------ URDF chains
URDF = """<?xml version="1.0"?>
<robot name="branchy">
  <link name="world"/>
  <link name="base_link"/>
  <link name="torso"><inertial><origin xyz="0 0 0.2"/><mass value="20"/>
    <inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="upper"><inertial><origin xyz="0.2 0 0"/><mass value="5"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="lower"/>
  <link name="hand"/>
  <link name="head"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base_link"/>
    <origin xyz="1 2 0.1" rpy="0 0 0.5"/></joint>
  <joint name="lift" type="prismatic"><parent link="base_link"/><child link="torso"/>
    <origin xyz="0 0 0.5"/><axis xyz="0 0 1"/><limit lower="0" upper="0.35" effort="100" velocity="0.1"/></joint>
  <joint name="shoulder" type="revolute"><parent link="torso"/><child link="upper"/>
    <origin xyz="0.1 0 0.4" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="50" velocity="1"/></joint>
  <joint name="elbow" type="continuous"><parent link="upper"/><child link="lower"/>
    <origin xyz="0.4 0 0"/><axis xyz="0 1 0"/></joint>
  <joint name="tool" type="fixed"><parent link="lower"/><child link="hand"/><origin xyz="0.3 0 0"/></joint>
  <joint name="neck" type="revolute"><parent link="torso"/><child link="head"/>
    <origin xyz="0 0 0.6"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="5" velocity="1"/></joint>
</robot>
"""


def _urdf_robot(tmp_path, joints=("lift", "shoulder", "elbow"), extra=""):
    (tmp_path / "r.urdf").write_text(URDF)
    tables = "".join(f'[[joint]]\nname = "{n}"\n' + ('lower = -3.0\nupper = 3.0\n' if n == "elbow" else "")
                     for n in joints)
    text = (f'name = "branchy"\nurdf = "r.urdf"\nbase_link = "base_link"\ntip_link = "hand"\n{extra}{tables}'
            '[tool]\nload_point = [0.05, 0, 0]\n[tool.markers]\nP = [0.1, 0.0, 0.0]\n')
    return parse_robot(text, source=str(tmp_path / "robot.toml"), base_dir=tmp_path)


def test_a_urdf_chain_between_base_link_and_tip_link(tmp_path):
    robot = _urdf_robot(tmp_path)
    assert robot.joint_kinds == (JointKind.PRISMATIC, JointKind.REVOLUTE, JointKind.REVOLUTE)
    q = np.array([0.2, 0.3, -0.5])
    # first principles: base_link frame, lift along z, shoulder and elbow about y, hand 0.3 m out
    c1, s1 = math.cos(0.3), math.sin(0.3)
    c12, s12 = math.cos(-0.2), math.sin(-0.2)
    x = 0.1 + 0.4 * c1 + (0.3 + 0.1) * c12
    z = 0.5 + 0.2 + 0.4 - 0.4 * s1 - (0.3 + 0.1) * s12
    np.testing.assert_allclose(robot.positions(robot.theta(q), ["P"])[0], [x, 0.0, z], atol=1e-12)
    # the torso's 20 kg on the lift: gravity pushes the prismatic joint down with 25 kg * g
    g = robot.gravity_torque(robot.theta(q))
    assert g[0] == pytest.approx(25.0 * 9.81, rel=1e-9)
    assert robot.lower[0] == 0.0 and robot.upper[0] == pytest.approx(0.35)


def test_a_urdf_chain_joint_without_a_table_is_refused(tmp_path):
    with pytest.raises(InputError, match=r"joint.name.*'elbow' has no \[\[joint\]\] table"):
        _urdf_robot(tmp_path, joints=("lift", "shoulder"))
    with pytest.raises(InputError, match=r"'neck' is not on the chain"):
        _urdf_robot(tmp_path, joints=("lift", "neck", "shoulder", "elbow"))
    text = (f'name = "b"\nurdf = "{tmp_path / "r.urdf"}"\nbase_link = "nowhere"\n'
            '[[joint]]\nname = "lift"\n[tool]\nload_point = [0, 0, 0]\n[tool.markers]\nP = [0, 0, 0]\n')
    with pytest.raises(InputError, match=r"base_link.*no link or frame 'nowhere'"):
        parse_robot(text, source="b.toml")


def test_the_urdf_agrees_with_pinocchios_own_reading(tmp_path):
    """The full URDF read by Pinocchio, with the neck locked, gives the hand where elastocal does."""
    robot = _urdf_robot(tmp_path)
    full = pin.buildModelFromXML(URDF)
    data = full.createData()
    q_full = pin.neutral(full)
    values = {"lift": 0.12, "shoulder": -0.4, "elbow": 0.9}
    for name, v in values.items():
        jm = full.joints[full.getJointId(name)]
        if jm.nq == 2:
            q_full[jm.idx_q:jm.idx_q + 2] = [math.cos(v), math.sin(v)]
        else:
            q_full[jm.idx_q] = v
    pin.framesForwardKinematics(full, data, q_full)
    o_m_base = data.oMf[full.getFrameId("base_link")]
    o_m_hand = data.oMf[full.getFrameId("hand")]
    expected = o_m_base.actInv(o_m_hand.act(np.array([0.1, 0.0, 0.0])))
    got = robot.positions(robot.theta(np.array(list(values.values()))), ["P"])[0]
    np.testing.assert_allclose(got, expected, atol=1e-12)


@pytest.mark.parametrize("bent", [False, True])
def test_the_geometry_jacobian_of_a_prismatic_joint_is_a_slide_along_its_axis(bent):
    """The derivative of the marker positions in each DH error, against central differences of
    the corrected robot: a prismatic joint's zero dq1 is a length along its axis (the chain
    slides), its dd1 moves nothing (d1 is the travel); on the rigid chain and the chain with
    its links bent (the absolute fit with link_compliance)."""
    from elastocal.identify import kinematics as kin

    robot = bundled_robot("hh150_track")
    markers = list(robot.marker_names)
    names = kin.parameter_names(robot, markers)
    theta = robot.theta(np.array([1.2, 0.3, -0.4, 0.5, 0.2, -0.9, 0.4]))
    links = np.random.default_rng(1).normal(0.0, 1e-4, len(robot.springs_in_link_model)) if bent else None
    jac = assert_jacobian_is_the_differences(robot, theta, markers, names, links)
    i = names.index("dq1")
    axis = jac[0, :, i]
    assert np.allclose(jac[:, :, i], axis) and math.isclose(np.linalg.norm(axis), 1.0, rel_tol=1e-9)
    assert not np.any(jac[..., names.index("dd1")])
    if not bent:
        batch = kin.position_jacobian_batch(robot, theta[None], markers, names)[1][0]
        np.testing.assert_allclose(batch, jac, atol=1e-12)
