"""The calibration history (acquisition/history.py, `elastocal history`):
records round-trip through SQLite, the current calibration is the latest,
drift follows the parameters, foreign files are refused, plots are written."""

import json
import sqlite3

import numpy as np
import pytest

from elastocal.acquisition.history import MAX_CHECK_RELATIVE_STD, History, iso_utc, plot_drift
from elastocal.acquisition.procedures import run_procedures
from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.identify.calibration import Calibration, file_sha256, write_calibration
from elastocal.identify.robot import bundled_robot
from elastocal.sims.cell import CellTruth, SimCell

DAY_NS = 86400 * 10**9
T0 = 1_767_600_000 * 10**9          # 2026-01-05


def calibration(k2: float, created: str) -> Calibration:
    params = {f"k{j}": {"value": v, "std": v * 1e-3, "unit": "N*m/rad"}
              for j, v in enumerate((559e3, k2, 1829e3, 184e3, 171e3, 70e3), start=1)}
    params["fc2"] = {"value": 180.0, "std": 0.5, "unit": "N*m"}
    return Calibration(robot="HH-150", created=created, model=("joint_stiffness", "coulomb_friction"),
                       torque="current", parameters=params, residual={"rms": 8e-6, "max": 3e-5, "n": 216},
                       data=({"path": "log.mcap", "sha256": "ab" * 32},))


def check_result(k2: float, k2_std: float, unexplained: float) -> dict:
    return {"verdict": "holds", "deflection": {
        "rms_unexplained": unexplained, "noise_floor": 7.5e-6,
        "parameters": {"k2": {"calibrated": 1.435e6, "check": k2, "check_std": k2_std, "std": k2_std, "z": 0.0},
                       "k1": {"calibrated": 559e3, "check": 3e7, "check_std": 5e7, "std": 5e7, "z": 0.6}}}}


def test_records_round_trip_and_the_latest_calibration_is_current(tmp_path):
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        first = h.add_calibration(calibration(1.435e6, "2026-01-05T08:00:00Z"), time_ns=T0, log_sha256="11" * 32,
                                  log_path="/cell/cal1.mcap", plan='name = "p"\n')
        h.add_check(calibration_id=first, time_ns=T0 + 7 * DAY_NS, verdict="holds", reasons=("fine",),
                    result=check_result(1.43e6, 2e3, 8e-6), log_sha256="22" * 32, log_path="/cell/c1.mcap")
        h.add_check(calibration_id=first, time_ns=T0 + 14 * DAY_NS, verdict="recalibrate", reasons=("k2 dropped",),
                    result=check_result(1.29e6, 2e3, 80e-6))
        second = h.add_calibration(calibration(1.29e6, "2026-01-19T09:00:00Z"), time_ns=T0 + 15 * DAY_NS)
    with History(db, create=False) as h:      # reopened: everything is on disk
        cals, checks, current = h.calibrations(), h.checks(), h.current()
        drift = h.drift()
    assert [c.id for c in cals] == [first, second] and current.id == second
    assert cals[0].calibration == calibration(1.435e6, "2026-01-05T08:00:00Z")
    assert cals[0].log_sha256 == "11" * 32 and cals[0].plan == 'name = "p"\n' and cals[1].plan is None
    assert cals[0].time == "2026-01-05T08:00:00Z" == iso_utc(T0)
    assert [c.verdict for c in checks] == ["holds", "recalibrate"] and checks[1].reasons == ("k2 dropped",)
    assert checks[0].result == check_result(1.43e6, 2e3, 8e-6)
    assert drift.names[:6] == tuple(f"k{j}" for j in range(1, 7)) and "fc2" in drift.names
    k2 = drift.names.index("k2")
    assert np.allclose(drift.calibration_value[:, k2], [1.435e6, 1.29e6])
    assert np.allclose(drift.check_value[:, k2], [1.43e6, 1.29e6])
    # a check that barely determines k1 stays out of the drift
    assert 5e7 / 3e7 > MAX_CHECK_RELATIVE_STD and np.all(np.isnan(drift.check_value[:, drift.names.index("k1")]))
    assert np.allclose(drift.check_unexplained_m, [8e-6, 80e-6])
    with History(db) as h:
        with pytest.raises(InputError, match="no calibration 99"):
            h.add_check(calibration_id=99, time_ns=T0, verdict="holds", reasons=(), result={})
        with pytest.raises(InputError, match="verdict"):
            h.add_check(calibration_id=first, time_ns=T0, verdict="maybe", reasons=(), result={})
        # the same data checked again against the same calibration is not recorded twice
        again = h.add_check(calibration_id=first, time_ns=T0 + 30 * DAY_NS, verdict="holds", reasons=("fine",),
                            result=check_result(1.43e6, 2e3, 8e-6), log_sha256="22" * 32, log_path="/copy.mcap")
        assert again == checks[0].id and len(h.checks()) == 2
        # against another calibration, it is a new check
        other = h.add_check(calibration_id=second, time_ns=T0 + 30 * DAY_NS, verdict="holds", reasons=(),
                            result={}, log_sha256="22" * 32)
        assert other not in (c.id for c in checks) and len(h.checks()) == 3


