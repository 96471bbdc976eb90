"""`elastocal sim path` (README, "Try every command"): Yang's process path under a constant
wrench, read back by the path reader, compensated by `compensate`; bad flags refused, nothing
written."""

import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.compensation.files import read_path
from elastocal.compensation.ik import yang_path
from elastocal.formats.robot_toml import bundled_robot, load_robot
from elastocal.model.kinds import TorqueSource


def test_sim_path_writes_yangs_line_under_the_wrench(tmp_path, capsys):
    assert main(["sim", "path", "--out", str(tmp_path / "p"), "--wrench", "0,200,-1500", "--json"]) == 0
    written = json.loads(capsys.readouterr().out)
    robot = load_robot(written["robot"])
    assert robot.name == bundled_robot().name
    planned = read_path(written["path"], robot)
    reference = yang_path(bundled_robot())
    assert written["points"] == len(planned) == len(reference) == 121     # 0.6 m in 5 mm steps
    np.testing.assert_allclose(planned.q, reference.q, rtol=0, atol=1e-15)
    np.testing.assert_allclose(planned.t, reference.t, rtol=0, atol=1e-15)
    assert np.array_equal(planned.wrench, np.tile([0.0, 200.0, -1500.0, 0.0, 0.0, 0.0], (121, 1)))
    # the tool point runs along x at z 0.116 m (Yang Table 8)
    import pinocchio as pin

    from elastocal.model.robot import LOAD_FRAME

    model = robot.model
    data = model.createData()
    tool = []
    for q in planned.q[[0, 60, 120]]:
        pin.forwardKinematics(model, data, robot.theta(q))
        tool.append(pin.updateFramePlacement(model, data, robot.frame_id(LOAD_FRAME)).translation.copy())
    tool = np.array(tool)
    np.testing.assert_allclose(tool[:, 1:], [[0.0, 0.116]] * 3, atol=1e-5)
    np.testing.assert_allclose(tool[:, 0], [1.2, 1.5, 1.8], atol=1e-5)

def test_sim_path_feeds_compensate(tmp_path, capsys):
    from elastocal.formats.calibration import CalibratedParameter, Calibration, write_calibration

    assert main(["sim", "path", "--out", str(tmp_path)]) == 0
    params = tuple(CalibratedParameter(f"k{j}", v, v * 1e-3, "N*m/rad")
                   for j, v in enumerate((559e3, 1435e3, 1829e3, 184e3, 171e3, 70e3), start=1))
    write_calibration(tmp_path / "cal.json", Calibration(robot="HH-150", created="2026-01-05T08:00:00Z",
                                                          model=("joint_stiffness",), torque=TorqueSource.CURRENT,
                                                          parameters=params))
    capsys.readouterr()
    assert main(["compensate", "--robot", str(tmp_path / "robot.toml"), "--calibration", str(tmp_path / "cal.json"),
                 "--path", str(tmp_path / "path.csv"), "--out", str(tmp_path / "out.csv"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    # Yang's 1500 N deflect the HH-150's tool by millimetres (docs/compensation.md: 2.94 mm at most)
    assert 2e-3 < obj["deflection"]["max"] < 4e-3, obj


@pytest.mark.parametrize("argv, flag", [(["--wrench", "1,2"], "--wrench"), (["--wrench", "a,b,c"], "--wrench"),
                                        (["--step", "0"], "--step"), (["--step", "nan"], "--step")])
def test_sim_path_bad_flags_write_nothing(tmp_path, capsys, argv, flag):
    assert main(["sim", "path", "--out", str(tmp_path / "p"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{flag}:" in err
    assert not (tmp_path / "p").exists()


def test_sim_path_refuses_an_existing_path_unless_force(tmp_path, capsys):
    assert main(["sim", "path", "--out", str(tmp_path)]) == 0
    (tmp_path / "path.csv").write_text("mine\n")
    assert main(["sim", "path", "--out", str(tmp_path)]) == 2
    assert "already exists; choose another --out, or --force" in capsys.readouterr().err
    assert (tmp_path / "path.csv").read_text() == "mine\n"
    assert main(["sim", "path", "--out", str(tmp_path), "--force"]) == 0
    assert (tmp_path / "path.csv").read_text().startswith("t,q1,q2,q3,q4,q5,q6,fx,fy,fz,mx,my,mz\n")
