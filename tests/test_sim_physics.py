"""The simulator's own physics (sims/physics.py) against closed forms it does not share.

A two-link planar arm in the vertical plane (gravity along -y), point-like link masses at
mid-link and a force at the tip: the joint torques are written out by hand from the
potential energy and the tip's position, and the deflected equilibrium is solved by
scipy's root finder on those closed-form torques. The compensator's torque from its
pivots is checked against the papers' closed form (Y11, K7) and against virtual work,
and friction's sign against the motor's torque balance.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
import scipy.optimize

from elastocal.model.compensator import CompensatorSpec
from elastocal.model.kinds import CompensatorKind
from elastocal.model.robot import JointSpec, Robot, ToolSpec
from elastocal.sims import physics

G = 9.81
L1, L2 = 1.1, 0.8          # link lengths [m]
M1, M2 = 60.0, 35.0        # link masses [kg], at mid-link
K = np.array([2.0e5, 8.0e4])   # joint stiffness [N·m/rad]


def planar_arm(masses: bool = True) -> Robot:
    joints = (
        JointSpec(a=0.0, alpha=0.0, d=0.0, offset=0.0, lower=-3.0, upper=3.0, torque_constant=1.0,
                  mass=M1 if masses else 0.0, com=(L1 / 2, 0.0, 0.0), name="j1"),
        JointSpec(a=L1, alpha=0.0, d=0.0, offset=0.0, lower=-3.0, upper=3.0, torque_constant=1.0,
                  mass=M2 if masses else 0.0, com=(L2 / 2, 0.0, 0.0), name="j2"),
    )
    return Robot(name="planar", joints=joints, gravity=(0.0, -G, 0.0),
                 tool=ToolSpec(flange_p_load=(L2, 0.0, 0.0), flange_p_markers=(("T", (L2, 0.0, 0.0)),)))


def closed_form_load(theta: np.ndarray, force: np.ndarray) -> np.ndarray:
    """``J^T F - dV/dtheta`` of the planar arm, by hand."""
    t1, t12 = theta[0], theta[0] + theta[1]
    c1, s1, c12, s12 = math.cos(t1), math.sin(t1), math.cos(t12), math.sin(t12)
    g1 = G * (M1 * L1 / 2 * c1 + M2 * (L1 * c1 + L2 / 2 * c12))
    g2 = G * M2 * L2 / 2 * c12
    fx, fy = force[0], force[1]
    e1 = fx * (-L1 * s1 - L2 * s12) + fy * (L1 * c1 + L2 * c12)
    e2 = fx * (-L2 * s12) + fy * (L2 * c12)
    return np.array([e1 - g1, e2 - g2])


def _actuated(robot: Robot, theta: np.ndarray) -> np.ndarray:
    return robot.theta_links(theta)


@pytest.mark.parametrize("theta", [(0.0, 0.0), (0.4, -0.9), (-1.2, 2.1), (2.5, 0.3)])
def test_gravity_and_tip_force_torques_match_the_closed_form(theta):
    robot = planar_arm()
    data = robot.link_model.createData()
    force = np.array([120.0, -450.0, 0.0])
    wrench = np.concatenate([force, np.zeros(3)])
    th = np.array(theta)
    load = physics.load_effort(robot, data, _actuated(robot, th), physics.Loads(wrench=wrench))
    np.testing.assert_allclose(load[robot.actuated_in_link_model], closed_form_load(th, force), rtol=1e-12,
                               atol=1e-9)
    # gravity alone is pin.rnea at rest: the hand-written g and rnea agree
    g = physics.gravity_effort(robot.link_model, data, _actuated(robot, th))[robot.actuated_in_link_model]
    np.testing.assert_allclose(-g, closed_form_load(th, np.zeros(3)), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("q", [(0.3, -0.5), (-0.8, 1.4), (1.0, 0.0)])
def test_deflected_equilibrium_matches_the_closed_form_torques(q):
    """k (theta - q) = J^T F - g at theta, solved by scipy on the closed form, against
    the simulator's own fixed point; and the first-order deflection tau(q)/k with its
    second-order term."""
    robot = planar_arm()
    force = np.array([300.0, -900.0, 0.0])
    loads = physics.Loads(wrench=np.concatenate([force, np.zeros(3)]))
    q = np.array(q)
    sim = physics.solve_equilibrium(robot, q, loads, physics.linear_springs(K, n_link_springs=2))
    exact = scipy.optimize.fsolve(lambda th: K * (th - q) - closed_form_load(th, force), q, xtol=1e-12)
    np.testing.assert_allclose(sim.theta, exact, atol=1e-12)
    np.testing.assert_allclose(sim.gear_torque, K * (exact - q), rtol=1e-9)
    dtheta = sim.theta - q
    assert np.all(np.abs(dtheta) > 1e-4)                      # the arm sags measurably
    first = closed_form_load(q, force) / K                  # closed-form first-order deflection
    jac = scipy.optimize.approx_fprime(q, lambda th: closed_form_load(th, force), 1e-7)
    second = first + (jac @ first) / K
    # the closed form to second order leaves a third-order error: far below the first-order one
    assert np.max(np.abs(dtheta - first)) > 10 * np.max(np.abs(dtheta - second))


def test_tip_position_follows_the_deflected_angles():
    robot = planar_arm()
    data = robot.link_model.createData()
    th = np.array([0.7, -1.1])
    p = physics.frame_positions(robot, data, _actuated(robot, th), ["T"])[0]
    want = [L1 * math.cos(th[0]) + L2 * math.cos(th.sum()), L1 * math.sin(th[0]) + L2 * math.sin(th.sum()), 0.0]
    np.testing.assert_allclose(p, want, atol=1e-12)


HYDRO = CompensatorSpec(kind=CompensatorKind.HYDROPNEUMATIC, joint=2,
                        geometry=(("a", 0.60), ("b", 0.25), ("h", -0.0346)))   # the HH-150 description's
SPRING = CompensatorSpec(kind=CompensatorKind.SPRING, joint=2,
                         geometry=(("a", 0.6938), ("L", 0.18472), ("alpha", 0.1738)))


@pytest.mark.parametrize("spec, params", [(HYDRO, (4771.4, 0.9112)), (SPRING, (2.0e5, 0.5))])
def test_compensator_torque_from_its_pivots(spec, params):
    """The lever-arm torque of the pivots' tension is the papers' closed form with the sign
    of a relief (load = J^T W - g - M), and equals virtual work -F dl/dq."""
    for q in np.linspace(-0.8, 1.6, 9):
        effort = physics.compensator_effort(spec, q, params)
        assert effort == pytest.approx(-float(spec.torque(q, params)), rel=1e-10)
        pivots = physics.compensator_pivots(spec)

        def length(x: float) -> float:
            a, b = pivots.at(x)
            return float(np.linalg.norm(b - a))

        dl = (length(q + 1e-6) - length(q - 1e-6)) / 2e-6
        assert effort == pytest.approx(-physics.compensator_tension(spec, length(q), params) * dl, rel=1e-6)
    # the pivot distance is the papers' length (Y6, K4)
    fixed, moving = physics.compensator_pivots(spec).at(0.37)
    want = spec.hydro_length(0.37) if spec.kind is CompensatorKind.HYDROPNEUMATIC else spec.spring_length(0.37)
    assert np.linalg.norm(moving - fixed) == pytest.approx(float(want), rel=1e-12)


def test_friction_is_supplied_in_the_direction_of_motion():
    dq = np.array([0.1, -0.2, 0.0])
    tau = np.array([-500.0, -500.0, 300.0])
    f = physics.friction_effort(dq, tau, np.array([100.0, 100.0, 100.0]), np.array([50.0, 50.0, 50.0]),
                                np.array([0.1, 0.1, 0.1]))
    np.testing.assert_allclose(f, [100 + 5 + 50, -(100 + 10 + 50), 0.0])


def test_external_effort_is_the_frame_jacobian_transpose():
    """J^T W equals the power balance: W . (frame twist) for any joint velocity."""
    robot = planar_arm(masses=False)
    model = robot.link_model
    data = model.createData()
    rng = np.random.default_rng(5)
    th = rng.uniform(-1, 1, model.nq)
    wrench = rng.normal(size=6) * 100
    effort = physics.external_effort(model, data, th, wrench)
    v = rng.normal(size=model.nv)
    pin.forwardKinematics(model, data, th, v)
    pin.updateFramePlacements(model, data)
    fid = model.getFrameId("load_point")
    twist = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
    assert effort @ v == pytest.approx(wrench[:3] @ twist.linear + wrench[3:] @ twist.angular, rel=1e-10)


def _track_robot() -> Robot:
    """The seven-joint HH-150 on a floor track of tests/test_any_chain.py."""
    import importlib.util
    import pathlib

    from elastocal.formats.robot_toml import parse_robot

    spec = importlib.util.spec_from_file_location("any_chain", pathlib.Path(__file__).with_name("test_any_chain.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return parse_robot(module.track_robot_text(), source="track.toml")


@pytest.mark.parametrize("which", ["hh150", "track"])
def test_the_cell_and_the_description_model_agree_on_any_chain(robot, which):
    """Two computations of the same statics: the simulator's (rnea, frame Jacobian, pivots)
    and the bottom layer's (computeGeneralizedGravity, Robot.load_torque, the closed-form
    compensator) agree at the simulator's equilibrium, on the six-axis arm and on a
    seven-joint arm on a floor track (prismatic first joint, compensator on joint 3)."""
    from elastocal.sims.cell import CellTruth, SimCell

    r = robot if which == "hh150" else _track_robot()
    truth = CellTruth.for_robot(r, compensator=(4771.4, 0.9112)).with_hidden("link_compliance")
    cell = SimCell(r, truth)
    rng = np.random.default_rng(11)
    for _ in range(4):
        q = rng.uniform(0.7 * r.lower + 0.3 * r.upper, 0.3 * r.lower + 0.7 * r.upper)
        w = np.concatenate([rng.normal(0.0, 600.0, 3), rng.normal(0.0, 80.0, 3)])
        eq = cell.equilibrium(q, w)
        th = r.theta_links(eq.theta, eq.link_angles)
        c = r.compensator.index
        model = r.load_torque(th, w, truth.compensator, links=True, q_compensator=eq.theta[c] - r.joints[c].offset)
        np.testing.assert_allclose(eq.gear_torque, model[r.actuated_in_link_model], rtol=1e-9, atol=1e-6)
        # each spring carries its torque: k (theta - theta_rigid) = gear torque
        np.testing.assert_allclose(truth.stiffness * (eq.theta - r.theta(q)), eq.gear_torque, rtol=1e-7, atol=1e-6)
        assert eq.gear_torque.shape == (r.n_joints,) and cell.read_currents(eq, rng).shape == (r.n_joints,)


def test_a_seven_joint_cell_runs_with_friction_in_the_direction_of_motion():
    from elastocal.sims.cell import CellTruth, SimCell
    from elastocal.sims.runs import default_run_truth

    r = _track_robot()
    cell = SimCell(r, default_run_truth(CellTruth.for_robot(r)))
    from elastocal.sims.runs import DEFAULT_COULOMB, TRACK_FRICTION

    assert cell.truth.coulomb[0] == TRACK_FRICTION[0] and tuple(cell.truth.coulomb[1:]) == DEFAULT_COULOMB
    q = (r.lower + r.upper) / 2
    dq = np.linspace(-0.1, 0.1, 7)
    i_move = cell.motion_currents(q, dq)
    i_rest = cell.currents(cell.equilibrium(q))
    xi = r.torque_constants
    np.testing.assert_allclose(xi * (i_move - i_rest), cell.friction_torque(dq, xi * i_rest), rtol=1e-9, atol=1e-9)
    moving = dq != 0
    assert np.all(np.sign(xi * (i_move - i_rest))[moving] == np.sign(dq)[moving])
