"""Batched compensation: the batched chain against Pinocchio, and every
compensated path identical to the per-point implementation it replaced.

``tests/data/compensation_reference.npz`` holds the results of the per-point Pinocchio
implementation (commit 39d2c42, one ``computeFrameJacobian``/``computeGeneralizedGravity``
call per sample and iteration), made by ``tests/helpers/make_compensation_reference.py``
before the batched kernel replaced it: 7 models (gravity and compensator, no compensator,
no masses, the URDF robot, a marker as tool, a geometric calibration with the nominal
reference), both forms, every reference, commands, targets, predicted deflections and
predicted residuals.
"""

from __future__ import annotations

import importlib.util
import pathlib

import numpy as np
import pinocchio as pin
import pytest

from elastocal.compensation.chain import TAYLOR_LIMIT_RAD, Angles, BatchedChain
from elastocal.compensation.model import BLOCK_SAMPLES, WARM_STRIDE, CompensationModel, NotConverged, StaticKernel
from elastocal.compensation.trajectory import compensate_path, predicted_residual
from elastocal.identify import kinematics as kin
from elastocal.model.robot import LOAD_FRAME
from elastocal.formats.robot_toml import bundled_robot_path, load_robot
from elastocal.sims.cell import CellTruth
from elastocal.model.kinds import KinematicForm

HERE = pathlib.Path(__file__).parent
REFERENCE = HERE / "data" / "compensation_reference.npz"


