"""elastocal fleet: many logs on Dask or a process pool, the same numbers as one log alone.

The plant (made once per session): 4 cells x 10 inputs = 40, each cell folder
with its cell.toml and history; small simulated logs (4 poses, 2 loads, 2
repeats), one table folder, and broken ones: an empty file, a non-MCAP file,
a log cut after 300 bytes (errors), a log cut in half (read up to its last
complete chunk, with a note, as `elastocal identify` reads it).
"""

from __future__ import annotations

import json
import math
import pathlib
import shutil
import sqlite3

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.fleet import pool as fleet_pool
from elastocal.fleet.table import read_table

pytest.importorskip("distributed")

HELPERS = pathlib.Path(__file__).parent / "helpers"
CELLS = ("cell-a", "cell-b", "cell-c", "cell-d")
BROKEN = {"cell-c/logs/empty.mcap": "empty file", "cell-c/logs/garbage.mcap": "not an MCAP file",
          "cell-d/logs/cut-300.mcap": ""}


def _write_cell(folder: pathlib.Path, name: str) -> pathlib.Path:
    folder.mkdir(parents=True)
    cfg = folder / "cell.toml"
    cfg.write_text(f'[cell]\nname = "{name}"\nrobot = "hh150"\nhistory = "history.sqlite"\n', encoding="utf-8")
    return cfg


