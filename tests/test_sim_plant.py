"""`elastocal sim plant`: a plant of simulated cells laid out as docs/fleet.md says, seeded,
each cell's history holding its first calibration as `fleet identify --record` records it.
(The whole fleet workflow on it, check -> identify -> history, runs in
tests/test_readme_workflows.py from the README's lines.)"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import pathlib

import pytest

from elastocal.cli import main

SMALL = ["--cells", "2", "--logs", "3", "--poses", "6"]


def _sha(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    root = tmp_path_factory.mktemp("simplant") / "plant"
    assert main(["sim", "plant", "--out", str(root), *SMALL, "--seed", "4", "--json"]) == 0
    return root


@pytest.mark.heavy
def test_the_plant_is_laid_out_as_the_fleet_reads_it(plant, capsys):
    from elastocal.drivers.config import load_cell_config
    from elastocal.fleet.discover import find_inputs

    truth = json.loads((plant / "truth.json").read_text())
    assert [c["cell"] for c in truth["cells"]] == ["cell-01", "cell-02"]
    names = {"cell-01": [], "cell-02": []}
    for item in find_inputs([plant]):
        assert not item.tables and item.cell_config == item.path.parents[1] / "cell.toml"
        names[item.path.parents[1].name].append(item.path.name)
    assert names == {c: ["2026-11-02.mcap", "2026-11-09.mcap", "2026-11-16.mcap"] for c in names}
    for c, name in enumerate(names):
        cfg = load_cell_config(plant / name / "cell.toml")
        assert cfg.name == name and cfg.history == (plant / name / "history.sqlite")
    # the second cell's joint 2 is 10 % softer from the second half's first log (the 2nd of 3) on
    a, b = truth["cells"]
    assert a["drift"] is None and not any(log["drifted"] for log in a["logs"])
    assert b["drift"] == {"joint": 2, "fraction": 0.1, "from_log": "logs/2026-11-09.mcap"}
    assert [log["drifted"] for log in b["logs"]] == [False, True, True]
    built, soft = b["built_stiffness"], b["logs"][1]["stiffness"]
    assert soft[1] == pytest.approx(0.9 * built[1], rel=1e-12) and soft[2:] == built[2:]
    # the cells are built differently (a few per cent), each log of a cell the same build
    assert a["built_stiffness"] != b["built_stiffness"]
    assert all(log["stiffness"] == a["built_stiffness"] for log in a["logs"])


@pytest.mark.heavy
def test_each_log_is_dated_as_measured_a_week_apart(plant):
    from elastocal.fleet.discover import find_inputs
    from elastocal.fleet.tasks import FleetTask, run_task

    times = {}
    for item in find_inputs([plant / "cell-02"]):
        r = run_task(FleetTask(command="identify", path=str(item.path)))
        assert r.ok, r.error
        times[item.path.name] = dt.datetime.fromtimestamp(r.time_ns / 1e9, dt.timezone.utc)
    utc = dt.timezone.utc
    assert times == {"2026-11-02.mcap": dt.datetime(2026, 11, 2, 7, tzinfo=utc),
                     "2026-11-09.mcap": dt.datetime(2026, 11, 9, 7, tzinfo=utc),
                     "2026-11-16.mcap": dt.datetime(2026, 11, 16, 7, tzinfo=utc)}


@pytest.mark.heavy
def test_each_history_holds_the_first_calibration_identified_from_the_first_log(plant, capsys):
    from elastocal.acquisition.history import History

    truth = json.loads((plant / "truth.json").read_text())
    for cell in truth["cells"]:
        first = plant / cell["cell"] / cell["first_calibration"]
        with History(plant / cell["cell"] / "history.sqlite", create=False) as h:
            (rec,) = h.calibrations()
            assert h.checks() == ()
        assert rec.log_sha256 == _sha(first) and rec.log_path == str(first.resolve())
        assert rec.time == cell["logs"][0]["measured"]
        # the calibration identify prints for that log alone, and the cell's true build within 4 std
        capsys.readouterr()
        assert main(["identify", str(first), "--json"]) == 0
        alone = json.loads(capsys.readouterr().out)["parameters"]
        for j in range(1, 7):
            p = rec.calibration.find(f"k{j}")
            assert p.value == alone[f"k{j}"]["value"]
        for j in (2, 3):        # the joints six poses load well
            p = rec.calibration.find(f"k{j}")
            assert abs(p.value - cell["built_stiffness"][j - 1]) < 4 * p.std, (cell["cell"], j)


@pytest.mark.heavy
def test_the_same_seed_writes_the_same_plant_and_another_seed_another(plant, tmp_path, capsys):
    again, other = tmp_path / "again", tmp_path / "other"
    assert main(["sim", "plant", "--out", str(again), *SMALL, "--seed", "4"]) == 0
    assert "joint 2 10 % softer from logs/2026-11-09.mcap on" in capsys.readouterr().out
    assert main(["sim", "plant", "--out", str(other), *SMALL, "--seed", "5", "--drift-cell", "0"]) == 0
    out = capsys.readouterr().out
    assert "cell-02" in out and "softer" not in out
    for log in sorted(plant.glob("cell-*/logs/*.mcap")):
        rel = log.relative_to(plant)
        assert _sha(again / rel) == _sha(log), rel
        assert _sha(other / rel) != _sha(log), rel
    assert (again / "truth.json").read_text() == (plant / "truth.json").read_text()
    other_truth = json.loads((other / "truth.json").read_text())
    assert not any(log["drifted"] for c in other_truth["cells"] for log in c["logs"])
    # --force writes it again, the history anew: one calibration, not two
    assert main(["sim", "plant", "--out", str(again), *SMALL, "--seed", "4"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["sim", "plant", "--out", str(again), *SMALL, "--seed", "4", "--force"]) == 0
    from elastocal.acquisition.history import History

    with History(again / "cell-01" / "history.sqlite", create=False) as h:
        assert len(h.calibrations()) == 1


@pytest.mark.parametrize("extra, words", [
    (["--cells", "0"], "--cells: must be between 1 and 99, got 0"),
    (["--logs", "1"], "--logs: must be between 2 and 200, got 1"),
    (["--poses", "3"], "--poses: must be between 6 and 500, got 3"),
    (["--drift-cell", "4"], "--drift-cell: must be 0 (none) or a cell between 1 and --cells (3), got 4"),
    (["--cells", "1", "--drift-cell", "2"], "--drift-cell: must be 0 (none) or a cell between 1 and --cells (1)"),
    (["--drift-joint", "7"], "--drift-joint: must be a joint between 1 and 6, got 7"),
    (["--drift", "1.5"], "--drift: must be a fraction between -1 and 1"),
    (["--drift", "nan"], "--drift: must be a fraction between -1 and 1"),
    (["--drift-from", "1"], "--drift-from: must be a log between 2 and --logs (4)"),
    (["--seed", "-1"], "--seed: must be >= 0, got -1"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, extra, words):
    out = tmp_path / "plant"
    assert main(["sim", "plant", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_a_file_in_the_way_is_refused_and_nothing_written(tmp_path, capsys):
    out = tmp_path / "plant"
    (out / "cell-02").mkdir(parents=True)
    (out / "cell-02" / "history.sqlite").write_bytes(b"someone's history")
    assert main(["sim", "plant", "--out", str(out), *SMALL]) == 2
    err = capsys.readouterr().err
    assert "history.sqlite: a history of an earlier plant is in the way" in err and "--force" in err
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == ["cell-02", "cell-02/history.sqlite"]
    assert (out / "cell-02" / "history.sqlite").read_bytes() == b"someone's history"
