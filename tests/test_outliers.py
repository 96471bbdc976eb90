"""Outliers: readings far off their repeats, found by a robust test, listed by
input line, left out of the noise floor; --exclude-outliers refits without them
(docs/cli.md ``outliers``)."""

import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.diagnose.static import diagnose_static
from elastocal.identify.outliers import find_outliers
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import build_dataset
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, add_outliers, simulate_static

ROBOT = bundled_robot()


@pytest.mark.parametrize("shared", (False, True))
def test_no_reading_of_20_complete_seeds_is_flagged(shared):
    flagged = [(seed, o.line) for seed in range(20)
               for o in find_outliers(simulate_static(ROBOT, CellTruth(), seed=seed,
                                                      plan=StaticPlan(shared_currents=shared)))]
    assert flagged == []


@pytest.mark.parametrize("seed", range(6))
def test_bad_readings_are_found_by_line_and_left_out_of_the_floor(seed):
    clean = simulate_static(ROBOT, CellTruth().with_hidden("link_compliance"), seed=seed)
    table, lines = add_outliers(clean, 2, np.random.default_rng(seed))
    found = find_outliers(table)
    assert sorted(o.line for o in found) == sorted(lines.tolist())
    assert all(2.5e-4 < o.residual < 6e-4 for o in found)
    # the floor does not grow with the bad readings in the data
    assert build_dataset(table).sigma_tracker == pytest.approx(build_dataset(clean).sigma_tracker, rel=0.02)
    kept = diagnose_static(ROBOT, table)
    assert kept.noise_floor == pytest.approx(diagnose_static(ROBOT, clean).noise_floor, rel=0.02)
    if kept.verdict is None:       # in the fit they leave an excess: the text says where and what to do
        assert any("diagnose again leaving them out" in u for u in kept.unexplained), kept.unexplained
        assert not any("--" in u for u in kept.unexplained)     # the library names no command-line flag
    diag = diagnose_static(ROBOT, table, exclude_outliers=True)
    assert diag.verdict == "link_compliance"
    assert diag.final.rms <= 1.3 * diag.final.noise_floor
    assert sorted(o.line for o in diag.outliers) == sorted(lines.tolist()) and all(o.excluded for o in diag.outliers)


def test_cli_outliers_by_line_and_exclude_outliers(tmp_path, capsys):
    out = tmp_path / "bad"
    assert main(["sim", "static", "--hidden", "link_compliance", "--outliers", "2", "--seed", "4",
                 "--out", str(out)]) == 0
    capsys.readouterr()
    truth = json.loads((out / "truth.json").read_text())
    args = ["--robot", str(out / "robot.toml"), "--static", str(out / "static.csv")]
    assert main(["diagnose", *args, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert sorted(o["line"] for o in obj["outliers"]) == sorted(truth["outliers"])
    row = obj["outliers"][0]
    assert {"line", "pose", "load", "marker", "residual"} <= set(row) and row["excluded"] is False
    # the line is that of the file: the row there is the bad reading
    lines = (out / "static.csv").read_text().splitlines()
    header = lines[0].split(",")
    fields = lines[row["line"] - 1].split(",")
    assert fields[header.index("pose")] == row["pose"] and fields[header.index("marker")] == row["marker"]
    # with them in the fit the residual stays above the floor: the library says so in its words, the
    # command line names its flag
    assert any("are in the fit: diagnose again leaving them out" in u for u in obj["unexplained"]["sentences"])
    assert main(["diagnose", *args]) == 0
    assert "to leave the outliers out: diagnose again with --exclude-outliers" in capsys.readouterr().out
    assert main(["diagnose", *args, "--json", "--exclude-outliers"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["verdict"] == "link_compliance" and all(o["excluded"] for o in obj["outliers"])
    assert main(["diagnose", *args, "--exclude-outliers"]) == 0
    text = capsys.readouterr().out
    assert f"outlier: line {truth['outliers'][0]}" in text and "left out" in text
    assert "--exclude-outliers" in text          # the suggested identify command keeps the flag
    assert main(["identify", *args, "--model", "joint_stiffness,link_compliance", "--json",
                 "--exclude-outliers"]) == 0
    fit = json.loads(capsys.readouterr().out)
    assert sorted(o["line"] for o in fit["outliers"]) == sorted(truth["outliers"])
    assert fit["residual"]["rms"] <= 1.3 * fit["noise_floor"]


def test_outliers_need_three_repeats(tmp_path, capsys):
    code = main(["sim", "static", "--outliers", "1", "--repeats", "2", "--out", str(tmp_path / "x")])
    assert code == 2 and "--outliers" in capsys.readouterr().err
