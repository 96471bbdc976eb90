"""Every sign and unit that touches hardware, from first principles (docs/physics.md, "Signs
and units at the hardware", names the source of each).

* CiA 402 (CiA 402-2 / IEC 61800-7-201): current actual value 0x6078 and torque actual value
  0x6077 are INTEGER16 in per-mille of the rated current 0x6075 [mA] and rated motor torque
  0x6076 [mN·m]; position in encoder increments, 0x608F increments per motor revolution
  and 0x6091 motor revolutions per shaft revolution.
* Modbus (Modbus Application Protocol V1.1b3 §4.2): 16-bit big-endian registers, signed
  types in two's complement, 32-bit values over two registers in the map's word order.
* Joint direction and torque constant: ``xi i`` is the torque the joint carries, so a
  hung weight makes every joint deflect ``xi i / k`` in the direction that lowers it.
* Tracker: readings in metres in a right-handed frame, a rigid placement of the base.
* Friction and gravity torques against ``pin.rnea`` at the simulated equilibrium.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from elastocal.drivers.canopen_drive import CURRENT_OBJECT, POSITION_OBJECT, STATUS_OBJECT, TORQUE_OBJECT, \
    VELOCITY_OBJECT, CanopenDrive
from elastocal.drivers.modbus import decode, encode
from elastocal.drivers.registers import RegisterSpec
from elastocal.model.robot import LOAD_FRAME
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.runs import default_run_truth


def _cia402_drive(sdo: dict) -> CanopenDrive:
    """The driver's decoding without a bus: its SDO reads answered from ``sdo``."""
    drive = object.__new__(CanopenDrive)
    drive.name, drive.joint, drive.node_id = "drive1", 1, 1
    drive._sdo = lambda index, sub=None: sdo[(index, sub)]
    drive._call = lambda what, fn: fn()
    drive._read_factors()
    return drive


SDO = {(0x1000, None): 0x00020192, (0x6075, None): 4000, (0x6076, None): 2000,
       (0x608F, 1): 4096, (0x608F, 2): 1, (0x6091, 1): 120, (0x6091, 2): 1}


def test_cia402_current_and_torque_are_per_mille_of_the_rated_values():
    drive = _cia402_drive(SDO)
    assert drive.rated_current_a == 4.0 and drive.rated_torque_nm == 2.0 and drive.gear_ratio == 120.0
    quarter_turn = 4096 * 120 // 4      # increments of a quarter of a joint revolution
    s = drive._sample(7, {POSITION_OBJECT: quarter_turn, CURRENT_OBJECT: -250, TORQUE_OBJECT: 500,
                          VELOCITY_OBJECT: -4096 * 120, STATUS_OBJECT: 0x0237})
    assert s.current_a == pytest.approx(-1.0)               # -250 ‰ of 4 A, signed
    assert s.torque_nm == pytest.approx(0.5 * 2.0 * 120)     # 500 ‰ of 2 N·m at the motor, times the gear
    assert s.position_rad == pytest.approx(math.pi / 2)
    assert s.velocity_rad_s == pytest.approx(-2 * math.pi)   # one joint revolution a second, backward


def test_a_drive_that_is_not_cia402_is_refused():
    from elastocal.errors import ProtocolError

    with pytest.raises(ProtocolError, match="not a CiA 402 drive"):
        _cia402_drive({**SDO, (0x1000, None): 0x00020191})


def test_modbus_registers_are_big_endian_twos_complement_scaled_to_si():
    current = RegisterSpec(name="current", address=0, type="int16", scale=10.0, unit="mA")
    assert decode(current, [0xFF38]) == [pytest.approx(-2.0)]       # -200 * 10 mA
    assert decode(current, [0x00C8]) == [pytest.approx(2.0)]
    assert encode(current, [-2.0]) == [0xFF38]
    wide = RegisterSpec(name="position", address=0, type="int32", scale=1e-6, unit="rad")
    assert decode(wide, [0xFFFF, 0xFF38]) == [pytest.approx(-200e-6)]  # high word first
    little = RegisterSpec(name="position", address=0, type="int32", scale=1e-6, unit="rad", word_order="little")
    assert decode(little, [0xFF38, 0xFFFF]) == [pytest.approx(-200e-6)]
    unsigned = RegisterSpec(name="status", address=0, type="uint16")
    assert decode(unsigned, [0xFF38]) == [float(0xFF38)]


