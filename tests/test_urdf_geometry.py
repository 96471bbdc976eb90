"""Geometric calibration of a URDF robot (docs/cli.md, kinematic_errors on URDF robots): each joint
origin's six errors and the joint offsets, the identifiable set by the pivoted QR with what absorbs
the rest. The truth is written into the URDF text itself (origins moved), and the readings are
that robot's forward kinematics (Pinocchio), seen by a tracker placed anywhere."""

import pathlib
from dataclasses import replace
import re

import numpy as np
import pinocchio as pin
import pytest

import elastocal
from elastocal.formats.robot_toml import load_robot, parse_robot
from elastocal.formats.tables import static_table_from_arrays
from elastocal.identify import kinematics as kin
from elastocal.identify.absolute import identify_absolute

ROBOTS = pathlib.Path(elastocal.__file__).parent / "robots"
ROBOT = load_robot(ROBOTS / "hh150_urdf.toml")
MODEL = ("kinematic_errors", "tracker_frame")
NOISE_M = 1e-5
#: where the tracker of the readings stands: p_tracker = TRACKER_R p_base + TRACKER_T (3 m away, turned, tilted)
TRACKER_R, TRACKER_T = pin.exp3(np.array([0.01, -0.02, 2.0])), np.array([3.0, -1.0, 0.5])
FRAME_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")


def true_robot(rng):
    """The HH-150 URDF with every joint origin moved by ~0.3 mm and ~0.3 mrad and the marker by ~1 mm,
    written into the URDF and robot.toml text; returns it and the true errors in elastocal's names
    (origin errors in the previous joint's frame: the HH-150's URDF has no fixed joints between)."""
    xml = (ROBOTS / "hh150.urdf").read_text()
    truth = {}
    nominal = {}

    def move(m):
        name, between = m.group(1), m.group(2)
        xyz = np.array([float(v) for v in m.group(3).split()])
        rpy = np.array([float(v) for v in m.group(4).split()])
        nominal[name] = pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)
        xyz, rpy = xyz + rng.normal(0, 3e-4, 3), rpy + rng.normal(0, 3e-4, 3)
        j = [jt.name for jt in ROBOT.joints].index(name) + 1
        r_true = pin.rpy.rpyToMatrix(*rpy)
        for axis, v in zip("xyz", xyz - nominal[name].translation):
            truth[f"dp{axis}{j}"] = float(v)
        for axis, v in zip("xyz", pin.log3(r_true @ nominal[name].rotation.T)):
            truth[f"dr{axis}{j}"] = float(v)
        fmt = " ".join
        return (f'<joint name="{name}"{between}<origin xyz="{fmt(repr(float(v)) for v in xyz)}" '
                f'rpy="{fmt(repr(float(v)) for v in rpy)}"/>')

    xml = re.sub(r'<joint name="(A\d)"(.*?)<origin xyz="([^"]*)" rpy="([^"]*)"/>', move, xml, flags=re.S)
    marker = np.array([0.0, 0.0, 0.30]) + rng.normal(0, 1e-3, 3)
    truth.update({f"d{axis}_R1": float(v) for axis, v in zip("xyz", marker - [0.0, 0.0, 0.30])})
    toml = (ROBOTS / "hh150_urdf.toml").read_text().replace('urdf = "hh150.urdf"', f"urdf_xml = '''{xml}'''")
    toml = toml.replace("R1 = [0.0, 0.0, 0.30]", "R1 = [" + ", ".join(repr(float(v)) for v in marker) + "]")
    return parse_robot(toml, base_dir=ROBOTS), truth


#: the joint stiffness of the sagging truth [N*m/rad] (Yang et al.'s HH-150)
K_TRUE = np.array([559000.0, 1435000.0, 1829000.0, 184000.0, 171000.0, 70000.0])


