"""The URDF elastocal writes (`elastocal robot --urdf`, ``Robot.to_urdf()``) is read by
other tools at the controller's joint angles: loaded in Pinocchio and in yourdfpy (a
second, independent URDF reader), its flange, load point and marker frames are where
elastocal's own forward kinematics puts them, to 1e-9 m, for the nominal and a
calibrated HH-150 (joint zeros moved), its URDF description and a robot with a
prismatic joint; its limits are those of the description; read back as a robot it
predicts the same positions."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pinocchio as pin
import pytest
import yourdfpy

from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path, load_robot, parse_robot
from elastocal.identify import kinematics as kin
from elastocal.model.kinds import JointKind
from elastocal.model.urdf_export import controller_urdf_robot

TOL_M = 1e-9
DH = bundled_robot()


def _calibrated(seed: int):
    """The HH-150 with random geometric errors of a real calibration's size: joint zeros by
    up to 0.5 deg, lengths by mm, twists by 0.1 deg, markers by mm."""
    rng = np.random.default_rng(seed)
    names = kin.parameter_names(DH, DH.marker_names)
    scale = {"dq": 0.01, "da": 2e-3, "dd": 2e-3, "dalpha": 2e-3, "dbeta": 2e-3}
    values = [rng.normal(0.0, scale.get(n.rstrip("0123456789"), 1e-3)) for n in names]
    return kin.corrected_robot(DH, names, values)


def _track_robot():
    """A 7-joint robot: the HH-150 on a vertical linear axis (prismatic joint 1)."""
    text = bundled_robot_path().read_text(encoding="utf-8")
    head, rest = text.split("[[joint]]", 1)
    track = ('[[joint]]\nname = "track"\ntype = "prismatic"\na = 0.0\nalpha = 0.0\ntheta = 0.3\noffset = 0.25\n'
             "lower = -0.5\nupper = 2.5\nmass = 400.0\ncom = [0.0, 0.0, 0.1]\nvelocity = 1.2\neffort = 20000.0\n\n")
    return parse_robot(head + track + "[[joint]]" + rest, source="track.toml")


ROBOTS = {"hh150": lambda: DH, "hh150_urdf": lambda: bundled_robot("hh150_urdf"),
          "calibrated": lambda: _calibrated(1), "track": _track_robot,
          "hh150_track": lambda: bundled_robot("hh150_track")}


def _frames(robot) -> list[tuple[str, str]]:
    """(URDF link, elastocal frame) of the flange, the load point and every marker."""
    return [("flange", "flange"), ("load_point", "load_point"), *((f"marker_{m}", m) for m in robot.marker_names)]


def _controller_angles(robot, n: int = 8, seed: int = 5) -> np.ndarray:
    return np.random.default_rng(seed).uniform(robot.lower, robot.upper, size=(n, robot.n_joints))


@pytest.mark.parametrize("which", ROBOTS)
def test_pinocchio_and_yourdfpy_put_every_frame_where_elastocal_does_at_controller_angles(tmp_path, which):
    robot = ROBOTS[which]()
    path = tmp_path / "robot.urdf"
    path.write_text(robot.to_urdf(), encoding="utf-8")
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    other = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)
    names = [j.name for j in robot.joints]
    assert list(other.actuated_joint_names) == names
    frames = _frames(robot)
    worst = 0.0
    for q in _controller_angles(robot):
        expected = robot.positions(robot.theta(q), [f for _, f in frames])
        config = pin.neutral(model)
        for name, value in zip(names, q):
            config[model.idx_qs[model.getJointId(name)]] = value
        pin.framesForwardKinematics(model, data, config)
        by_pinocchio = np.array([data.oMf[model.getFrameId(link)].translation for link, _ in frames])
        other.update_cfg(dict(zip(names, q)))
        by_yourdfpy = np.array([other.get_transform(link, "base_link")[:3, 3] for link, _ in frames])
        worst = max(worst, np.abs(by_pinocchio - expected).max(), np.abs(by_yourdfpy - expected).max())
    assert worst < TOL_M
    # the joint variable is q, not q + offset: fed theta instead, the flange is elsewhere
    if np.any(robot.offsets != 0):
        q = _controller_angles(robot, 1)[0]
        other.update_cfg(dict(zip(names, robot.theta(q))))
        assert np.linalg.norm(other.get_transform("flange", "base_link")[:3, 3]
                              - robot.positions(robot.theta(q), ["flange"])[0]) > 0.01


@pytest.mark.parametrize("which", ROBOTS)
def test_limits_kinds_and_masses_are_the_descriptions(tmp_path, which):
    robot = ROBOTS[which]()
    path = tmp_path / "robot.urdf"
    path.write_text(robot.to_urdf(), encoding="utf-8")
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)
    for i, j in enumerate(robot.joints, start=1):
        joint = urdf.joint_map[j.name]
        assert joint.type == j.kind.value
        assert (joint.limit.lower, joint.limit.upper) == (j.lower, j.upper)      # limits of q
        assert joint.limit.velocity == j.velocity > 0 and joint.limit.effort == j.effort > 0
        link = urdf.link_map[f"link{i}"]
        assert (link.inertial.mass if link.inertial is not None else 0.0) == pytest.approx(j.mass, abs=1e-12)
    for link, _ in _frames(robot):
        assert urdf.joint_map[f"{link}_joint"].type == "fixed"
    if which == "track":
        assert urdf.joint_map["track"].type == "prismatic" and robot.joint_kinds[0] is JointKind.PRISMATIC


@pytest.mark.parametrize("which", ROBOTS)
def test_read_back_as_a_robot_it_predicts_the_same_positions(tmp_path, which):
    robot = ROBOTS[which]()
    path = tmp_path / "again.toml"
    path.write_text(controller_urdf_robot(robot).to_toml(), encoding="utf-8")
    again = load_robot(path)
    assert again.urdf is not None and not np.any(again.offsets)
    frames = [f for _, f in _frames(robot)]
    for q in _controller_angles(robot):
        np.testing.assert_allclose(again.positions(again.theta(q), frames), robot.positions(robot.theta(q), frames),
                                   rtol=0, atol=TOL_M)
        np.testing.assert_allclose(again.gravity_torque(again.theta(q)), robot.gravity_torque(robot.theta(q)),
                                   rtol=1e-9, atol=1e-6)
    assert [(j.lower, j.upper, j.velocity, j.effort, j.torque_constant) for j in again.joints] == \
        [(j.lower, j.upper, j.velocity, j.effort, j.torque_constant) for j in robot.joints]


def test_a_description_without_speed_limits_is_refused_naming_the_joint():
    text = re.sub(r"\nvelocity = [^\n]*", "", bundled_robot_path().read_text(encoding="utf-8"), count=2)
    robot = parse_robot(text, source="r.toml")
    assert robot.joints[0].velocity is None and robot.joints[2].velocity is not None
    with pytest.raises(InputError, match=r"joint\[1\]\.velocity.*joint 1 \(A1\) has no velocity limit") as err:
        robot.to_urdf()
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("key, value, match", [("velocity", "-1.0", "positive"), ("effort", "0.0", "positive"),
                                               ("velocity", '"fast"', "number")])
def test_bad_limits_are_one_line_errors(key, value, match):
    text = re.sub(rf"\n{key} = [^\n]*", f"\n{key} = {value}", bundled_robot_path().read_text(encoding="utf-8"),
                  count=1)
    with pytest.raises(InputError, match=rf"joint\[1\]\.{key}.*{match}"):
        parse_robot(text, source="r.toml")


@pytest.mark.parametrize("which", ["hh150", "hh150_urdf"])
def test_the_robot_command_writes_the_calibrated_urdf_at_controller_angles(tmp_path, capsys, which):
    """`elastocal robot --urdf` on a calibration with kinematic errors (DH ones, or a URDF
    robot's joint-origin errors): both outputs give the calibrated robot's positions at
    controller angles, the URDF in yourdfpy."""
    from elastocal.formats.calibration import calibration_from_fit, write_calibration

    robot = bundled_robot(which)
    names = kin.parameter_names(robot, robot.marker_names)
    rng = np.random.default_rng(2)
    values = {n: float(rng.normal(0.0, 1e-3)) for n in names}
    values["dq2"], values["dq3"] = math.radians(0.4), math.radians(-0.3)     # calibrated joint zeros
    fit = {"model": ["joint_stiffness", "kinematic_errors", "tracker_frame"],
           "residual": {"rms": 1e-5, "max": 3e-5, "n": 100},
           "parameters": {**{n: {"value": v, "std": 1e-5, "unit": kin.unit_of(n)} for n, v in values.items()},
                          **{f"k{j}": {"value": 1e6, "std": 1e3, "unit": "N·m/rad"} for j in range(1, 7)},
                          **{n: {"value": 0.0, "std": 1e-6, "unit": "rad" if n[0] == "r" else "m"}
                             for n in ("rx", "ry", "rz", "tx", "ty", "tz")}}}
    cal = tmp_path / "cal.json"
    write_calibration(cal, calibration_from_fit(robot.name, fit, [], robot_description=robot.to_toml()))
    code = main(["robot", "--calibration", str(cal), "--out", str(tmp_path / "c.toml"),
                 "--urdf", str(tmp_path / "c.urdf"), "--json"])
    assert code == 0
    assert json.loads(capsys.readouterr().out) == {"robot": str(tmp_path / "c.toml"), "urdf": str(tmp_path / "c.urdf")}
    truth = kin.corrected_robot(robot, list(values), list(values.values()))
    urdf = yourdfpy.URDF.load(str(tmp_path / "c.urdf"), load_meshes=False, build_collision_scene_graph=False)
    toml = load_robot(tmp_path / "c.toml")
    for q in _controller_angles(robot):
        expected = truth.positions(truth.theta(q), ["R1", "R2", "R3"])
        urdf.update_cfg(dict(zip([j.name for j in robot.joints], q)))
        got = np.array([urdf.get_transform(f"marker_{m}", "base_link")[:3, 3] for m in ("R1", "R2", "R3")])
        np.testing.assert_allclose(got, expected, rtol=0, atol=TOL_M)
        np.testing.assert_allclose(toml.positions(toml.theta(q), ["R1", "R2", "R3"]), expected, rtol=0, atol=TOL_M)
