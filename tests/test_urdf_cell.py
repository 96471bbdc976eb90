"""The simulated cell of a URDF robot (elastocal/robots/hh150_urdf.toml, the HH-150 described by
hh150.urdf) through the command line: a calibration identified on one seed's poses predicts another
seed's unseen poses at the noise floor, as on the seven-joint track cell (tests/test_track_cell.py)."""

from __future__ import annotations

import json
import subprocess
import sys

from elastocal.formats.robot_toml import bundled_robot_path


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "elastocal", *args], capture_output=True, text=True, timeout=600)


def test_validate_on_unseen_poses_is_within_a_quarter_above_the_floor(tmp_path):
    robot = bundled_robot_path("hh150_urdf")
    seen, unseen, cal = tmp_path / "seen", tmp_path / "unseen", tmp_path / "cal.json"
    for out, seed in ((seen, "3"), (unseen, "11")):
        done = _cli("sim", "static", "--robot", str(robot), "--out", str(out), "--seed", seed)
        assert done.returncode == 0, done.stderr
    assert "urdf_xml" in (seen / "robot.toml").read_text(encoding="utf-8")
    done = _cli("identify", "--robot", str(seen / "robot.toml"), "--static", str(seen / "static.csv"),
                "--model", "joint_stiffness,tracker_frame", "--out", str(cal))
    assert done.returncode == 0, done.stderr
    done = _cli("validate", "--robot", str(seen / "robot.toml"), "--calibration", str(cal), "--static",
                str(unseen / "static.csv"), "--keep-frame", "--json")
    assert done.returncode == 0, done.stderr
    absolute = json.loads(done.stdout)["absolute"]
    # the unseen poses are another draw: nothing of the fit's own residual is reused
    assert absolute["calibrated"]["n"] > 100
    assert absolute["calibrated"]["rms"] <= 1.25 * absolute["noise_floor"], absolute
    # and the calibration is what brings them there: the uncalibrated description is far off
    assert absolute["nominal"]["rms"] > 20 * absolute["noise_floor"], absolute