def sagged(robot, theta, k):
    """The link-side angles of ``robot`` holding its own weight on springs ``k`` (fixed point of
    theta = theta0 - g(theta)/k with the compensator's torque on joint 2): Pinocchio's gravity."""
    data = robot.model.createData()
    comp = robot.compensator
    th = np.array(theta, dtype=float)
    for _ in range(20):
        tau = -pin.computeGeneralizedGravity(robot.model, data, th)
        if comp is not None:
            tau[comp.index] -= float(comp.torque(th[comp.index] - robot.joints[comp.index].offset,
                                                 comp.nominal_parameters()))
        th = np.asarray(theta) + tau / k
    return th


def readings(robot, rng, n_poses=50, repeats=2, k=None):
    """An absolute-only table of ``robot``'s marker seen by a tracker 3 m away, turned and tilted."""
    lo, hi = np.maximum(ROBOT.lower, -2.0), np.minimum(ROBOT.upper, 2.0)
    q = rng.uniform(lo, hi, (n_poses, ROBOT.n_joints))
    rot, trans = TRACKER_R, TRACKER_T
    pose, qs, marker, xyz = [], [], [], []
    for i, qi in enumerate(q):
        theta = robot.theta(qi) if k is None else sagged(robot, robot.theta(qi), k)
        for m, p in zip(ROBOT.marker_names, robot.positions(theta, ROBOT.marker_names)):
            for _ in range(repeats):
                pose.append(str(i + 1))
                qs.append(qi)
                marker.append(m)
                xyz.append(rot @ p + trans + rng.normal(0, NOISE_M, 3))
    return static_table_from_arrays(pose=pose, load=["0"] * len(pose), q=np.array(qs), marker=marker,
                                    xyz=np.array(xyz), robot=ROBOT)


def test_urdf_parameters_and_their_jacobian():
    names = kin.parameter_names(ROBOT, ROBOT.marker_names)
    assert names[:7] == ("dq1", "dpx1", "dpy1", "dpz1", "drx1", "dry1", "drz1") and len(names) == 6 * 7 + 3 * len(ROBOT.marker_names)
    assert kin.unit_of("dpx3") == "m" and kin.unit_of("dry3") == "rad"
    q = np.array([0.3, 0.4, -0.5, 0.7, 1.1, -0.4])
    h = 1e-6
    for values, tol in ((np.zeros(len(names)), 1e-7),
                        (np.random.default_rng(1).normal(0, 1e-3, len(names)), 3e-3)):
        robot = kin.corrected_robot(ROBOT, names, values)
        pos, jac = kin.position_jacobian(robot, robot.theta(q), list(ROBOT.marker_names), names)
        np.testing.assert_allclose(pos, robot.positions(robot.theta(q), ROBOT.marker_names), atol=1e-12)
        for k, name in enumerate(names):
            step = np.zeros(len(names))
            step[k] = h
            a, b = (kin.corrected_robot(ROBOT, names, values + s) for s in (step, -step))
            fd = (a.positions(a.theta(q), ROBOT.marker_names) - b.positions(b.theta(q), ROBOT.marker_names)) / (2 * h)
            # exact at zero; elsewhere to first order in the origin's rotation error (SO(3)'s Jacobian)
            np.testing.assert_allclose(jac[:, :, k], fd, atol=tol, err_msg=name)


def fit_and_z(seed, stiffness=False, registration=False):
    """The fit of one seed's truth and each identified parameter's error in standard deviations:
    the kinematic ones against what they estimate (their own value plus what they absorb), the
    joint stiffness (the robot's own weight on its springs, ``stiffness``) against the truth, and
    with ``registration`` rx..tz against the tracker's placement (:func:`registration_z`)."""
    rng = np.random.default_rng(seed)
    truth_robot, truth = true_robot(rng)
    k = K_TRUE if stiffness else None
    model = ("joint_stiffness", *MODEL) if stiffness else MODEL
    fit = identify_absolute(ROBOT, readings(truth_robot, rng, k=k), model=model)
    if stiffness:
        truth.update({f"c{j}": 1.0 / kj for j, kj in enumerate(K_TRUE, start=1)})
    expected = fit.identifiable.base_value(truth)
    z = {p.name: (p.value - expected[p.name]) / p.std for p in fit.parameters if p.name in fit.kinematic_names}
    for p in fit.parameters:
        if p.name.startswith("k") and p.name[1:].isdigit():
            z[p.name] = (p.value - K_TRUE[int(p.name[1:]) - 1]) / p.std
    if registration:
        z.update(registration_z(fit, truth))
    return fit, z


