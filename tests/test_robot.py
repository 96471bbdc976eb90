"""Robot model: Pinocchio frames, Jacobians and gravity against an independent
modified-DH chain written with numpy."""

import math

import numpy as np
import pytest

from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot, parse_robot

ROBOT = bundled_robot()


def rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def trans(x, y, z):
    t = np.eye(4)
    t[:3, 3] = [x, y, z]
    return t


def dh_frames(theta):
    """Craig: T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)."""
    t = np.eye(4)
    out = []
    for j, th in zip(ROBOT.joints, theta):
        t = t @ rx(j.alpha) @ trans(j.a, 0, 0) @ rz(th) @ trans(0, 0, j.d)
        out.append(t)
    return out


def dh_point(theta, flange_p):
    return (dh_frames(theta)[-1] @ np.append(flange_p, 1.0))[:3]


POSES = np.random.default_rng(7).uniform(ROBOT.lower, ROBOT.upper, size=(5, 6))


@pytest.mark.parametrize("q", POSES)
def test_marker_and_load_positions_match_dh_chain(q):
    theta = ROBOT.theta(q)
    frames = list(ROBOT.marker_names) + ["load_point"]
    pin_pos = ROBOT.positions(theta, frames)
    points = [p for _, p in ROBOT.tool.flange_p_markers] + [ROBOT.tool.flange_p_load]
    for got, flange_p in zip(pin_pos, points):
        np.testing.assert_allclose(got, dh_point(theta, np.array(flange_p)), atol=1e-12)


@pytest.mark.parametrize("q", POSES)
def test_position_jacobian_matches_finite_difference_of_dh_chain(q):
    theta = ROBOT.theta(q)
    jac = ROBOT.jacobians(theta, ["R2", "load_point"])
    for k, flange_p in enumerate([ROBOT.tool.flange_p_markers[1][1], ROBOT.tool.flange_p_load]):
        fd = np.empty((3, 6))
        h = 1e-6
        for j in range(6):
            e = np.zeros(6)
            e[j] = h
            fd[:, j] = (dh_point(theta + e, np.array(flange_p)) - dh_point(theta - e, np.array(flange_p))) / (2 * h)
        np.testing.assert_allclose(jac[k][:3], fd, atol=1e-8)


def test_angular_jacobian_is_joint_axes():
    theta = ROBOT.theta(POSES[0])
    jac = ROBOT.jacobians(theta, ["flange"])[0]
    frames = dh_frames(theta)
    for j in range(6):
        np.testing.assert_allclose(jac[3:, j], frames[j][:3, 2], atol=1e-12)


def test_gravity_is_gradient_of_potential_energy():
    g_vec = np.array(ROBOT.gravity)

    def potential(theta):
        v = 0.0
        for frame, joint in zip(dh_frames(theta), ROBOT.joints):
            com = (frame @ np.append(joint.com, 1.0))[:3]
            v -= joint.mass * g_vec @ com
        return v

    theta = ROBOT.theta(POSES[1])
    fd = np.empty(6)
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1e-6
        fd[j] = (potential(theta + e) - potential(theta - e)) / 2e-6
    np.testing.assert_allclose(ROBOT.gravity_torque(theta), fd, atol=1e-5)


def test_load_torque_is_jacobian_transpose_of_wrench_minus_gravity():
    theta = ROBOT.theta(POSES[2])
    w = np.array([100.0, -200.0, -900.0, 5.0, 0.0, -3.0])
    jac = ROBOT.jacobians(theta, ["load_point"])[0]
    expected = jac.T @ w - ROBOT.gravity_torque(theta)
    np.testing.assert_allclose(ROBOT.load_torque(theta, w), expected, atol=1e-9)


def test_compensator_balances_gravity_and_matches_yang_zero():
    comp = ROBOT.compensator
    params = comp.nominal_parameters()
    np.testing.assert_allclose(params, [4771.4, 0.9112])
    # torque zero near q2 = 3.3 deg (Yang), positive beyond, like gravity's holding torque
    assert abs(float(comp.torque(math.radians(3.3), params))) < 1.0
    q = np.array([0.0, math.radians(40.0), 0.0, 0.0, 0.0, 0.0])
    g2 = ROBOT.gravity_torque(ROBOT.theta(q))[1]
    with_comp = ROBOT.load_torque(ROBOT.theta(q), None, params)[1]
    assert abs(with_comp) < abs(g2)


def test_compensator_derivatives_are_exact():
    comp = ROBOT.compensator
    p = comp.nominal_parameters()
    q2 = np.radians([-20.0, 10.0, 60.0])
    d = comp.torque_derivatives(q2, p)
    for k in range(2):
        e = np.zeros(2)
        e[k] = 1e-6 * p[k]
        fd = (comp.torque(q2, p + e) - comp.torque(q2, p - e)) / (2 * e[k])
        np.testing.assert_allclose(d[:, k], fd, rtol=1e-6)


def test_link_model_reduces_to_rigid_model_at_zero_link_angles():
    theta = ROBOT.theta(POSES[3])
    np.testing.assert_allclose(ROBOT.positions(ROBOT.theta_links(theta), ["R1", "R3"], links=True),
                               ROBOT.positions(theta, ["R1", "R3"]), atol=1e-14)


def test_robot_round_trips_through_toml():
    again = parse_robot(ROBOT.to_toml())
    theta = ROBOT.theta(POSES[4])
    np.testing.assert_allclose(again.positions(theta, ["R1"]), ROBOT.positions(theta, ["R1"]), atol=1e-15)
    assert again.compensator == ROBOT.compensator


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("lower = -3.2289", "lower = -185.0"), "look like degrees"),
    (lambda t: t.replace('kind = "hydropneumatic"', 'kind = "gas"'), "compensator.kind"),
    (lambda t: t.replace("R1 = [0.0, 0.0, 0.3]", "R1 = [0.0, 0.0, 300.0]"), "tool.markers.R1"),
    (lambda t: t.replace("torque_constant = 169.6355", "torque_constant = \"x\""), "joint[1].torque_constant"),
    (lambda t: t.replace("load_point = [0.1, 0.0, 0.35]", ""), "column tool.load_point: missing required key"),
])
def test_bad_robot_descriptions_name_the_key(edit, message):
    text = edit(ROBOT.to_toml())
    assert text != ROBOT.to_toml()
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("]", r"\]")):
        parse_robot(text, source="robot.toml")