def _reference_cases():
    spec = importlib.util.spec_from_file_location("make_compensation_reference",
                                                  HERE / "helpers" / "make_compensation_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.cases()


def _robots(robot):
    rng = np.random.default_rng(7)
    names = kin.parameter_names(robot, robot.marker_names)
    geometry = kin.corrected_robot(robot, names, rng.normal(size=len(names)) * 2e-4)
    return {"dh": robot, "urdf": load_robot(bundled_robot_path("hh150_urdf")), "geometry": geometry}


@pytest.mark.parametrize("which", ["dh", "urdf", "geometry", "links"])
def test_batched_chain_equals_pinocchio(robot, which):
    """Positions, J^T W - g and Jacobians of every frame on the last joint, to 1e-12, on random
    configurations; ``links`` is the link-spring model (10 joints, unaligned axes)."""
    rob = robot if which == "links" else _robots(robot)[which]
    model = rob.link_model if which == "links" else rob.model
    data = model.createData()
    chain = BatchedChain(model)
    rng = np.random.default_rng(3)
    n = 50
    theta = rng.uniform(-np.pi, np.pi, (n, model.nq))
    wrench = rng.normal(size=(n, 6)) * np.array([800, 800, 800, 80, 80, 80])
    ang = Angles.of(theta.T)
    state = chain.state(ang, masses=True)
    fid = model.getFrameId(LOAD_FRAME)
    tau = chain.torque(state, force=wrench[:, :3].T, moment=wrench[:, 3:].T, frame_id=fid)
    frames = [f for f in range(len(model.frames)) if model.frames[f].parentJoint == model.njoints - 1]
    assert len(frames) >= 5                                 # flange, load point and the markers
    for i in range(n):
        jac = pin.computeFrameJacobian(model, data, theta[i], fid, pin.LOCAL_WORLD_ALIGNED)
        want = jac.T @ wrench[i] - pin.computeGeneralizedGravity(model, data, theta[i])
        np.testing.assert_allclose(tau[:, i], want, rtol=0, atol=1e-12 * max(1.0, np.abs(want).max()))
        pin.framesForwardKinematics(model, data, theta[i])
        for f in frames:
            np.testing.assert_allclose(chain.position(state, f)[:, i], data.oMf[f].translation, rtol=0, atol=1e-14)
    jac = chain.jacobian(chain.state(ang), fid)
    for i in range(0, n, 7):
        want = pin.computeFrameJacobian(model, data, theta[i], fid, pin.LOCAL_WORLD_ALIGNED)
        np.testing.assert_allclose(jac[:, :, i], want, rtol=0, atol=1e-14)
    rate = rng.normal(size=(model.nq, n)) * 1e-3
    np.testing.assert_allclose(chain.point_velocity(state, fid, rate),
                               np.einsum("ijn,jn->in", jac[:3], rate), rtol=0, atol=1e-15)


def test_gravity_alone_and_no_masses(robot):
    from dataclasses import replace

    bare = replace(robot, joints=tuple(replace(j, mass=0.0) for j in robot.joints))
    theta = np.random.default_rng(4).uniform(-2, 2, (20, 6))
    for rob in (robot, bare):
        model, data = rob.model, rob.model.createData()
        chain = BatchedChain(model)
        tau = chain.torque(chain.state(Angles.of(theta.T), masses=True))
        want = -np.array([pin.computeGeneralizedGravity(model, data, th) for th in theta])
        np.testing.assert_allclose(tau.T, want, rtol=0, atol=1e-11)
    assert not np.any(tau)                                  # no masses, no wrench: no torque


def test_angles_near_a_base_are_numpys_cos_and_sin():
    rng = np.random.default_rng(5)
    base = Angles.of(rng.uniform(-np.pi, np.pi, (6, 1000)))
    for spread in (1e-9, 1e-4, TAYLOR_LIMIT_RAD):
        theta = base.theta + rng.uniform(-spread, spread, base.theta.shape)
        near = base.near(theta)
        np.testing.assert_allclose(near.cos, np.cos(theta), rtol=0, atol=4e-16)
        np.testing.assert_allclose(near.sin, np.sin(theta), rtol=0, atol=4e-16)
    far = base.near(base.theta + 0.5)                      # beyond the series: numpy's own
    np.testing.assert_array_equal(far.cos, np.cos(base.theta + 0.5))


def test_every_case_is_identical_to_the_per_point_implementation():
    """Results identical to the per-point implementation to 1e-9 (rad, m). The fixed points
    agree to about 1e-15; the nominal reference's targets to its Newton tolerance (1e-12 on the
    SE(3) error), reached from other starts (the per-point Newton started from the previous
    sample's solution, the batched one from its neighbours' interpolated)."""
    ref = np.load(REFERENCE)
    checked = 0
    worst = 0.0
    for name, (model, q, w) in _reference_cases().items():
        np.testing.assert_array_equal(ref[f"{name}/q"], q)
        np.testing.assert_array_equal(ref[f"{name}/wrench"], np.broadcast_to(w, q.shape))
        refs = ("unloaded", "rigid") + (("nominal",) if model.nominal is not None else ())
        for form in KinematicForm:
            for reference in refs:
                path = compensate_path(model, q, w, form=form, reference=reference)
                key = f"{name}/{form}/{reference}"
                got = {"q_command": path.q_command, "theta_target": path.theta_target,
                       "tcp_deflection": path.tcp_deflection, "residual": predicted_residual(model, path)}
                for what, value in got.items():
                    diff = np.abs(value - ref[f"{key}/{what}"]).max()
                    assert diff <= 1e-9, (key, what, diff)
                    if reference == "nominal":
                        assert diff < 1e-11, (key, what, diff)
                    else:
                        worst = max(worst, diff)
                    checked += 1
    assert checked == 4 * (6 * 4 + 6)
    assert worst < 1e-13


def _dense(robot, n):
    from elastocal.compensation.ik import yang_path

    coarse = yang_path(robot, step_m=0.02)
    s, s_new = np.linspace(0, 1, len(coarse)), np.linspace(0, 1, n)
    return np.column_stack([np.interp(s_new, s, coarse.q[:, j]) for j in range(6)])


def test_warm_start_and_blocks_do_not_change_the_result(robot):
    """A path longer than a block, solved warm-started, equals every sample solved alone from a
    cold start (the per-sample iteration of the fixed point), and the samples' order does not matter."""
    truth = CellTruth()
    model = CompensationModel(robot, truth.stiffness, truth.compensator)
    n = BLOCK_SAMPLES + 3 * WARM_STRIDE + 5
    q = _dense(robot, n)
    w = np.array([0.0, 0.0, 1500.0, 0.0, 0.0, 0.0]) + np.sin(np.arange(n) / 50.0)[:, None] * 300.0
    path = compensate_path(model, q, w)
    k = StaticKernel(model)
    some = np.r_[0, 1, WARM_STRIDE - 1, WARM_STRIDE, BLOCK_SAMPLES - 1, BLOCK_SAMPLES, BLOCK_SAMPLES + 7, n - 2, n - 1]
    alone = np.array([k.equilibrium(q[i:i + 1], np.zeros((1, 6)))[0] for i in some])
    np.testing.assert_allclose(path.theta_target[some], alone, rtol=0, atol=1e-13)
    loaded = np.array([k.equilibrium(path.q_command[i:i + 1], w[i:i + 1])[0] for i in some])
    np.testing.assert_allclose(loaded, path.theta_target[some], rtol=0, atol=1e-13)   # the commands work
    order = np.random.default_rng(6).permutation(n)
    shuffled = compensate_path(model, q[order], w[order])
    np.testing.assert_allclose(shuffled.q_command, path.q_command[order], rtol=0, atol=1e-13)
    np.testing.assert_allclose(shuffled.tcp_deflection, path.tcp_deflection[order], rtol=0, atol=1e-13)


@pytest.mark.parametrize("bad", [[3], [WARM_STRIDE * 3], [40, WARM_STRIDE * 2], [BLOCK_SAMPLES + 9, BLOCK_SAMPLES + 20]])
def test_a_load_too_large_names_the_first_sample_without_a_fixed_point(robot, bad):
    truth = CellTruth()
    model = CompensationModel(robot, truth.stiffness, truth.compensator)
    n = BLOCK_SAMPLES + 100
    q = _dense(robot, n)
    w = np.tile([0.0, 0.0, 1500.0, 0.0, 0.0, 0.0], (n, 1))
    w[bad, 1] = -4e7
    with pytest.raises(NotConverged) as err:
        compensate_path(model, q, w)
    assert err.value.sample == min(bad)
    assert f"at sample {min(bad) + 1} of the path" in str(err.value)


def test_log6_equals_pinocchios_at_every_angle():
    from elastocal.compensation.chain import log6_local

    rng = np.random.default_rng(8)
    scales = np.repeat([1e-10, 1e-6, 3e-3, 1e-2, 3e-2, 0.09, 0.2, 1.0, 2.5], 30)
    start = [pin.SE3.Random() for _ in scales]
    target = [m * pin.exp6(pin.Motion(rng.normal(size=6) * sc)) for m, sc in zip(start, scales)]

    def stack(poses):
        return np.stack([m.rotation for m in poses], axis=-1), np.stack([m.translation for m in poses], axis=-1)

    got = log6_local(*stack(start), *stack(target))
    want = np.stack([pin.log6(m.actInv(t)).vector for m, t in zip(start, target)], axis=-1)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)   # near pi the log loses digits


