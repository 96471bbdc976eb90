"""Where elastocal's results leave it (the integrator's first day): each output stays
right in another tool's, a timer's or a colleague's hands. Small simulated data, seeded."""

import json

import pytest

from elastocal.cli import main


@pytest.fixture(scope="module")
def absolute_calibration(tmp_path_factory):
    """A geometry calibration of the simulated cell (seed 2) and a second day's table (seed 3)."""
    root = tmp_path_factory.mktemp("abs")
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "2", "--out", str(root / "a")]) == 0
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "3", "--out", str(root / "b")]) == 0
    assert main(["identify", "--robot", str(root / "a" / "robot.toml"), "--static", str(root / "a" / "static.csv"),
                 "--model", "joint_stiffness,kinematic_errors,tracker_frame", "--out", str(root / "cal.json")]) == 0
    return root


def test_validate_says_the_fit_data_when_the_hashes_match_and_reads_the_robot_from_the_calibration(
        absolute_calibration, capsys):
    root = absolute_calibration
    capsys.readouterr()
    cal = str(root / "cal.json")
    # no --robot: the calibration carries its description
    assert main(["validate", "--calibration", cal, "--static", str(root / "a" / "static.csv")]) == 0
    out = capsys.readouterr().out
    assert "poses of the fit data" in out and "not used in the fit" not in out
    assert main(["validate", "--calibration", cal, "--static", str(root / "a" / "static.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fit_data"] is True
    # another day's table: a validation
    other = str(root / "b" / "static.csv")
    assert main(["validate", "--calibration", cal, "--static", other]) == 0
    out = capsys.readouterr().out
    assert "poses not used in the fit" in out and "fit data" not in out
    assert main(["validate", "--robot", str(root / "a" / "robot.toml"), "--calibration", cal, "--static", other,
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fit_data"] is False