def registration_z(fit, truth):
    """The registration's error (rx..tz) in standard deviations against what it estimates: the tracker's
    placement moved by the base errors it absorbs (joint 1's origin and zero, what of joint 2's turns or
    slides along axis 1), to first order, as the fit perturbs it: p_tracker = R (exp(dr) p + dt) + t."""
    base = fit.identifiable.base_value({**truth, **dict.fromkeys(FRAME_NAMES, 0.0)})
    dr, dt = (np.array([base[n] for n in names]) for names in (FRAME_NAMES[:3], FRAME_NAMES[3:]))
    expected = (*pin.log3(TRACKER_R @ pin.exp3(dr)), *(TRACKER_R @ dt + TRACKER_T))
    got = {p.name: p for p in fit.parameters}
    return {n: (got[n].value - e) / got[n].std for n, e in zip(FRAME_NAMES, expected)}


def test_urdf_geometry_fit_reaches_the_noise_and_names_what_absorbs_the_rest():
    fit, z = fit_and_z(11, registration=True)
    assert fit.noise_floor is not None and fit.rms < 1.25 * fit.noise_floor, (fit.rms, fit.noise_floor)
    # the base's origin and joint 1's zero: the registration's; joint 6's zero: the marker's
    assert {"dq1", "dpx1", "dpy1", "dpz1", "drx1", "dry1", "drz1", "dq6"} <= set(fit.unidentifiable)
    assert fit.absorbed_by["dq1"][0][0] == "rz" and fit.absorbed_by["dpx1"][0][0] == "tx"
    assert fit.identifiable.keep.sum() == len(z) and len(z) >= 26
    assert max(abs(v) for v in z.values()) < 4.5, z


def test_urdf_self_weight_stiffness_with_the_geometry():
    fit, z = fit_and_z(12, stiffness=True)
    assert "k1" in fit.unidentifiable                     # a vertical first axis carries no weight torque
    assert {"k2", "k3"} <= set(z) and max(abs(v) for v in z.values()) < 4.5, z
    assert fit.rms < 1.25 * fit.noise_floor


@pytest.mark.heavy
@pytest.mark.acceptance
@pytest.mark.parametrize("stiffness", [False, True])
def test_urdf_geometry_intervals_cover_over_100_seeds(stiffness):
    """Measured: the geometry's intervals cover 95.9 % of 2700 alone, 95.4 % of 2700 beside the
    self-weight springs (93.3 % before the base's tilt from level was fitted beside them); the registration's (rx..tz against the tracker's placement with the base errors
    it absorbs) 95.2 % of 600 beside the geometry alone, each of the six 90-98 %. Beside the springs the
    registration is not checked here (test_urdf_registration_beside_the_springs_covers_over_100_seeds)."""
    inside, frame = [], []
    for seed in range(100):
        _, z = fit_and_z(1000 + seed, stiffness=stiffness, registration=not stiffness)
        inside += [abs(v) < 1.959964 for n, v in z.items() if not n.startswith("k") and n not in FRAME_NAMES]
        frame += [[abs(z[n]) < 1.959964 for n in FRAME_NAMES]] if not stiffness else []
    share = float(np.mean(inside))
    assert 0.91 <= share <= 0.99, share
    if not stiffness:
        each = np.mean(frame, axis=0)
        assert 0.91 <= np.mean(frame) <= 0.99 and np.all(each >= 0.95 - 3 * np.sqrt(0.95 * 0.05 / 100)), each


