"""Compensated trajectories: library, simulated-cell validation, CLI and exports."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from dataclasses import replace

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.compensation.files import read_path, write_path
from elastocal.compensation.ik import PlannedPath, yang_path
from elastocal.compensation.model import CompensationModel
from elastocal.compensation.trajectory import compensate_path, predicted_residual
from elastocal.compensation.validate import YANG_WRENCH, validate_on_sim, yang_validation
from elastocal.errors import InputError
from elastocal.formats.calibration import CalibratedParameter, Calibration, Residual, write_calibration
from elastocal.model.robot import LOAD_FRAME
from elastocal.formats.robot_toml import bundled_robot_path
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.model.kinds import KinematicForm, TorqueSource


@pytest.fixture(scope="module")
def path(robot):
    return yang_path(robot, step_m=0.05)


def _calibration(robot, stiffness, compensator=(4771.4, 0.9112), name=None) -> Calibration:
    params = tuple(CalibratedParameter(f"k{j + 1}", float(k), 1.0, "N*m/rad") for j, k in enumerate(stiffness))
    if compensator is not None:
        params += (CalibratedParameter("C", compensator[0], unit="N*m"),
                   CalibratedParameter("l_c", compensator[1], unit="m"))
    return Calibration(robot=name or robot.name, created="2026-11-22T10:00:00Z", model=("joint_stiffness",),
                       torque=TorqueSource.CURRENT, parameters=params, residual=Residual(rms=8e-6, max=3e-5, n=10))


def test_yang_path_follows_the_line(robot, path):
    p = np.array([robot.positions(robot.theta(q), [LOAD_FRAME])[0] for q in path.q])
    np.testing.assert_allclose(p[:, 1:], np.tile([0.0, 0.116], (len(p), 1)), atol=1e-9)
    np.testing.assert_allclose(p[[0, -1], 0], [1.2, 1.8], atol=1e-9)
    np.testing.assert_allclose(np.diff(path.t), 5.0)  # 50 mm at 10 mm/s
    assert np.all(path.q >= robot.lower) and np.all(path.q <= robot.upper)


def test_exact_compensation_on_the_simulated_cell(robot):
    """Acceptance: exact leaves < 5 % of the uncompensated tool error (here: the
    numerical zero, calibration = truth); first order is reported beside it."""
    result = yang_validation(SimCell(robot, CellTruth()), step_m=0.05)
    s = result.summary()
    assert s["uncompensated"]["max"] > 1e-3          # 1500 N deflects the tool by millimetres
    assert s["ratio_exact"] < 0.05
    assert s["exact"]["max"] < 1e-9
    assert 1e-6 < s["ratio_first_order"] < 0.01       # second-order effects remain
    assert s["prediction_error_max"] < 1e-9           # the model predicts the deflection it removes


def test_compensation_with_an_imperfect_calibration(robot, path):
    truth = CellTruth()
    cell = SimCell(robot, truth)
    model = CompensationModel(robot, truth.stiffness * 1.03, truth.compensator)
    s = validate_on_sim(cell, model, path, YANG_WRENCH).summary()
    # 3 % too stiff: about 3 % of the deflection stays
    assert 0.015 < s["ratio_exact"] < 0.05


def test_rigid_reference_removes_the_sag_as_well(robot, path):
    s = yang_validation(SimCell(robot, CellTruth()), step_m=0.05, reference="rigid").summary()
    assert s["unloaded_sag"]["max"] > 1e-4
    assert s["exact"]["max"] < 1e-9 and s["first_order"]["max"] < 1e-9  # coincide for joint springs


def test_first_order_is_q_minus_c_jt_w(robot, path):
    truth = CellTruth()
    model = CompensationModel(robot, truth.stiffness, truth.compensator)
    res = compensate_path(model, path.q, YANG_WRENCH, form=KinematicForm.FIRST_ORDER)
    jac = robot.jacobians(robot.theta(path.q[3]), [LOAD_FRAME])[0]
    np.testing.assert_allclose(res.dtheta[3], (jac.T @ np.array(YANG_WRENCH)) / truth.stiffness, rtol=1e-12,
                               atol=1e-15)
    residual = predicted_residual(model, compensate_path(model, path.q, YANG_WRENCH))
    assert np.max(np.abs(residual)) < 1e-12


def test_model_without_masses_leaves_gravity_out(robot, path):
    bare = replace(robot, joints=tuple(replace(j, mass=0.0) for j in robot.joints))
    model = CompensationModel(bare, CellTruth().stiffness, (4771.4, 0.9112))
    assert not model.uses_gravity and not model.uses_compensator
    exact = compensate_path(model, path.q, YANG_WRENCH)
    first = compensate_path(model, path.q, YANG_WRENCH, form=KinematicForm.FIRST_ORDER)
    np.testing.assert_allclose(exact.theta_target, bare.theta(path.q))
    np.testing.assert_allclose(exact.q_command, first.q_command, atol=1e-15)


def test_calibration_checks(robot):
    with pytest.raises(InputError, match="robot 'KR-270'"):
        CompensationModel.from_calibration(robot, _calibration(robot, np.ones(6) * 1e5, name="KR-270"))
    cal = _calibration(robot, np.ones(6) * 1e5)
    cal = dataclasses.replace(cal, parameters=tuple(p for p in cal.parameters if p.name != "k4"))
    with pytest.raises(InputError, match="k4"):
        CompensationModel.from_calibration(robot, cal, source="cal.json")
    spring = _calibration(robot, np.ones(6) * 1e5, compensator=None)
    spring = dataclasses.replace(spring, parameters=spring.parameters + (CalibratedParameter("K_c", 1.0),
                                                                         CalibratedParameter("s0", 1.0)))
    with pytest.raises(InputError, match="do not fit"):
        CompensationModel.from_calibration(robot, spring)
    nominal = CompensationModel.from_calibration(robot, _calibration(robot, np.ones(6) * 1e5, compensator=None))
    assert nominal.compensator == (4771.4, 0.9112)    # the description's nominal values


# ------------------------------------------------------------------ CLI
@pytest.fixture()
def files(tmp_path, robot, path):
    write_path(tmp_path / "path.csv", path)
    write_calibration(tmp_path / "cal.json", _calibration(robot, CellTruth().stiffness))
    return tmp_path


def _cli(files, *extra):
    return ["compensate", "--robot", str(bundled_robot_path()), "--calibration", str(files / "cal.json"),
            "--path", str(files / "path.csv"), "--out", str(files / "out.csv"), *extra]


def test_cli_csv_krl_rapid(files, robot, path, capsys):
    code = main(_cli(files, "--wrench", "0,0,1500,0,0,0", "--krl", str(files / "yang.src"),
                     "--rapid", str(files / "yang.mod"), "--json", "--validate"))
    out = capsys.readouterr()
    assert code == 0, out.err
    obj = json.loads(out.out)
    assert obj["n"] == len(path) and obj["form"] == "exact" and obj["reference"] == "unloaded"
    assert obj["deflection"]["max"] > 1e-3 and obj["residual"]["max"] < 1e-12
    assert obj["validation"]["ratio_exact"] < 0.05
    with open(files / "out.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == (["t"] + [f"q{j}" for j in range(1, 7)] + ["fx", "fy", "fz", "mx", "my", "mz"]
                             + [f"qc{j}" for j in range(1, 7)] + ["dx", "dy", "dz"])
    truth = CellTruth()
    lib = compensate_path(CompensationModel(robot, truth.stiffness, truth.compensator), path.q, YANG_WRENCH)
    qc = np.array([[float(r[f"qc{j}"]) for j in range(1, 7)] for r in rows])
    np.testing.assert_allclose(qc, lib.q_command, rtol=0, atol=1e-15)
    d = np.array([[float(r[k]) for k in ("dx", "dy", "dz")] for r in rows])
    np.testing.assert_allclose(d, lib.tcp_deflection, atol=1e-15)
    # KRL: one PTP per point, degrees, approximated except the last
    krl = (files / "yang.src").read_text()
    ptp = re.findall(r"PTP \{AXIS: A1 (\S+), A2 (\S+), A3 (\S+), A4 (\S+), A5 (\S+), A6 (\S+)\}( C_PTP)?", krl)
    assert len(ptp) == len(path) and krl.startswith("&ACCESS RVP\nDEF yang( )") and krl.rstrip().endswith("END")
    np.testing.assert_allclose(np.array([[float(v) for v in m[:6]] for m in ptp]), np.degrees(lib.q_command),
                               atol=1e-6)
    assert all(m[6] for m in ptp[:-1]) and not ptp[-1][6]
    # RAPID: MoveAbsJ per point, degrees, timed by the path
    rapid = (files / "yang.mod").read_text()
    moves = re.findall(r"MoveAbsJ \[\[([^\]]+)\],\[9E9(?:,9E9){5}\]\]\\NoEOffs, (\S+), (\S+), tool0;", rapid)
    assert len(moves) == len(path) and rapid.startswith("MODULE yang") and "ENDMODULE" in rapid
    np.testing.assert_allclose(np.array([[float(v) for v in m[0].split(",")] for m in moves]),
                               np.degrees(lib.q_command), atol=1e-6)
    assert moves[1][1] == "v1000\\T:=5.0000" and moves[-1][2] == "fine"


def test_cli_wrench_per_sample_and_first_order(files, robot, path, capsys):
    w = np.tile(YANG_WRENCH, (len(path), 1))
    w[:, 0] = np.linspace(0.0, -400.0, len(path))
    write_path(files / "path.csv", PlannedPath(t=path.t, q=path.q, wrench=w))
    assert main(_cli(files, "--form", "first-order", "--json")) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["form"] == "first-order"
    assert 1e-8 < obj["residual"]["max"] < 1e-4
    back = read_path(files / "path.csv", robot)
    np.testing.assert_allclose(back.wrench, w)


@pytest.mark.parametrize("case, message", [
    ("none", "no process wrench"),
    ("both", "not both"),
    ("badwrench", "--wrench"),
    ("degrees", "column q2"),
    ("robot", "KR-270"),
])
def test_cli_input_errors_one_line_exit_2(files, robot, path, capsys, case, message):
    extra = []
    if case == "both":
        write_path(files / "path.csv", PlannedPath(t=path.t, q=path.q, wrench=np.zeros((len(path), 6))))
        extra = ["--wrench", "0,0,1,0,0,0"]
    elif case == "badwrench":
        extra = ["--wrench", "0,0,1500,0"]      # 3 or 6 numbers: FX,FY,FZ[,MX,MY,MZ]
    elif case == "degrees":
        write_path(files / "path.csv", PlannedPath(t=path.t, q=np.degrees(path.q)))
        extra = ["--wrench", "0,0,1500,0,0,0"]
    elif case == "robot":
        write_calibration(files / "cal.json", _calibration(robot, CellTruth().stiffness, name="KR-270"))
        extra = ["--wrench", "0,0,1500,0,0,0"]
    code = main(_cli(files, *extra))
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and message in err
    assert not (files / "out.csv").exists()
