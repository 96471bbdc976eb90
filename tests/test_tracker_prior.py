"""The tracker position prior: cell.toml's ``[tracker]
base_p_tracker`` taken from the cell.toml a log carries and from ``--cell``, in
identify, diagnose and validate; ``--tracker-position`` before both; reported
with the offset of the registration found (docs/absolute.md)."""

import json

import numpy as np
import pytest

from elastocal.acquisition.logwriter import write_log_from_tables
from elastocal.cli import main
from elastocal.identify.absolute import TRACKER_PRIOR_STD_M
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import DEFAULT_TRACKER, CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
FULL = "joint_stiffness,kinematic_errors,tracker_frame"
#: where the default simulated tracker stands in base coordinates (docs/absolute.md, "The simulated cell")
TRUE_BASE_P_TRACKER = -DEFAULT_TRACKER[0].T @ DEFAULT_TRACKER[1]


def cell_text(base_p_tracker) -> str:
    tracker = "" if base_p_tracker is None else f"base_p_tracker = {list(base_p_tracker)}\n"
    return ('[cell]\nname = "cell-7"\nrobot = "hh150"\n\n[tracker]\nurl = "tracker+tcp://127.0.0.1:7000"\n'
            f'markers = ["R1", "R2", "R3"]\n{tracker}')


@pytest.fixture(scope="module")
def cell_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("prior")
    truth = CellTruth().with_hidden("kinematic_errors")
    table = simulate_static(ROBOT, truth, seed=21)
    (d / "robot.toml").write_text(ROBOT.to_toml())
    from elastocal.formats.tables import write_static_table

    write_static_table(d / "static.csv", table)
    # a tape measure's placement: 4-6 cm off the true one
    said = (3.15, -1.76, 0.64)
    (d / "cell.toml").write_text(cell_text(said))
    (d / "far.toml").write_text(cell_text((0.0, 2.0, 0.5)))
    (d / "silent.toml").write_text(cell_text(None))
    write_log_from_tables(d / "log.mcap", ROBOT, static=table, cell_text=cell_text(said))
    write_log_from_tables(d / "plain.mcap", ROBOT, static=table)
    return d, table, np.array(said)


def run_json(capsys, argv):
    capsys.readouterr()
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


def test_identify_takes_the_prior_from_the_log_cell_and_the_flags(cell_data, capsys):
    d, table, said = cell_data
    from_log = run_json(capsys, ["identify", str(d / "log.mcap"), "--model", FULL, "--json"])
    prior = from_log["registration"]["prior"]
    assert prior["base_p_tracker"] == pytest.approx(list(said)) and prior["std"] == TRACKER_PRIOR_STD_M
    assert "cell.toml" in prior["source"] and "log.mcap" in prior["source"]
    found = np.array(from_log["registration"]["base_p_tracker"])
    # the data fix the registration to micrometres: the tape measure does not move it, and the offset
    # reported is the distance to where the cell says the tracker stands
    np.testing.assert_allclose(found, TRUE_BASE_P_TRACKER, atol=2e-3)
    assert prior["offset"] == pytest.approx(float(np.linalg.norm(found - said)), rel=1e-9)
    assert 0.03 < prior["offset"] < 0.1
    # the same log without a cell.toml: no prior, the same registration
    plain = run_json(capsys, ["identify", str(d / "plain.mcap"), "--model", FULL, "--json"])
    assert "prior" not in plain["registration"]
    np.testing.assert_allclose(plain["registration"]["base_p_tracker"], found, atol=1e-6)
    # tables with --cell: the same prior; --tracker-position before --cell; a cell that does not say: none
    tables = ["--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"), "--model", FULL, "--json"]
    with_cell = run_json(capsys, ["identify", *tables, "--cell", str(d / "cell.toml")])
    assert with_cell["registration"]["prior"]["base_p_tracker"] == pytest.approx(list(said))
    assert str(d / "cell.toml") in with_cell["registration"]["prior"]["source"]
    both = run_json(capsys, ["identify", *tables, "--cell", str(d / "cell.toml"), "--tracker-position", "3,-2,1"])
    assert both["registration"]["prior"]["base_p_tracker"] == [3.0, -2.0, 1.0]
    assert both["registration"]["prior"]["source"] == "--tracker-position"
    silent = run_json(capsys, ["identify", *tables, "--cell", str(d / "silent.toml")])
    assert "prior" not in silent["registration"]
    # --cell overrides the log's cell.toml
    far = run_json(capsys, ["identify", str(d / "log.mcap"), "--model", FULL, "--cell", str(d / "far.toml"),
                            "--json"])
    assert far["registration"]["prior"]["base_p_tracker"] == [0.0, 2.0, 0.5]


