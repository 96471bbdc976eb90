"""The next experiment: `elastocal plan --discriminate` (design/discriminate.py, docs/plan.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.design.candidates import Workspace
from elastocal.design.discriminate import given_from_diagnosis, plan_discrimination
from elastocal.diagnose.static import diagnose_static
from elastocal.formats.plan import load_plan
from elastocal.formats.robot_toml import load_robot
from elastocal.formats.tables import concat_static_tables, read_static_table
from elastocal.identify.design_matrix import planned_dataset, regressor
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import simulate_static


@pytest.fixture(scope="module")
def first_round(tmp_path_factory):
    """A cell with link compliance measured on three poses under two hung weights: too few to tell it
    from the joint springs."""
    out = tmp_path_factory.mktemp("first")
    assert main(["sim", "static", "--hidden", "link_compliance", "--seed", "1", "--poses", "3",
                 "--loads-per-pose", "2", "--out", str(out)]) == 0
    return out


def test_concat_keeps_poses_apart(first_round):
    robot = load_robot(first_round / "robot.toml")
    a = read_static_table(first_round / "static.csv", robot)
    both = concat_static_tables([a, a])
    assert len(both) == 2 * len(a)
    assert set(both.pose[len(a):]) == {f"2:{p}" for p in set(a.pose)}
    assert set(both.pose[:len(a)]) == set(a.pose)


def test_backlash_column_is_zero_where_no_torque_reverses():
    robot = load_robot("elastocal/robots/hh150.toml")
    q = np.array([[0.0, 0.4, -0.4, 0.0, 1.0, 0.0]])
    down = np.array([[0.0, 0.0, -1000.0, 0.0, 0.0, 0.0]])
    sideways = np.array([[0.0, 1000.0, 0.0, 0.0, 0.0, 0.0]])
    cols = []
    for w in (down, sideways):
        ds = planned_dataset(robot, q, [w], robot.marker_names, repeats=3, sigma_tracker=1e-5,
                             sigma_current=np.full(6, 0.02))
        a, names = regressor(robot, ds, ["backlash"])
        cols.append(np.abs(a[:, :, names.index("b1")]).max())
    # a hung weight puts no torque on the vertical joint 1; a sideways pull does, from zero
    assert cols[0] == 0.0
    assert cols[1] > 0.1


def test_plan_discriminate_decides_what_the_first_round_leaves_open(first_round, tmp_path, capsys):
    out = tmp_path / "next.toml"
    args = ["plan", "--discriminate", "link_compliance", "--robot", str(first_round / "robot.toml"),
            "--static", str(first_round / "static.csv"), "--out", str(out), "--json", "--seed", "3"]
    assert main(args) == 0
    obj = json.loads(capsys.readouterr().out)
    ev = obj["evidence"]["link_compliance"]
    assert obj["worth"] and obj["plan"] == str(out)
    assert ev["delta_bic_rival_given"] > -10.0          # the first round cannot decide it
    assert ev["delta_bic_rival"] < -10.0                # the planned one is expected to
    assert ev["delta_bic_rival"] < ev["delta_bic_random"]   # better than random poses of the same count
    plan = load_plan(out)
    assert 1 <= len(plan.static.poses) <= 6
    robot = load_robot(first_round / "robot.toml")
    plan.validate_for(robot)
    for spec in plan.loads:
        force = spec.wrench(robot.gravity)[:3]
        assert np.linalg.norm(force) <= obj["f_max"] * (1 + 1e-9)
    assert "[expected.link_compliance]" in out.read_text()

    # the round measured on the simulated cell, diagnosed with the first: the effect is named
    truth = CellTruth().with_hidden("link_compliance")
    loads = {s.id: s.wrench(robot.gravity) for s in plan.loads}
    poses = np.array([p.q for p in plan.static.poses])
    wrenches = [np.array([loads[lid] for lid in p.loads]) for p in plan.static.poses]
    second = simulate_static(robot, truth, seed=101, poses=poses, wrenches=wrenches)
    first = read_static_table(first_round / "static.csv", robot)
    assert diagnose_static(robot, first).verdict is None
    both = diagnose_static(robot, concat_static_tables([first, second]))
    assert both.verdict == "link_compliance"

    # sequential: with both rounds given, a third is not worth its time (the data decide it)
    third = plan_discrimination(robot, given_from_diagnosis(both), ["link_compliance"],
                                Workspace(f_max_n=obj["f_max"]), markers=robot.marker_names, n_candidates=60,
                                seed=3, n_random=0)
    assert not third.worth
    assert "already decide" in third.reason
    assert third.evidence[0].delta_bic_rival_given < -10.0


def test_report_ends_with_the_next_experiment(first_round, tmp_path):
    out = tmp_path / "report.html"
    assert main(["report", str(first_round / "log.mcap"), "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")
    assert 'id="next-experiment"' in page
    assert "elastocal plan --discriminate" in page and "link_compliance" in page


def test_diagnose_ends_open_lines_with_the_plan_command(first_round, capsys):
    assert main(["diagnose", str(first_round / "log.mcap"), str(first_round / "log.mcap")]) == 0
    text = capsys.readouterr().out
    assert "deflection components" in text
    assert main(["diagnose", str(first_round / "log.mcap")]) == 0
    text = capsys.readouterr().out
    assert f"elastocal plan --discriminate link_compliance --given {first_round / 'log.mcap'}" in text


def test_plan_discriminate_bad_input(first_round, tmp_path, capsys):
    base = ["plan", "--robot", str(first_round / "robot.toml"), "--static", str(first_round / "static.csv"),
            "--out", str(tmp_path / "x.toml")]
    assert main(base + ["--discriminate", "no_such_effect"]) == 2
    assert main(base + ["--discriminate", "coulomb_friction"]) == 2
    assert main(base + ["--discriminate", "joint_stiffness"]) == 2
    assert not (tmp_path / "x.toml").exists()
    assert "--discriminate" in capsys.readouterr().err