@pytest.mark.heavy
@pytest.mark.acceptance
def test_urdf_registration_beside_the_springs_covers_over_100_seeds():
    """Measured: 95.8 % of 600, each of rx..tz 93-99 % (80.7 %, ty 54 %, before the base's tilt from
    level was fitted beside the springs: the truth's joint-1 origin is tilted as its geometry's errors
    are drawn, which the registration absorbs as geometry but not as the weight's direction)."""
    frame = []
    for seed in range(100):
        _, z = fit_and_z(1000 + seed, stiffness=True, registration=True)
        frame += [abs(z[n]) < 1.959964 for n in FRAME_NAMES]
    assert 0.91 <= float(np.mean(frame)) <= 0.99, float(np.mean(frame))


@pytest.mark.heavy
@pytest.mark.acceptance
def test_urdf_self_weight_stiffness_intervals_cover_over_100_seeds():
    """Measured: k2..k5 within their 95 % intervals 93.0 % of 400 (85 % before the weight's torques
    were taken at the sagged configuration: k2 was biased by 1.3 standard deviations; 92.0 % before
    the base's tilt from level was fitted)."""
    inside = []
    for seed in range(100):
        _, z = fit_and_z(1000 + seed, stiffness=True)
        inside += [abs(v) < 1.959964 for n, v in z.items() if n.startswith("k")]
    share = float(np.mean(inside))
    assert 0.91 <= share <= 0.99, share


def first_origin_turned(dr):
    """The HH-150 URDF robot whose joint-1 origin is turned by ``dr`` [rad] in the base's axes (the arm
    stands out of level by that much), written into the URDF text; and that rotation as fitted (log3)."""
    xml = (ROBOTS / "hh150.urdf").read_text()
    m = re.search(r'<joint name="A1".*?<origin xyz="[^"]*" rpy="([^"]*)"/>', xml, flags=re.S)
    r_nom = pin.rpy.rpyToMatrix(*[float(v) for v in m.group(1).split()])
    rpy = pin.rpy.matrixToRpy(pin.exp3(np.asarray(dr, dtype=float)) @ r_nom)
    xml = xml[:m.start(1)] + " ".join(repr(float(v)) for v in rpy) + xml[m.end(1):]
    toml = (ROBOTS / "hh150_urdf.toml").read_text().replace('urdf = "hh150.urdf"', f"urdf_xml = '''{xml}'''")
    robot = parse_robot(toml, base_dir=ROBOTS)
    return robot, pin.log3(pin.rpy.rpyToMatrix(*rpy) @ r_nom.T)


def test_the_tilt_torques_are_those_of_an_arm_out_of_level():
    """First principles for the tilt's sign and unit: the weight's torques of the URDF robot whose first
    origin is turned by 1 mrad about x and -0.7 mrad about y (Pinocchio on that URDF, gravity along the
    base's -z) equal the level robot's plus the tilt's torques times that turn, to second order in it."""
    from elastocal.identify.level import tilt_torques

    turned, dr = first_origin_turned([1e-3, -7e-4, 0.0])
    theta = ROBOT.theta(np.random.default_rng(5).uniform(-1.5, 1.5, (8, ROBOT.n_joints)))
    per_rad = tilt_torques(ROBOT, theta)
    for s, th in enumerate(theta):
        level = -pin.computeGeneralizedGravity(ROBOT.model, ROBOT.model.createData(), th)
        tilted = -pin.computeGeneralizedGravity(turned.model, turned.model.createData(), th)
        change = per_rad[s] @ dr[:2]
        # second order: |dr|^2 times the weight's torque (a few 1e3 N*m) is a few 1e-3 N*m
        np.testing.assert_allclose(tilted - level, change, atol=1e-2)
        assert np.max(np.abs(change)) > 0.3          # the first order is there: about 1 N*m on joint 1