def test_frame_rotations_equal_pinocchios(robot):
    for rob in _robots(robot).values():
        model, data = rob.model, rob.model.createData()
        chain = BatchedChain(model)
        theta = np.random.default_rng(9).uniform(-np.pi, np.pi, (20, 6))
        st = chain.state(Angles.of(theta.T))
        for fid in (model.getFrameId(LOAD_FRAME), rob.frame_id(rob.marker_names[0])):
            rot = chain.rotation(st, fid)
            for i, th in enumerate(theta):
                pin.framesForwardKinematics(model, data, th)
                np.testing.assert_allclose(rot[:, :, i], data.oMf[fid].rotation, rtol=0, atol=1e-14)


def test_nominal_targets_name_the_first_point_the_calibrated_robot_cannot_reach(robot):
    """A drawing with a 0.8 m longer forearm: the batched, warm-started Newton refuses the path
    naming the first point that no Newton reaches when each point is solved alone."""
    from dataclasses import replace

    from elastocal.errors import InputError

    longer = replace(robot, joints=tuple(replace(j, a=j.a + 0.8) if i == 2 else j for i, j in enumerate(robot.joints)))
    truth = CellTruth()
    k = StaticKernel(CompensationModel(robot, truth.stiffness, truth.compensator, nominal=longer))
    n = 80
    q = np.tile([0.0, 0.3, -0.3, 0.0, 0.5, 0.0], (n, 1))
    q[:, 1] = np.linspace(-0.5, 1.2, n)
    q[:, 2] = np.linspace(1.5, -0.5, n)
    alone = []
    for i in range(n):
        try:
            k.nominal_targets(q[i:i + 1])
            alone.append(True)
        except InputError:
            alone.append(False)
    first = alone.index(False)
    assert 0 < first < n - 20 and not alone[-1] and sum(alone) > n // 2
    with pytest.raises(InputError, match=f"reaches point {first + 1} of the path as the drawing does"):
        k.nominal_targets(q)
    reachable = np.flatnonzero(alone)[-40:]                       # a run of reachable points in the middle
    targets = k.nominal_targets(q[reachable])
    drawn = np.array([longer.positions(longer.theta(qi), [robot.marker_names[0]])[0] for qi in q[reachable]])
    k_marker = StaticKernel(CompensationModel(robot, truth.stiffness, truth.compensator, nominal=longer,
                                              tool=robot.marker_names[0]))
    got = k_marker.positions(k_marker.nominal_targets(q[reachable]))
    np.testing.assert_allclose(got, drawn, rtol=0, atol=1e-12)
    assert targets.shape == (len(reachable), 6)


