"""An unattended check runs what needs no person: the check poses read unloaded and compared with
the calibration's own unloaded readings at those poses (diagnose/check_positions.py), a verdict
either way; `schedule install` accepts such a plan once the history holds the calibration's log."""

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest

from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.procedures import run_procedures
from elastocal.cli import main
from elastocal.diagnose.check_positions import FLOOR_RATIO, check_positions
from elastocal.formats.plan import CheckSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.static import StaticPlan, simulate_static

#: joint 2's zero moved by 0.02 deg (a knock): a few hundred µm at the tool
KNOCKED = CellTruth(kinematic_errors=(("dq2", math.radians(0.02)),))
POSES = {"P1": (0.2, 0.3, -0.4, 0.3, 1.0, 0.2), "P2": (0.5, 0.55, -0.2, 0.6, 1.2, 0.5),
         "P3": (-0.3, 0.45, -0.6, -0.4, 0.8, -0.3), "P4": (0.1, 0.2, -0.1, 0.2, 0.7, 0.6)}


def test_unloaded_positions_hold_on_an_unchanged_robot_and_drift_on_a_knocked_one(robot):
    """Over 30 seeds: the unchanged robot's unloaded positions never count as moved and chi2/dof
    averages about 1 (the noise pooled from the repeats is the right one); a 0.02 deg knock of
    joint 2's zero always does."""
    rng = np.random.default_rng(5)
    from elastocal.sims.static import random_poses

    ratios, moved = [], []
    for seed in range(30):
        poses = random_poses(robot, 3, rng)
        plan = StaticPlan(n_poses=3, n_loads=1, repeats=3)
        calibration = simulate_static(robot, CellTruth(), seed=seed, plan=plan, poses=poses)
        same = simulate_static(robot, CellTruth(), seed=1000 + seed, plan=plan, poses=poses)
        knocked = simulate_static(robot, KNOCKED, seed=2000 + seed, plan=plan, poses=poses)
        ok = check_positions(same, calibration)
        assert ok.passed, ok.reason()
        assert ok.dof == 3 * 9 - 6 and ok.markers == 9
        ratios.append(ok.chi2 / ok.dof)
        bad = check_positions(knocked, calibration)
        assert not bad.passed and bad.reason().startswith("unloaded positions drifted by")
        moved.append(bad.rms_m / bad.noise_floor_m)
    # the mean of chi2/dof over 30 seeds: 1 within ~4 of its std (sqrt(2/21/30) = 0.056), a little above
    # 1 because the noise is estimated from 18 repeat dof per axis and session
    assert 0.8 < np.mean(ratios) < 1.3, ratios
    # how far past the floor depends on how much of the knock three poses let the rigid fit absorb
    assert min(moved) > FLOOR_RATIO and np.median(moved) > 3 * FLOOR_RATIO, moved


def _plan() -> str:
    return plan_toml(poses=POSES, loads=(LoadSpec("L1", force_n=(-635.0, 635.0, -635.0)),),
                     markers=("R1", "R2", "R3"), repeats=3, reading_s=0.04, speed_rad_s=0.8,
                     settle=SettleSpec(speed_rad_s=2e-3, spread_m=60e-6, window_s=0.15, timeout_s=20.0),
                     check=CheckSpec(poses=("P1", "P2", "P3"), load="L1"))


@pytest.fixture(scope="module")
def calibrated_cell(tmp_path_factory):
    """The README's shop-floor flow on the virtual cell: the static procedure to a log, identified,
    recorded in the history with its log (the plan has a [check] of loaded poses, no friction path)."""
    root = tmp_path_factory.mktemp("unattended")
    (root / "plan.toml").write_text(_plan())
    (root / "cell.toml").write_text('[cell]\nname = "line 3"\nrobot = "hh150"\nhistory = "history.sqlite"\n')
    timing = VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0)
    out = run_procedures(VirtualCellIO(SimCell(_robot(), CellTruth()), seed=3, timing=timing),
                         parse_plan(_plan()), root / "cal.mcap", procedures=("static",))
    assert out.status == "completed"
    assert main(["identify", str(root / "cal.mcap"), "--out", str(root / "cal.json")]) == 0
    assert main(["history", "add", "--cell", str(root / "cell.toml"), "--calibration", str(root / "cal.json"),
                 "--log", str(root / "cal.mcap"), "--plan", str(root / "plan.toml")]) == 0
    return root


