"""Geometric calibration of a URDF robot (docs/cli.md, kinematic_errors on URDF robots): each joint
origin's six errors and the joint offsets, the identifiable set by the pivoted QR with what absorbs
the rest. The truth is written into the URDF text itself (origins moved), and the readings are
that robot's forward kinematics (Pinocchio), seen by a tracker placed anywhere."""

import pathlib
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
    """Measured: the geometry's intervals cover 95.9 % of 2700 alone, 93.3 % of 2700 beside the
    self-weight springs; the registration's (rx..tz against the tracker's placement with the base errors
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
@pytest.mark.xfail(strict=True, reason="open: beside the self-weight springs the registration covers 80.7 % of "
                   "600 (ty 54 %): on noise-free readings it already lies up to 3.4 std (a few um, its std "
                   "about 1 um) from the tracker's placement with the absorbed base errors, where alone it "
                   "lies within 0.4 std; the same seeds' k2..k5 cover 92 %. Cause: the fit takes the weight's "
                   "torques on the drawing's geometry, the truth sags on its as-built one (1-2 um rms unmodelled "
                   "on noise-free readings, 0.001 um when the truth sags on the drawing's geometry)")
def test_urdf_registration_beside_the_springs_covers_over_100_seeds():
    frame = []
    for seed in range(100):
        _, z = fit_and_z(1000 + seed, stiffness=True, registration=True)
        frame += [abs(z[n]) < 1.959964 for n in FRAME_NAMES]
    assert 0.91 <= float(np.mean(frame)) <= 0.99, float(np.mean(frame))


@pytest.mark.heavy
@pytest.mark.acceptance
def test_urdf_self_weight_stiffness_intervals_cover_over_100_seeds():
    """Measured: k2..k5 within their 95 % intervals 92.0 % of 400 (85 % before the weight's torques
    were taken at the sagged configuration: k2 was biased by 1.3 standard deviations)."""
    inside = []
    for seed in range(100):
        _, z = fit_and_z(1000 + seed, stiffness=True)
        inside += [abs(v) < 1.959964 for n, v in z.items() if n.startswith("k")]
    share = float(np.mean(inside))
    assert 0.91 <= share <= 0.99, share