@pytest.fixture(scope="session")
def plant(tmp_path_factory):
    from elastocal.acquisition.logwriter import write_log_from_tables
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.formats.tables import write_static_table
    from elastocal.sims.cell import CellTruth
    from elastocal.sims.static import StaticPlan, simulate_static

    root = tmp_path_factory.mktemp("plant")
    robot = bundled_robot()
    plan = StaticPlan(n_poses=4, n_loads=2, repeats=2)
    seed = 100
    for c, name in enumerate(CELLS):
        folder = root / name
        _write_cell(folder, name)
        n_logs = {"cell-a": 10, "cell-b": 9, "cell-c": 8, "cell-d": 8}[name]
        for k in range(n_logs):
            truth = CellTruth()
            if name == "cell-c" and k >= 5:   # joint 2 of cell c went 10 % softer
                stiffness = truth.stiffness.copy()
                stiffness[1] *= 0.9
                truth = CellTruth(stiffness=stiffness)
            seed += 1
            table = simulate_static(robot, truth, seed=seed, plan=plan)
            log = folder / "logs" / f"{k:02d}" / "log.mcap"
            log.parent.mkdir(parents=True)
            write_log_from_tables(log, robot, static=table)
            if name == "cell-b" and k == 0:
                tables = folder / "tables"
                tables.mkdir()
                (tables / "robot.toml").write_text(robot.to_toml(), encoding="utf-8")
                write_static_table(tables / "static.csv", table)
    (root / "cell-c/logs/empty.mcap").write_bytes(b"")
    (root / "cell-c/logs/garbage.mcap").write_bytes(b"this is not a log\n" * 20)
    whole = (root / "cell-d/logs/00/log.mcap").read_bytes()
    (root / "cell-d/logs/cut-300.mcap").write_bytes(whole[:300])
    (root / "cell-d/logs/cut-half.mcap").write_bytes(whole[:len(whole) // 2])
    return root


def _fleet(capsys, *argv) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["fleet", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def _single(capsys, *argv) -> dict:
    capsys.readouterr()
    main([*map(str, argv), "--json"])
    return json.loads(capsys.readouterr().out)


def _without_seconds(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """A Dask cluster this module's tests share through --scheduler (its start costs more than most tests'
    work); module-scoped, so its worker processes end with the module instead of idling to the run's end."""
    import logging

    import dask
    from distributed import LocalCluster

    scratch = str(tmp_path_factory.mktemp("dask"))       # not Dask's default $TMPDIR/dask-scratch-space
    with dask.config.set({"temporary-directory": scratch}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL,
                         local_directory=scratch) as cluster:
        yield cluster.scheduler_address


@pytest.fixture(scope="session")
def identified(plant, tmp_path_factory):
    """fleet identify of the plant on Dask with 2 workers (no recording)."""
    out = tmp_path_factory.mktemp("identify") / "results.csv"
    assert main(["fleet", "identify", str(plant), "--out", str(out), "--workers", "2"]) == 0
    return read_table(out)


@pytest.mark.heavy   # a process pool over dozens of logs: about a minute
def test_forty_inputs_one_row_each_in_path_order_broken_ones_with_their_error(plant, identified):
    rows = identified
    assert len(rows) == 40
    paths = [r["path"] for r in rows]
    assert paths == sorted(paths)
    by_path = {pathlib.Path(r["path"]).relative_to(plant).as_posix(): r for r in rows}
    for rel, words in BROKEN.items():
        row = by_path[rel]
        assert row["error"].startswith(str(plant / rel)) and words in row["error"], row["error"]
        assert row["k2"] is None and row["residual_rms"] is None
    assert sum(bool(r["error"]) for r in rows) == len(BROKEN)
    half = by_path["cell-d/logs/cut-half.mcap"]
    assert half["error"] == "" and "last complete chunk" in half["note"] and half["k2"] > 0
    assert by_path["cell-b/tables"]["k2"] == by_path["cell-b/logs/00/log.mcap"]["k2"]
    good = [r for r in rows if not r["error"]]
    assert {r["cell"] for r in good} == set(CELLS)
    assert all(r["robot"] == "HH-150" and len(r["sha256"]) == 64 for r in good)
    # the recovered stiffness of joint 2 is the truth's within its std (cell c: 10 % softer from log 05 on)
    from elastocal.sims.cell import CellTruth

    k2 = CellTruth().stiffness[1]
    for r in good:
        soft = r["cell"] == "cell-c" and "/logs/0" in r["path"] and int(r["path"].split("/logs/")[1][:2]) >= 5
        truth = 0.9 * k2 if soft else k2
        assert abs(r["k2"] - truth) < 5 * r["k2_std"], r["path"]


def test_rows_are_exactly_what_identify_prints_for_each_log(plant, identified, capsys):
    rows = {r["path"]: r for r in identified}
    for rel in ("cell-a/logs/03/log.mcap", "cell-d/logs/cut-half.mcap"):
        obj = _single(capsys, "identify", plant / rel)
        row = rows[str(plant / rel)]
        # Dask's workers run BLAS on one thread (its nanny sets OMP/OPENBLAS_NUM_THREADS=1),
        # this process on the machine's cores: the sums of the weighted fit's matrix
        # products then differ in their last bits, hence a relative 1e-12, not ==
        for name, p in obj["parameters"].items():
            assert math.isclose(row[name], p["value"], rel_tol=1e-12)
            assert math.isclose(row[f"{name}_std"], p["std"], rel_tol=1e-12)
        assert math.isclose(row["residual_rms"], obj["residual"]["rms"], rel_tol=1e-12)
        assert math.isclose(row["noise_floor"], obj["noise_floor"], rel_tol=1e-12)
    folder = plant / "cell-b/tables"
    obj = _single(capsys, "identify", "--robot", folder / "robot.toml", "--static", folder / "static.csv")
    assert rows[str(folder)]["k3"] == obj["parameters"]["k3"]["value"]


@pytest.mark.heavy   # a process pool over dozens of logs: about a minute
def test_one_worker_and_the_process_pool_give_identical_results(plant, identified, tmp_path, capsys):
    one = tmp_path / "one.parquet"
    code, out, err = _fleet(capsys, "identify", plant, "--out", one, "--workers", "1")
    assert code == 0 and "40 input(s), 37 ok, 3 failed" in out and "Dask LocalCluster (1 worker)" in out
    last = [line for line in err.splitlines() if line.startswith("fleet identify: [")][-1]
    assert " 40/40 " in last and last.endswith(", 3 failed")
    pooled = tmp_path / "pool.csv"
    code, out, _ = _fleet(capsys, "identify", plant, "--out", pooled, "--workers", "2", "--pool", "processes")
    assert code == 0 and "local process pool (2 workers)" in out
    reference = _without_seconds(identified)
    assert _without_seconds(read_table(one)) == reference
    assert _without_seconds(read_table(pooled)) == reference


def test_without_dask_fleet_falls_back_to_the_process_pool_and_says_how_to_install(plant, tmp_path, capsys,
                                                                                   monkeypatch):
    monkeypatch.setattr(fleet_pool, "dask_available", lambda: False)
    out_csv = tmp_path / "r.csv"
    code, out, err = _fleet(capsys, "identify", plant / "cell-a", "--out", out_csv, "--workers", "2")
    assert code == 0 and "local process pool" in out
    assert "pip install 'elastocal[fleet]'" in err
    assert len(read_table(out_csv)) == 10
    code, _, err = _fleet(capsys, "identify", plant / "cell-a", "--out", tmp_path / "s.csv",
                          "--scheduler", "tcp://127.0.0.1:1")
    assert code == 2 and "pip install 'elastocal[fleet]'" in err


def test_record_identify_then_check_and_a_rerun_adds_nothing(plant, scheduler, tmp_path_factory, capsys):
    root = tmp_path_factory.mktemp("recorded")
    for name in CELLS:
        shutil.copytree(plant / name, root / name)
    code, out, _ = _fleet(capsys, "identify", root, "--out", root / "cal.csv", "--record", "--scheduler", scheduler)
    assert code == 0 and "recorded 37 calibration(s) and 0 check(s) in 4 histories; 0 already recorded" in out

    def counts() -> dict:
        out = {}
        for name in CELLS:
            with sqlite3.connect(root / name / "history.sqlite") as db:
                out[name] = (db.execute("select count(*) from calibration").fetchone()[0],
                             db.execute("select count(*) from check_run").fetchone()[0])
        return out

    assert counts() == {"cell-a": (10, 0), "cell-b": (10, 0), "cell-c": (8, 0), "cell-d": (9, 0)}
    code, out, _ = _fleet(capsys, "identify", root, "--out", root / "cal.csv", "--record", "--force",
                          "--scheduler", scheduler)
    assert code == 0 and "recorded 0 calibration(s) and 0 check(s) in 4 histories; 37 already recorded" in out
    checked = (root / "cell-a", root / "cell-c")     # two cells of the plant: 18 logs, 2 broken
    code, out, _ = _fleet(capsys, "check", *checked, "--out", root / "check.csv", "--record", "--scheduler", scheduler)
    assert code == 0 and "recorded 0 calibration(s) and 18 check(s)" in out
    first = counts()
    code, out, _ = _fleet(capsys, "check", *checked, "--out", root / "check.csv", "--record", "--force",
                          "--scheduler", scheduler)
    assert "18 already recorded" in out and counts() == first == {
        "cell-a": (10, 10), "cell-b": (10, 0), "cell-c": (8, 8), "cell-d": (9, 0)}
    rows = {r["path"]: r for r in read_table(root / "check.csv")}
    # the decisions are exactly elastocal check's on each log alone
    for rel in ("cell-a/logs/04/log.mcap", "cell-c/logs/01/log.mcap", "cell-c/logs/06/log.mcap"):
        obj = _single(capsys, "check", "--cell", root / rel.split("/")[0] / "cell.toml", "--log", root / rel,
                      "--no-record")
        row = rows[str(root / rel)]
        assert row["decision"] == obj["verdict"]
        # to the last bits: see test_rows_are_exactly_what_identify_prints_for_each_log
        assert math.isclose(row["residual_rms"], obj["deflection"]["rms_unexplained"], rel_tol=1e-12)
        assert math.isclose(row["k2"], obj["deflection"]["parameters"]["k2"]["check"], rel_tol=1e-12)
    # cell c's current calibration is from a soft log: its stiff logs (00-04) no longer agree with it
    c_rows = [r for p, r in rows.items() if "/cell-c/logs/0" in p]
    assert [r["decision"] for r in c_rows] == ["recalibrate"] * 5 + ["holds"] * 3
    code, out, _ = _fleet(capsys, "history", root)
    assert code == 0
    lines = {line.split()[0]: line for line in out.splitlines()[2:]}
    assert set(lines) == set(CELLS)
    assert "5 of 8" in lines["cell-c"] and "0 of 10" in lines["cell-a"]
    obj = json.loads(_fleet(capsys, "history", root, "--json")[1])
    c = next(x for x in obj["cells"] if x["cell"] == "cell-c")
    assert c["calibrations"] == 8 and c["checks"] == 8 and c["checks_failed"] == 5
    assert -0.15 < c["drift"]["k2"]["change"] < -0.05     # first (stiff) to latest (soft): about -10 %
    assert c["drift"]["k2"]["determined"] and not c["drift"]["k1"]["determined"]   # 4 poses hardly load joint 1
    assert "n/d" in lines["cell-c"]


@pytest.mark.parametrize("pool", ["dask", "processes"])
def test_a_task_that_kills_its_worker_is_retried_once_then_recorded(plant, tmp_path, monkeypatch, pool):
    from elastocal.fleet.discover import find_inputs
    from elastocal.fleet.tasks import FleetTask

    logs = tmp_path / "logs"
    logs.mkdir()
    for k in range(3):
        shutil.copy(plant / f"cell-a/logs/{k:02d}/log.mcap", logs / f"{k}.mcap")
    shutil.copy(plant / "cell-a/logs/05/log.mcap", logs / "poison.mcap")
    tries = tmp_path / "tries"
    tries.mkdir()
    monkeypatch.setenv("FLEET_POISON_DIR", str(tries))
    monkeypatch.setenv("PYTHONPATH", str(HELPERS))
    monkeypatch.syspath_prepend(str(HELPERS))
    from fleet_poison import kill_on_poison

    tasks = [FleetTask(command="identify", path=str(i.path)) for i in find_inputs([logs])]
    seen = []
    results = fleet_pool.run_tasks(tasks, pool=pool, workers=2, fn=kill_on_poison,
                                   progress=lambda done, total, failed, r: seen.append((done, total, failed)))
    assert [pathlib.Path(r.path).name for r in results] == ["0.mcap", "1.mcap", "2.mcap", "poison.mcap"]
    assert all(r.ok and r.parameters for r in results[:3])
    assert "worker process died 2 times" in results[3].error
    assert len(list(tries.iterdir())) == 2               # tried, retried once, then recorded
    assert seen[-1] == (4, 4, 1)


@pytest.mark.parametrize("argv, words", [
    (["identify", "{plant}", "--out", "{tmp}/r.txt"], ".csv or .parquet"),
    (["diagnose", "{plant}", "--out", "{tmp}/r.csv", "--record"], "not kept in the history"),
    (["identify", "{tmp}/nowhere", "--out", "{tmp}/r.csv"], "no such file or folder"),
    (["identify", "{plant}", "--out", "{tmp}/r.csv", "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"],
     "--workers sizes a local cluster"),
    (["identify", "{plant}"], "needs --out"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(plant, tmp_path, capsys, argv, words):
    argv = [a.format(plant=plant, tmp=tmp_path) for a in argv]
    code, out, err = _fleet(capsys, *argv)
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.iterdir())


def test_diagnose_rows_are_what_diagnose_prints(plant, scheduler, tmp_path, capsys):
    out_csv = tmp_path / "d.csv"
    code, out, _ = _fleet(capsys, "diagnose", plant / "cell-a" / "logs" / "00", plant / "cell-c" / "logs",
                          "--out", out_csv, "--scheduler", scheduler)
    assert code == 0 and f"on {scheduler}" in out
    rows = {r["path"]: r for r in read_table(out_csv)}
    assert len(rows) == 11
    for rel in ("cell-a/logs/00/log.mcap", "cell-c/logs/06/log.mcap"):
        obj = _single(capsys, "diagnose", plant / rel)
        row = rows[str(plant / rel)]
        assert row["residual_rms"] == obj["residual"]["rms"] and row["noise_floor"] == obj["noise_floor"]
        assert (row["verdict"] or None) == obj["verdict"]
    assert all(math.isfinite(r["residual_rms"]) for r in rows.values() if not r["error"])
    assert np.count_nonzero([bool(r["error"]) for r in rows.values()]) == 2