# ------------------------------------------------------------------ path files
def _old_deg(v: float) -> str:
    return f"{round(float(v), 6) + 0.0:.6f}"


def _old_krl(name, t, result):
    """format_krl as it was written per value before the batched kernel (the reference for the bytes)."""
    deg = np.degrees(result.q_command)
    lines = ["&ACCESS RVP", f"DEF {name}( )"] + _old_header(result, ";")
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    lines += [f"; planned duration {duration:.3f} s: set the axis speed (BAS #VEL_PTP) to match",
              "  BAS(#INITMOV, 0)", "  $APO.CPTP = 1"]
    for i, row in enumerate(deg):
        axes = ", ".join(f"A{j + 1} {_old_deg(v)}" for j, v in enumerate(row))
        lines.append(f"  PTP {{AXIS: {axes}}}" + (" C_PTP" if i < len(deg) - 1 else ""))
    return "\n".join(lines + ["END"]) + "\n"


def _old_rapid(name, t, result):
    deg = np.degrees(result.q_command)
    lines = [f"MODULE {name}"] + ["  " + s for s in _old_header(result, "!")] + ["  PROC main()"]
    for i, row in enumerate(deg):
        target = "[[" + ",".join(_old_deg(v) for v in row) + "],[9E9,9E9,9E9,9E9,9E9,9E9]]"
        speed = "v100" if i == 0 else f"v1000\\T:={max(float(t[i] - t[i - 1]), 1e-3):.4f}"
        zone = "fine" if i == len(deg) - 1 else "z1"
        lines.append(f"    MoveAbsJ {target}\\NoEOffs, {speed}, {zone}, tool0;")
    return "\n".join(lines + ["  ENDPROC", "ENDMODULE"]) + "\n"