def test_foreign_and_missing_files_are_refused(tmp_path):
    text = tmp_path / "notes.sqlite"
    text.write_text("this is not a database, " * 100)
    with pytest.raises(InputError, match="not an elastocal history database"):
        History(text)
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE things (x)")
    con.commit()
    con.close()
    with pytest.raises(InputError, match="another application"):
        History(other)
    with pytest.raises(InputError, match="history add"):
        History(tmp_path / "none.sqlite", create=False)
    with pytest.raises(InputError, match="folder"):
        History(tmp_path / "no" / "such" / "h.sqlite")
    newer = tmp_path / "newer.sqlite"
    History(newer).close()
    con = sqlite3.connect(newer)
    con.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    con.commit()
    con.close()
    with pytest.raises(InputError, match="schema version 99"):
        History(newer)


def test_drift_plot_png_and_svg(tmp_path):
    with History(tmp_path / "h.sqlite") as h:
        cid = h.add_calibration(calibration(1.435e6, "a"), time_ns=T0)
        h.add_check(calibration_id=cid, time_ns=T0 + DAY_NS, verdict="recalibrate", reasons=("x",),
                    result=check_result(1.3e6, 1e3, 50e-6))
        h.add_calibration(calibration(1.3e6, "b"), time_ns=T0 + 2 * DAY_NS)
        drift = h.drift()
    plot_drift(drift, tmp_path / "d.png")
    plot_drift(drift, tmp_path / "d.svg")
    assert (tmp_path / "d.png").read_bytes()[:4] == b"\x89PNG"
    assert "<svg" in (tmp_path / "d.svg").read_text()
    with pytest.raises(InputError, match=r"\.png or \.svg"):
        plot_drift(drift, tmp_path / "d.jpg")


def test_history_command_add_and_show(tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nname = "c"\nrobot = "hh150"\nhistory = "db/history.sqlite"\n')
    (tmp_path / "db").mkdir()
    write_calibration(tmp_path / "cal.json", calibration(1.435e6, "2026-01-05T08:00:00Z"))
    # a real log with its plan: the plan is kept with the calibration
    robot = bundled_robot()
    plan_text = plan_toml(poses=[(0.2, 0.3, -0.4, 0.3, 1.0, 0.2)], loads=(LoadSpec("L1", mass_kg=60.0),),
                          markers=("R1",), repeats=2, reading_s=0.04,
                          settle=SettleSpec(speed_rad_s=2e-3, spread_m=60e-6, window_s=0.15, timeout_s=20.0))
    io = VirtualCellIO(SimCell(robot, CellTruth()), seed=1, timing=VirtualTiming(drive_rate_hz=100.0,
                                                                                 tracker_rate_hz=100.0))
    assert run_procedures(io, parse_plan(plan_text), tmp_path / "cal.mcap").status == "completed"
    assert main(["history", "add", "--cell", str(cell), "--calibration", str(tmp_path / "cal.json"),
                 "--log", str(tmp_path / "cal.mcap"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"db": str(tmp_path / "db" / "history.sqlite"), "calibration": 1}
    with History(tmp_path / "db" / "history.sqlite") as h:
        rec = h.current()
    assert rec.plan == plan_text and rec.log_sha256 == file_sha256(tmp_path / "cal.mcap")
    assert main(["history", "--cell", str(cell), "--plot", str(tmp_path / "drift.svg")]) == 0
    out = capsys.readouterr().out
    assert "1 calibration(s), 0 check(s)" in out and "1.4350" in out and (tmp_path / "drift.svg").exists()
    assert main(["history", "--db", str(tmp_path / "db" / "history.sqlite"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["calibrations"][0]["parameters"]["k2"]["value"] == 1.435e6 and obj["checks"] == []
    assert obj["drift"]["k2"]["change"] == 0.0
    # bad input: one line, exit 2
    assert main(["history", "--cell", str(cell), "--calibration", "x.json"]) == 2
    assert "history add" in capsys.readouterr().err
    no_db = tmp_path / "bare.toml"
    no_db.write_text('[cell]\nrobot = "hh150"\n')
    assert main(["history", "--cell", str(no_db)]) == 2
    err = capsys.readouterr().err
    assert "no history database" in err and err.count("\n") == 1
    assert main(["history", "--db", str(tmp_path / "empty.sqlite")]) == 2
    assert "history add" in capsys.readouterr().err