def test_a_hung_weight_lowers_the_load_point_through_xi_i_over_k(robot):
    """Joint direction and torque constant: the current change of each joint, times xi and
    over k, is the joint's deflection, and those deflections lower the weight (the
    weight's work is positive), as the load point itself moves in the simulator."""
    truth = CellTruth(current_noise_a=0.0, tracker_noise_m=0.0)
    cell = SimCell(robot, truth)
    q = np.array([0.3, 0.4, -0.3, 0.2, 1.1, -0.4])
    w = np.array([0.0, 0.0, -1500.0, 0.0, 0.0, 0.0])
    rest, loaded = cell.equilibrium(q), cell.equilibrium(q, w)
    dtheta = robot.torque_constants * (cell.currents(loaded) - cell.currents(rest)) / truth.stiffness
    data = robot.model.createData()
    jac = pin.computeFrameJacobian(robot.model, data, rest.theta, robot.model.getFrameId(LOAD_FRAME),
                                   pin.LOCAL_WORLD_ALIGNED)
    dz_first_order = (jac[:3] @ dtheta)[2]
    dz = (cell.load_point(loaded) - cell.load_point(rest))[2]
    assert dz < -1e-4 and dz_first_order < 0
    assert dz_first_order == pytest.approx(dz, rel=0.05)
    assert w @ np.concatenate([jac[:3] @ dtheta, jac[3:] @ dtheta]) > 0


def test_tracker_readings_are_metres_in_a_right_handed_rigid_frame(robot):
    truth = CellTruth(current_noise_a=0.0, tracker_noise_m=0.0)
    cell = SimCell(robot, truth)
    eq = cell.equilibrium(np.array([0.1, 0.2, -0.2, 0.3, 0.9, 0.5]))
    markers = list(robot.marker_names)
    base = cell.marker_positions(eq, markers)
    tracker = cell.tracker_positions(eq, markers)
    # distances between markers are the description's flange offsets [m], in either frame
    flange = dict(robot.tool.flange_p_markers)
    for a in range(len(markers)):
        for b in range(a + 1, len(markers)):
            d = np.linalg.norm(np.subtract(flange[markers[a]], flange[markers[b]]))
            assert np.linalg.norm(tracker[a] - tracker[b]) == pytest.approx(d, abs=1e-9)
            assert np.linalg.norm(base[a] - base[b]) == pytest.approx(d, abs=1e-9)
    # right-handed: the triple product of three markers and the load point keeps its sign
    base4 = np.vstack([base[:3], cell.load_point(eq)])
    tracker4 = np.vstack([tracker[:3], cell.to_tracker(cell.load_point(eq)[None, :])])
    tri = lambda p: np.linalg.det(np.array([p[1] - p[0], p[2] - p[0], p[3] - p[0]]))  # noqa: E731
    assert abs(tri(base4)) > 1e-6 and np.sign(tri(tracker4)) == np.sign(tri(base4))
    assert np.linalg.det(truth.tracker_rotation) == pytest.approx(1.0)


def test_motion_currents_are_rnea_gravity_jacobian_load_compensator_and_friction(robot):
    """At the simulated equilibrium: xi i = J^T W - rnea(theta, 0, 0) - M(q2) + friction, with
    pin.rnea and the frame Jacobian called here on the link model, the compensator's closed
    form (Y11), and friction in the direction of motion."""
    truth = default_run_truth(CellTruth(current_noise_a=0.0))
    cell = SimCell(robot, truth)
    q = np.array([-0.2, 0.5, -0.6, 0.4, 1.2, 0.3])
    dq = np.array([0.05, -0.03, 0.02, -0.04, 0.01, 0.06])
    w = np.array([400.0, -200.0, -900.0, 30.0, -20.0, 10.0])
    eq = cell.equilibrium(q, w)
    model = robot.link_model
    data = model.createData()
    th = robot.theta_links(eq.theta, eq.link_angles)
    act = robot.actuated_in_link_model
    gravity = pin.rnea(model, data, th, np.zeros(model.nv), np.zeros(model.nv))[act]
    jac = pin.computeFrameJacobian(model, data, th, model.getFrameId(LOAD_FRAME), pin.LOCAL_WORLD_ALIGNED)
    tau = (jac.T @ w)[act] - gravity
    tau[1] -= float(robot.compensator.torque(eq.theta[1] - robot.joints[1].offset, truth.compensator))
    friction = truth.coulomb * np.sign(dq) + truth.viscous * dq + truth.load_friction * np.abs(tau) * np.sign(dq)
    got = robot.torque_constants * cell.motion_currents(q, dq, w)
    np.testing.assert_allclose(got, tau + friction, rtol=1e-9, atol=1e-6)
    assert np.all(np.sign(got - tau) == np.sign(dq))