def _old_header(result, comment):
    return [f"{comment} elastocal compensated joint path: {len(result)} points, form {result.form}, "
            f"reference {result.reference}",
            f"{comment} joint angles in degrees; compensation removes up to "
            f"{1e3 * float(np.max(np.linalg.norm(result.tcp_deflection, axis=1))):.3f} mm of tool deflection"]


def test_programs_and_csv_are_the_bytes_the_per_value_writers_wrote(robot, tmp_path):
    """KRL, RAPID and the compensated CSV written a line at a time are byte-identical to the
    per-value writers, also for ties at the 7th decimal of a degree, tiny negative angles
    (never "-0.000000") and a zero time step (the 1 ms floor)."""
    import csv
    from dataclasses import replace

    from elastocal.compensation.files import format_krl, format_rapid, write_compensated_csv

    truth = CellTruth()
    model = CompensationModel(robot, truth.stiffness, truth.compensator)
    q = _dense(robot, 600)
    result = compensate_path(model, q, np.array([0.0, 0.0, 1500.0, 0.0, 0.0, 0.0]))
    qc = result.q_command.copy()
    special = np.radians([-0.0, -4e-7, -5e-7, -6e-7, 1.0000005, -2.0000005, 5e-7, 12.3456785, -179.9999995])
    qc[:len(special), 0] = special
    qc[100:300] = np.radians(np.round(np.random.default_rng(10).uniform(-180, 180, (200, 6)), 7))
    result = replace(result, q_command=qc)
    t = np.arange(len(q)) * 0.004
    t[5] = t[4]
    assert format_krl("p", t, result) == _old_krl("p", t, result)
    assert format_rapid("p", t, result) == _old_rapid("p", t, result)
    assert "-0.000000" not in format_krl("p", t, result)
    write_compensated_csv(tmp_path / "c.csv", t, result)
    rows = list(csv.reader(open(tmp_path / "c.csv", encoding="utf-8")))
    want = np.column_stack([t, result.q_planned, result.wrench, result.q_command, result.tcp_deflection])
    assert rows[0][0] == "t" and len(rows) == len(q) + 1
    assert all(r == [repr(float(v)) for v in w] for r, w in zip(rows[1:], want))


def test_reading_a_path_in_one_pass_equals_the_row_by_row_reader(robot, monkeypatch):
    from elastocal.compensation import files

    q = _dense(robot, 500)
    lines = ["q3,t,q1,q2,fx,fy,fz,mx,my,mz,q4,q5,q6"]          # columns in any order
    for i, qi in enumerate(q):
        fmt = (lambda x: repr(float(x)), lambda x: f" {x:.9e} ", lambda x: f"{x:+.12f}")[i % 3]
        lines.append(",".join([fmt(qi[2]), repr(i * 0.002), fmt(qi[0]), fmt(qi[1]), "0", "1e-3", "1500.", ".0",
                               "-0", "0", fmt(qi[3]), fmt(qi[4]), fmt(qi[5])]))
    text = "\n".join(lines) + "\n"
    fast = files.parse_path(text, robot)
    from elastocal.formats.tables import csv_records

    records = list(csv_records(text, "x"))
    header = records[0][1]
    assert files._parse_plain(records[1:], header, {c: i for i, c in enumerate(header)}, robot, True) is not None
    monkeypatch.setattr(files, "_parse_plain", lambda *args: None)
    slow = files.parse_path(text, robot)
    for what in ("t", "q", "wrench", "line"):
        np.testing.assert_array_equal(getattr(fast, what), getattr(slow, what))
    np.testing.assert_array_equal(fast.line, np.arange(2, len(q) + 2))
    monkeypatch.undo()
    gap = files.parse_path("\n".join(lines[:10] + [""] + lines[10:]) + "\n", robot)   # a blank line: lines shift
    np.testing.assert_array_equal(gap.line, np.r_[np.arange(2, 11), np.arange(12, len(q) + 3)])
    np.testing.assert_array_equal(gap.q, fast.q)
