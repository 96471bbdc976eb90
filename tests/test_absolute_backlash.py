"""Backlash on tables without loads (docs/absolute.md, "Tables without loads"): the play shows
where a joint's gravity torque changes sign across the poses, from the description's masses.
The simulated cell (sims/, its own Pinocchio statics) hides the play; the poses turn the
forearm over its vertical so joint 3's weight torque changes sign (joint 2's with it), as a
plan that wants to see that play does. A table whose poses keep every joint's weight on one
flank cannot show it: refused by name, listed as not testable by diagnose. Seeded."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.errors import EffectRefused
from elastocal.formats.robot_toml import bundled_robot
from elastocal.formats.tables import write_static_table
from elastocal.identify.absolute import identify_absolute
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.static import StaticPlan, random_poses, simulate_static

ROBOT = bundled_robot()
GEOMETRY = ("kinematic_errors", "tracker_frame")
MODEL = ("joint_stiffness", "backlash", *GEOMETRY)
#: geometry errors and the play the simulated cell hides (b2, b3 0.17 arcmin: 75 µm at the tool)
TRUTH = dataclasses.replace(CellTruth().with_hidden("kinematic_errors"),
                            backlash=CellTruth().with_hidden("backlash").backlash)


def unloaded(table):
    t = table.subset(table.load == "0")
    return dataclasses.replace(t, wrench=np.full_like(t.wrench, np.nan), currents=np.full_like(t.currents, np.nan))


def turning_over(seed: int, n: int = 40):
    """An absolute-only table whose poses take the forearm over its vertical (q3 to -2.6 rad)."""
    rng = np.random.default_rng(seed)
    q = random_poses(ROBOT, n, rng)
    q[:, 2] = rng.uniform(-2.6, 0.3, n)
    return unloaded(simulate_static(ROBOT, TRUTH, seed=seed, poses=q, plan=StaticPlan(n_poses=n, n_loads=1,
                                                                                     repeats=2)))


def one_flank(seed: int, n: int = 30):
    """An absolute-only table whose poses keep every joint's weight torque on one flank (chosen
    by the simulated cell's own gear torques: no joint's torque below -1 N·m)."""
    rng = np.random.default_rng(seed)
    cell = SimCell(ROBOT, TRUTH)
    q = random_poses(ROBOT, 12 * n, rng)
    keep = [p for p in q if np.all(cell.equilibrium(p).gear_torque >= -1.0)][:n]
    assert len(keep) == n
    return unloaded(simulate_static(ROBOT, TRUTH, seed=seed, poses=np.array(keep),
                                    plan=StaticPlan(n_poses=n, n_loads=1, repeats=2)))


@pytest.fixture(scope="module")
def table():
    return turning_over(3)


def test_the_play_of_joints_whose_weight_turns_over_is_found(table):
    fit = identify_absolute(ROBOT, table, model=MODEL)
    for j in (2, 3):                    # their weight torque changes sign across these poses
        p = fit.parameter(f"b{j}")
        assert abs(p.value - TRUTH.backlash[j - 1]) < 4 * p.std and p.std < 0.2 * p.value, p
    # joint 1 turns about the vertical, joint 6 carries no weight: no torque, no play to see
    assert {"b1", "b6", "k1"} <= set(fit.unidentifiable)
    assert fit.rms < 1.3 * fit.noise_floor, (fit.rms, fit.noise_floor)
    # without the play the residual stays well above its floor: the step between the flanks
    without = identify_absolute(ROBOT, table, model=("joint_stiffness", *GEOMETRY))
    assert without.rms > 2.0 * without.noise_floor, (without.rms, without.noise_floor)


def test_diagnose_names_the_play_on_a_table_without_loads(table, tmp_path, capsys):
    (tmp_path / "robot.toml").write_text(ROBOT.to_toml())
    write_static_table(tmp_path / "abs.csv", table)
    assert main(["diagnose", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "abs.csv"),
                 "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    steps = [s["effect"] for s in obj["steps"]]
    assert "backlash" in steps and {"backlash", "joint_stiffness"} <= set(obj["final"]["model"]), obj["final"]
    assert "backlash" not in {n["effect"] for n in obj["not_testable"]}
    assert obj["final"]["residual"]["rms"] < 1.3 * obj["final"]["noise_floor"]


def test_poses_on_one_flank_cannot_show_the_play(tmp_path, capsys):
    flat = one_flank(5)
    with pytest.raises(EffectRefused, match="gravity torque changes sign"):
        identify_absolute(ROBOT, flat, model=MODEL)
    (tmp_path / "robot.toml").write_text(ROBOT.to_toml())
    write_static_table(tmp_path / "flat.csv", flat)
    base = ["--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "flat.csv")]
    assert main(["identify", *base, "--model", ",".join(MODEL)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "backlash" in err[0] and "changes sign" in err[0], err
    assert main(["diagnose", *base, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    reasons = {n["effect"]: n["reason"] for n in obj["not_testable"]}
    assert "changes sign" in reasons["backlash"], reasons
    assert "backlash" not in [s["effect"] for s in obj["steps"]]


def test_without_masses_the_play_is_not_testable(table, tmp_path, capsys):
    text = ROBOT.to_toml()
    massless = "\n".join("mass = 0.0" if line.startswith("mass =") else line for line in text.splitlines())
    (tmp_path / "robot.toml").write_text(massless + "\n")
    write_static_table(tmp_path / "abs.csv", table)
    assert main(["diagnose", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "abs.csv"),
                 "--json"]) == 0
    reasons = {n["effect"]: n["reason"] for n in json.loads(capsys.readouterr().out)["not_testable"]}
    assert "masses" in reasons["backlash"] and "masses" in reasons["joint_stiffness"]


@pytest.mark.heavy
def test_the_play_is_found_with_95_percent_intervals_over_40_seeds():
    """Coverage of the 95 % intervals of b2 and b3 over 40 seeds (80 intervals): 95 % of them
    should cover the truth; the binomial 99 % band for 80 draws is 69..80."""
    inside = 0
    for seed in range(100, 140):
        fit = identify_absolute(ROBOT, turning_over(seed), model=MODEL)
        for j in (2, 3):
            p = fit.parameter(f"b{j}")
            inside += abs(p.value - TRUTH.backlash[j - 1]) < 1.96 * p.std
    assert inside >= 69, inside


def _turning_over_on(robot, forearm: int, seed: int, n: int = 40):
    """``turning_over`` on any chain: the forearm joint (0-based ``forearm``) over its vertical;
    the as-built geometry hidden (a DH table's errors, or a URDF robot's joint origins)."""
    base = CellTruth.for_robot(robot)
    truth = base.with_hidden("kinematic_errors")
    truth = dataclasses.replace(truth, backlash=base.with_hidden("backlash").backlash)
    rng = np.random.default_rng(seed)
    q = random_poses(robot, n, rng)
    q[:, forearm] = rng.uniform(-2.6, 0.3, n)
    plan = StaticPlan(n_poses=n, n_loads=1, repeats=2)
    return truth, unloaded(simulate_static(robot, truth, seed=seed, poses=q, plan=plan))


@pytest.mark.parametrize("name, forearm", [("hh150_track", 3), ("hh150_urdf", 2)])
def test_the_play_is_found_and_diagnosed_on_the_track_cell_and_a_urdf_robot(name, forearm):
    """Seven joints (a prismatic carriage first) and a URDF chain: the play of the two joints whose weight
    torque the poses turn over (the arm's joints 2 and 3) within 4 std, the diagnosis names backlash."""
    from elastocal.diagnose.absolute_only import diagnose_absolute_only
    from elastocal.identify.static import build_dataset

    robot = bundled_robot(name)
    truth, table = _turning_over_on(robot, forearm, seed=3)
    fit = identify_absolute(robot, table, model=("joint_stiffness", "backlash", *GEOMETRY))
    assert len(truth.backlash) == robot.n_joints
    for j in (forearm, forearm + 1):             # 1-based: the shoulder and the forearm of the arm
        p = fit.parameter(f"b{j}")
        assert abs(p.value - truth.backlash[j - 1]) < 4 * p.std and p.std < 0.2 * p.value, p
    # the first joint (the carriage, or the turret about the vertical) carries no weight torque that turns
    assert {"b1", f"b{robot.n_joints}"} <= set(fit.unidentifiable)
    assert fit.rms < 1.3 * fit.noise_floor, (fit.rms, fit.noise_floor)
    diag = diagnose_absolute_only(robot, build_dataset(table), GEOMETRY)
    assert [s.effect for s in diag.absolute.steps][:1] == ["backlash"], diag.text()
    assert diag.verdict == "backlash"


def test_the_plausibility_of_a_candidate_covers_every_joint_of_the_chain():
    """On seven joints a negative k7 or a play of 2 deg on joint 7 makes the candidate implausible (the
    rules looked at k1..k6 and b1..b6 only)."""
    from types import SimpleNamespace

    from elastocal.diagnose.absolute import _implausible
    from elastocal.identify.static import Parameter
    from elastocal.model.effects import get_effect

    robot = bundled_robot("hh150_track")
    eff = get_effect("backlash", robot)
    ks = [Parameter(f"k{j}", 1e6, 1e4, "N*m/rad") for j in range(1, 8)]
    bs = [Parameter(f"b{j}", 1e-4, 1e-5, "rad") for j in range(1, 8)]
    assert _implausible(eff, SimpleNamespace(parameters=[*ks, *bs]), eff.parameters) is None
    soft = [*ks[:6], Parameter("k7", -1e5, 1e4, "N*m/rad")]
    assert "k7" in _implausible(eff, SimpleNamespace(parameters=[*soft, *bs]), eff.parameters)
    wide = [*bs[:6], Parameter("b7", np.radians(2.0), 1e-5, "rad")]
    assert "joint 7" in _implausible(eff, SimpleNamespace(parameters=[*ks, *wide]), eff.parameters)