def test_a_base_out_of_level_is_fitted_beside_the_springs():
    """The arm 3.6 mrad out of level (its first origin turned; geometry otherwise the drawing's): the
    absolute fit of springs, geometry and registration finds the tilt within 3 std of the turn, at the
    floor (seeds 0-19: the tilt 5-10 std from zero, within 2.1 std of the turn)."""
    rng = np.random.default_rng(21)
    robot, dr = first_origin_turned([3e-3, -2e-3, 0.0])
    fit = identify_absolute(ROBOT, readings(robot, rng, k=K_TRUE), model=("joint_stiffness", *MODEL))
    got = {p.name: p for p in fit.parameters}
    for name, truth in zip(("tilt_x", "tilt_y"), dr[:2]):
        assert abs(got[name].value - truth) < 3 * got[name].std, (name, got[name], truth)
    assert abs(got["tilt_x"].value) > 3 * got["tilt_x"].std        # a tilt this large is determined (5-10 std)
    assert fit.rms < 1.25 * fit.noise_floor


def test_compensation_sags_under_the_tilted_weight():
    """The compensation model with a tilt of 3 mrad about x and -2 mrad about y sags the joints as
    the robot whose first origin is turned by that much does under level gravity (Pinocchio on that
    URDF), to second order in the tilt; level, it does not."""
    from elastocal.compensation.model import CompensationModel, StaticKernel

    turned, dr = first_origin_turned([3e-3, -2e-3, 0.0])
    q = np.random.default_rng(8).uniform(-1.5, 1.5, (6, ROBOT.n_joints))
    wrench = np.zeros((len(q), 6))

    def sag(robot, tilt):
        model = CompensationModel(robot=robot, stiffness=K_TRUE, tilt_rad=tilt)
        return StaticKernel(model).equilibrium(q, wrench) - (q + robot.offsets)

    truth = sag(turned, (0.0, 0.0))
    tilted, level = sag(ROBOT, (float(dr[0]), float(dr[1]))), sag(ROBOT, (0.0, 0.0))
    # joint 1 twists by ~1e-5 rad under the tilted weight; second order in 3.6 mrad is ~1e-8 rad
    assert np.max(np.abs(truth[:, 0])) > 5e-6
    np.testing.assert_allclose(tilted, truth, atol=1e-7)
    assert np.max(np.abs(level - truth)) > 5e-6


def test_validate_reads_the_tilt_back_on_unseen_poses():
    """What identify writes beside the springs of an arm out of level (the tilt and joint 1's
    compliance times it), validate reads: on another draw of poses with the frame kept, the calibrated
    model reaches the noise floor (without the tilt it is 2-3x above)."""
    from elastocal.formats.calibration import calibration_from_fit
    from elastocal.identify.accuracy import validate

    robot, _ = first_origin_turned([3e-3, -2e-3, 0.0])
    fit = identify_absolute(ROBOT, readings(robot, np.random.default_rng(3), k=K_TRUE),
                            model=("joint_stiffness", *MODEL))
    cal = calibration_from_fit(ROBOT.name, fit.to_json(), robot_description=ROBOT.to_toml())
    assert {"tilt_x", "tilt_y", "c1_tilt_x", "c1_tilt_y"} <= set(cal.names)
    unseen = readings(robot, np.random.default_rng(4), k=K_TRUE)
    v = validate(ROBOT, cal, unseen, keep_frame=True)
    assert v.absolute_calibrated.rms < 1.25 * v.noise_floor, (v.absolute_calibrated, v.noise_floor)
    level = replace(cal, parameters=tuple(p for p in cal.parameters if "tilt" not in p.name))
    assert validate(ROBOT, level, unseen, keep_frame=True).absolute_calibrated.rms > 1.5 * v.noise_floor