def test_a_prior_far_from_the_registration_is_said_in_words(cell_data, capsys):
    d, _, _ = cell_data
    capsys.readouterr()
    assert main(["identify", str(d / "log.mcap"), "--model", FULL, "--cell", str(d / "far.toml")]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("tracker at ("))
    assert "far.toml" in line and "more than 3x the prior's 0.1 m" in line
    assert main(["identify", str(d / "log.mcap"), "--model", FULL]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("tracker at ("))
    assert "more than" not in line and "log.mcap" in line


def test_diagnose_and_validate_take_the_prior(cell_data, capsys, tmp_path):
    d, table, said = cell_data
    capsys.readouterr()
    assert main(["diagnose", str(d / "log.mcap"), "--cell", str(d / "far.toml")]) == 0
    text = capsys.readouterr().out
    assert "far.toml [tracker] base_p_tracker: more than 3x" in text
    # the command it proposes keeps the prior the diagnosis used
    assert f"add it: elastocal identify {d / 'log.mcap'} --cell {d / 'far.toml'} --model " in text
    diag = run_json(capsys, ["diagnose", str(d / "log.mcap"), "--json"])
    prior = diag["registration"]["prior"]
    assert prior["base_p_tracker"] == pytest.approx(list(said)) and "log.mcap" in prior["source"]
    # the registration of the model without the geometry (the comparison's base): millimetres off
    np.testing.assert_allclose(diag["registration"]["base_p_tracker"], TRUE_BASE_P_TRACKER, atol=1e-2)
    assert prior["offset"] == pytest.approx(float(np.linalg.norm(
        np.array(diag["registration"]["base_p_tracker"]) - said)), rel=1e-9)
    assert diag["verdict"] == "kinematic_errors"
    # without a prior diagnose --json keeps its contract's fields only
    plain = run_json(capsys, ["diagnose", str(d / "plain.mcap"), "--json"])
    assert "registration" not in plain and plain["verdict"] == "kinematic_errors"
    cal = tmp_path / "cal.json"
    assert main(["identify", str(d / "log.mcap"), "--model", FULL, "--out", str(cal)]) == 0
    other = simulate_static(ROBOT, CellTruth().with_hidden("kinematic_errors"), seed=22,
                            plan=StaticPlan(n_poses=8))
    from elastocal.formats.tables import write_static_table

    write_static_table(tmp_path / "other.csv", other)
    argv = ["validate", "--robot", str(d / "robot.toml"), "--calibration", str(cal), "--static",
            str(tmp_path / "other.csv"), "--json"]
    val = run_json(capsys, [*argv, "--cell", str(d / "far.toml")])
    found = np.array(val["registration"]["base_p_tracker"])
    np.testing.assert_allclose(found, TRUE_BASE_P_TRACKER, atol=2e-3)
    assert val["registration"]["prior"]["offset"] == pytest.approx(float(np.linalg.norm(found - [0.0, 2.0, 0.5])))
    assert "prior" not in run_json(capsys, argv)["registration"]


def test_bad_tracker_position_is_one_line_exit_2(cell_data, capsys):
    d, _, _ = cell_data
    for bad in ("1,2", "a,b,c", "1,2,1e9"):
        capsys.readouterr()
        assert main(["identify", str(d / "log.mcap"), "--tracker-position", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--tracker-position" in err[0]



@pytest.mark.heavy
def test_a_log_whose_cell_file_says_nothing_or_garbage(cell_data, tmp_path, capsys):
    d, table, _ = cell_data
    # a procedure run without a cell file records an empty one; a cell file without [tracker]
    for name, text in (("empty", ""), ("no-tracker", '[cell]\nname = "c"\nrobot = "hh150"\n'),
                       ("not-toml", "[cell\nname = ")):
        log = tmp_path / f"{name}.mcap"
        write_log_from_tables(log, ROBOT, static=table, cell_text=text)
        obj = run_json(capsys, ["identify", str(log), "--model", FULL, "--json"])
        assert "prior" not in obj["registration"], name
    # a base_p_tracker that is there but not three numbers is refused, naming the log and the key
    bad = tmp_path / "bad.mcap"
    write_log_from_tables(bad, ROBOT, static=table, cell_text=cell_text(None) + "base_p_tracker = [1.0, 2.0]\n")
    capsys.readouterr()
    assert main(["identify", str(bad), "--json"]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert captured.out == "" and len(err) == 1 and "bad.mcap" in err[0] and "tracker.base_p_tracker" in err[0]
