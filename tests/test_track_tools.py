"""view, check, history and fleet on the seven-joint cell (the HH-150 on a track, joint 1
prismatic): each takes a 7-joint log or calibration, keeps all seven joints and says a
prismatic joint's values in N and N/m. Checked against the simulator's truth or against the
same command on the same data by another route (log against tables, fleet against identify)."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

from elastocal.cli import build_parser, main
from elastocal.diagnose.check import check_calibration
from elastocal.formats.calibration import calibration_from_fit, read_calibration
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.runs import identify_runs
from elastocal.identify.static import identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot("hh150_track")
FRICTION = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
TRUTH = default_run_truth(CellTruth.for_robot(ROBOT))
CHECK_RUN = FrictionPlan.for_robot(ROBOT, speeds_rad_s=(0.1,), loads=(("0", (0.0,) * 6),), samples=100)


@pytest.fixture(scope="module")
def sim_track(tmp_path_factory):
    """`elastocal sim static --robot hh150_track` and `identify --out cal.json` on it."""
    out = tmp_path_factory.mktemp("track_tools") / "sim"
    assert main(["sim", "static", "--robot", "hh150_track", "--seed", "3", "--poses", "10", "--out", str(out)]) == 0
    assert main(["identify", "--robot", str(out / "robot.toml"), "--static", str(out / "static.csv"),
                 "--out", str(out / "cal.json")]) == 0
    return out


@pytest.fixture(scope="module")
def calibration():
    """A 7-joint calibration with the stiffness and the friction of every joint (the carriage's in N)."""
    obj = identify_static(ROBOT, simulate_static(ROBOT, TRUTH, seed=1, plan=StaticPlan(n_poses=12, n_loads=2))).to_json()
    runs = identify_runs(ROBOT, simulate_runs(ROBOT, TRUTH, seed=2, sweeps=None,
                                              friction=FrictionPlan.for_robot(ROBOT, samples=120)),
                         model=("joint_stiffness", *FRICTION))
    obj["parameters"].update(runs.to_json()["parameters"])
    obj["model"] = obj["model"] + list(FRICTION)
    return calibration_from_fit(ROBOT.name, obj, created="2026-01-05T08:00:00Z")


def _check(calibration, truth, seed):
    static = simulate_static(ROBOT, truth, seed=seed, plan=StaticPlan(n_poses=3, n_loads=1, repeats=3))
    runs = simulate_runs(ROBOT, truth, seed=seed + 500, sweeps=None, friction=CHECK_RUN)
    return check_calibration(ROBOT, calibration, static=static, runs=runs)


def test_view_of_a_seven_joint_log_and_calibration(sim_track):
    from elastocal.commands.view import build_view

    parser, _ = build_parser("view")

    def args(*argv):
        out = parser.parse_args(["view", *argv])
        out.notes = []
        return out

    from_log = build_view(args(str(sim_track / "log.mcap"), "--calibration", str(sim_track / "cal.json")))
    from_tables = build_view(args("--robot", str(sim_track / "robot.toml"), "--static", str(sim_track / "static.csv")))
    # the skeleton: the base, one point per joint (seven) and the tool point, at every pose
    assert from_log.skeletons.shape == (10, ROBOT.n_joints + 2, 3)
    np.testing.assert_allclose(from_log.skeletons, from_tables.skeletons, rtol=0, atol=1e-12)
    np.testing.assert_allclose(from_log.measured, from_tables.measured, rtol=0, atol=1e-12)
    assert from_log.models[-1].title.startswith("calibration")
    # the carriage at its commanded place along the track: the second point sits q1 from the base
    # along the base's y axis (alpha1 = -90 deg turns the carriage's z onto y)
    q1 = np.unique(np.round(np.asarray(from_tables.skeletons[:, 1, 1] - from_tables.skeletons[:, 0, 1]), 9))
    assert np.all((q1 >= ROBOT.joints[0].lower) & (q1 <= ROBOT.joints[0].upper)) and np.ptp(q1) > 0


def test_check_of_a_seven_joint_calibration_holds_and_names_the_carriage(calibration):
    same = _check(calibration, TRUTH, 11)
    assert same.verdict == "holds", same.reasons
    assert [j.joint for j in same.friction.joints] == list(range(1, 8))
    assert same.friction.joints[0].unit == "N" and same.friction.joints[1].unit == "N*m"
    carriage = dataclasses.replace(TRUTH, coulomb=TRUTH.coulomb * np.r_[1.5, np.ones(6)])
    worn = _check(calibration, carriage, 12)
    assert worn.verdict == "recalibrate" and [j.joint for j in worn.friction.failing()] == [1]
    assert "friction of joint 1" in worn.reasons[0] and " N measured" in worn.reasons[0]
    assert worn.to_json()["friction"]["joints"]["1"]["unit"] == "N"
    softer = _check(calibration, dataclasses.replace(TRUTH, stiffness=TRUTH.stiffness * np.r_[1, 1, 0.9, 1, 1, 1, 1]),
                    13)
    top = softer.deflection.changes[0]
    assert softer.verdict == "recalibrate" and top.name == "k3"
    assert top.relative == pytest.approx(-0.10, abs=0.03)


def test_history_keeps_seven_stiffnesses_the_carriage_in_n_per_m(sim_track, tmp_path, capsys):
    db = tmp_path / "history.sqlite"
    assert main(["history", "add", "--db", str(db), "--calibration", str(sim_track / "cal.json"),
                 "--log", str(sim_track / "log.mcap")]) == 0
    capsys.readouterr()
    assert main(["history", "--db", str(db), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    text = json.dumps(shown)
    cal = read_calibration(sim_track / "cal.json")
    assert all(f'"k{j}"' in text for j in range(1, 8))
    assert main(["history", "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert "k7" in out and "N/m" in out
    line = next(x for x in out.splitlines() if x.strip().startswith("k1 "))
    assert f"{cal.value('k1'):.6g}" in line and "N/m" in line


def test_fleet_identify_of_a_seven_joint_log_gives_what_identify_gives(sim_track, tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "a.mcap").write_bytes((sim_track / "log.mcap").read_bytes())
    out = tmp_path / "results.csv"
    assert main(["fleet", "identify", str(logs), "--workers", "1", "--pool", "processes", "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open(encoding="utf-8")))
    assert len(rows) == 1 and rows[0]["error"] == "" and rows[0]["robot"] == ROBOT.name
    cal = read_calibration(sim_track / "cal.json")
    for j in range(1, 8):
        assert float(rows[0][f"k{j}"]) == pytest.approx(cal.value(f"k{j}"), rel=1e-6)


def test_stream_on_the_seven_joint_cell_brings_the_tool_onto_the_plan(sim_track, tmp_path, capsys):
    """`elastocal stream --sim --cell` with a cell.toml naming the track robot: Yang's process line
    with the carriage at 3 m, a 7-joint path and calibration, the simulated EGM controller and
    Net F/T (in a process of their own); judged against the simulated cell's truth."""
    from elastocal.compensation.ik import yang_path

    six = yang_path(bundled_robot("hh150"), step_m=0.01)
    q = np.column_stack([np.full(len(six.q), 3.0), six.q])      # the carriage mid-track, the arm's line
    t = np.linspace(0.0, 3.0, len(q))
    lines = ["t," + ",".join(f"q{j}" for j in range(1, 8))]
    lines += [",".join(repr(float(v)) for v in (ti, *qi)) for ti, qi in zip(t, q)]
    (tmp_path / "path.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "cell.toml").write_text('[cell]\nname = "track stream cell"\nrobot = "hh150_track"\n'
                                        '[guidance]\nurl = "egm://127.0.0.1:0"\n'
                                        '[force_sensor]\nurl = "netft://127.0.0.1:0"\n')
    out = tmp_path / "stream.mcap"
    code = main(["stream", "--sim", "--cell", str(tmp_path / "cell.toml"), "--calibration",
                 str(sim_track / "cal.json"), "--path", str(tmp_path / "path.csv"), "--out", str(out),
                 "--yes", "--force", "--json"])
    obj = json.loads(capsys.readouterr().out)
    assert code == 0 and obj["status"] == "completed", obj
    truth = obj["truth"]
    # the process deflects the uncompensated tool by millimetres; the stream removes nearly all of it
    assert truth["uncompensated"]["rms"] > 1e-3
    assert truth["stream"]["rms"] < 0.05 * truth["uncompensated"]["rms"]