def _robot():
    from elastocal.formats.robot_toml import bundled_robot

    return bundled_robot()


def _unattended_check(root, name: str, truth: CellTruth, seed: int):
    timing = VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0)
    out = run_procedures(VirtualCellIO(SimCell(_robot(), truth), seed=seed, timing=timing),
                         parse_plan(_plan()), root / f"{name}.mcap", procedures=("check",), unattended=True)
    assert out.status == "completed"
    return out


def test_an_unattended_check_reads_the_check_poses_unloaded_and_gives_a_verdict(calibrated_cell, capsys):
    root = calibrated_cell
    out = _unattended_check(root, "same", CellTruth(), seed=4)
    assert out.skipped == ("check pose P1 under load L1", "check pose P2 under load L1",
                           "check pose P3 under load L1")
    capsys.readouterr()
    base = ["check", "--cell", str(root / "cell.toml"), "--json", "--no-record", "--log"]
    assert main(base + [str(root / "same.mcap")]) == 0
    same = json.loads(capsys.readouterr().out)
    assert same["verdict"] == "holds" and same["deflection"] is None
    pos = same["positions"]
    assert pos["passed"] and pos["poses"] == ["P1", "P2", "P3"] and pos["n"] == 9 and pos["dof"] == 21
    assert pos["rms"] <= FLOOR_RATIO * pos["noise_floor"]
    assert any(r.startswith("unloaded positions still valid") for r in same["reasons"])
    # the robot knocked since (joint 2's zero moved): the unattended check asks for recalibration
    _unattended_check(root, "knocked", KNOCKED, seed=5)
    assert main(base + [str(root / "knocked.mcap")]) == 3
    knocked = json.loads(capsys.readouterr().out)
    assert knocked["verdict"] == "recalibrate" and not knocked["positions"]["passed"]
    assert knocked["reasons"][0].startswith("unloaded positions drifted by")
    assert knocked["positions"]["rms"] > 5 * knocked["positions"]["noise_floor"]


def test_schedule_accepts_a_plan_whose_check_poses_can_be_read_unattended(calibrated_cell, tmp_path, capsys):
    root = calibrated_cell
    units = tmp_path / "units"
    base = ["schedule", "install", "--every", "7d", "--cell", str(root / "cell.toml"), "--unit-dir", str(units)]
    capsys.readouterr()
    assert main([*base, "--json"]) == 0, capsys.readouterr().err
    assert sorted(p.name for p in units.iterdir()) == ["elastocal-check.service", "elastocal-check.timer"]
    # the same calibration whose log is gone since: nothing to compare the unloaded readings with
    (tmp_path / "cell.toml").write_text('[cell]\nname = "line 3"\nrobot = "hh150"\nhistory = "h2.sqlite"\n')
    shutil.copy(root / "cal.mcap", tmp_path / "gone.mcap")
    assert main(["history", "add", "--cell", str(tmp_path / "cell.toml"), "--calibration", str(root / "cal.json"),
                 "--log", str(tmp_path / "gone.mcap"), "--plan", str(root / "plan.toml")]) == 0
    (tmp_path / "gone.mcap").unlink()
    capsys.readouterr()
    other = tmp_path / "units2"
    assert main(["schedule", "install", "--every", "7d", "--cell", str(tmp_path / "cell.toml"),
                 "--unit-dir", str(other)]) == 2
    err = capsys.readouterr().err
    assert "would exit 2 every time" in err and "history add --log" in err and err.count("\n") == 1
    assert not other.exists()


def test_check_positions_needs_repeats_and_shared_poses(robot):
    from elastocal.errors import InputError

    plan = StaticPlan(n_poses=3, n_loads=1, repeats=1)
    one = simulate_static(robot, CellTruth(), seed=1, plan=plan)
    with pytest.raises(InputError, match="repeats >= 2"):
        check_positions(one, one)
    a = simulate_static(robot, CellTruth(), seed=1, plan=dataclasses.replace(plan, repeats=2))
    b = simulate_static(robot, CellTruth(), seed=2, plan=dataclasses.replace(plan, repeats=2))
    assert check_positions(a, b) is None                  # other poses: nothing to compare
