"""Export and replay: log -> robot.toml + tables; identification from the log
equals identification from the exported tables; tables -> log -> tables is
exact; bad logs fail with one line naming the file."""

import json

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.export import export_log, load_log
from elastocal.acquisition.logreader import read_log
from elastocal.acquisition.logwriter import write_log_from_tables
from elastocal.formats.plan import FrictionSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_procedures
from elastocal.acquisition.recorder import Recorder
from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot, load_robot
from elastocal.identify.static import identify_static
from elastocal.formats.tables import read_run_table, read_static_table
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.runs import default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, random_poses, simulate_static
from elastocal.model.kinds import KinematicForm, TorqueSource

ROBOT = bundled_robot()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A log of static poses and one friction pair recorded on the virtual cell."""
    poses = random_poses(ROBOT, 6, np.random.default_rng(8))
    loads = (LoadSpec("L1", mass_kg=60.0), LoadSpec("L2", mass_kg=110.0),
             LoadSpec("L3", force_n=(650.0, -300.0, -400.0)))
    friction = (FrictionSpec("F1", start=(0.2, 0.3, -0.4, 0.3, 1.0, 0.2), end=(0.4, 0.5, -0.3, 0.5, 1.1, 0.4),
                             speeds_rad_s=(0.2,), marker="R2"),)
    plan = parse_plan(plan_toml(poses=poses, loads=loads, markers=("R1", "R2", "R3"), repeats=2, reading_s=0.04,
                                speed_rad_s=0.6, settle=SettleSpec(spread_m=20e-6, window_s=0.15),
                                friction=friction))
    io = VirtualCellIO(SimCell(ROBOT, CellTruth()), seed=9,
                       timing=VirtualTiming(drive_rate_hz=250.0, tracker_rate_hz=250.0))
    log = tmp_path_factory.mktemp("rec") / "cal.mcap"
    assert run_procedures(io, plan, log).status == "completed"
    return log


def test_identification_from_log_equals_identification_from_exported_tables(recorded, tmp_path):
    robot, static, runs = load_log(recorded)
    result = export_log(recorded, tmp_path)
    assert result.complete and not result.truncated and result.incomplete_steps == ()
    assert {p.split("/")[-1] for p in result.files} == {"robot.toml", "cell.toml", "plan.toml", "static.csv",
                                                        "runs.csv"}
    robot2 = load_robot(tmp_path / "robot.toml")
    static2 = read_static_table(tmp_path / "static.csv", robot2)
    runs2 = read_run_table(tmp_path / "runs.csv", robot2)
    for name in ("q", "wrench", "currents", "xyz", "t"):
        np.testing.assert_array_equal(getattr(static, name), getattr(static2, name))
    for name in ("q", "dq", "currents", "xyz", "wrench", "t"):
        np.testing.assert_array_equal(getattr(runs, name), getattr(runs2, name))
    assert list(runs2.run) == list(runs.run) and set(runs.direction) == {"UV", "VU"}
    for torque in TorqueSource:
        a = identify_static(robot, static, torque=torque, form=KinematicForm.EXACT)
        b = identify_static(robot2, static2, torque=torque, form=KinematicForm.EXACT)
        np.testing.assert_array_equal(a.values([f"k{j}" for j in range(1, 7)]),
                                      b.values([f"k{j}" for j in range(1, 7)]))
        assert a.rms == b.rms


def test_cli_export_and_identify_agree(recorded, tmp_path, capsys):
    assert main(["export", str(recorded), "--out", str(tmp_path), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["static_rows"] == 6 * 4 * 2 * 3 and obj["run_rows"] > 100 and obj["complete"] is True
    assert main(["identify", str(recorded), "--json"]) == 0
    from_log = json.loads(capsys.readouterr().out)
    assert main(["identify", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "static.csv"),
                 "--json"]) == 0
    from_tables = json.loads(capsys.readouterr().out)
    assert from_log["parameters"] == from_tables["parameters"]
    assert from_log["residual"] == from_tables["residual"]


def test_tables_to_log_and_back_is_exact(tmp_path):
    static = simulate_static(ROBOT, CellTruth(), seed=5, plan=StaticPlan(n_poses=3, n_loads=2, repeats=2))
    runs = simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=5)
    write_log_from_tables(tmp_path / "t.mcap", ROBOT, static=static, runs=runs)
    robot, s2, r2 = load_log(tmp_path / "t.mcap")
    assert robot.to_toml() == ROBOT.to_toml()
    for name in ("q", "wrench", "currents", "xyz"):
        np.testing.assert_array_equal(getattr(static, name), getattr(s2, name))
    np.testing.assert_allclose(s2.t, static.t, rtol=0, atol=1e-9)
    for name in ("pose", "load", "marker"):
        assert list(getattr(static, name)) == list(getattr(s2, name))
    for name in ("q", "dq", "currents", "wrench", "xyz"):
        np.testing.assert_array_equal(getattr(runs, name), getattr(r2, name))
    for name in ("run", "direction", "load", "marker"):
        assert list(getattr(runs, name)) == list(getattr(r2, name))


def test_a_reading_without_tracker_samples_is_an_error(tmp_path):
    with Recorder(tmp_path / "bad.mcap") as rec:
        rec.document("robot", ROBOT.name, ROBOT.to_toml())
        rec.event("step_start", step_id="static/P1")
        rec.event("reading", step_id="static/P1", pose="P1", load="0", marker="R1", repeat=1, q=[0.0] * 6,
                  window_ns=[1, 2])
        rec.event("step_done", step_id="static/P1")
    with pytest.raises(InputError, match="no tracker sample"):
        load_log(tmp_path / "bad.mcap")


def test_bad_logs_fail_with_one_line(tmp_path, capsys):
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("pose,load\n")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:  # a valid MCAP file that elastocal did not write
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/camera", "json", sid)
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    corrupt = tmp_path / "corrupt.mcap"
    write_log_from_tables(tmp_path / "ok.mcap", ROBOT,
                          static=simulate_static(ROBOT, CellTruth(), seed=1, plan=StaticPlan(n_poses=2, n_loads=1)))
    data = bytearray((tmp_path / "ok.mcap").read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(64)
    corrupt.write_bytes(bytes(data))
    cases = [(not_mcap, "not an MCAP file"), (empty, "empty file"), (foreign, "no elastocal session"),
             (tmp_path / "missing.mcap", "cannot read"), (corrupt, "corrupt|decompress")]
    for path, message in cases:
        with pytest.raises(InputError, match=message):
            load_log(path)
        assert main(["export", str(path), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(path) in err, err


def test_read_log_reports_steps_and_sessions(recorded):
    contents = read_log(recorded)
    assert contents.completed_steps[:2] == ("static/P1", "static/P2")
    assert contents.completed_steps[-1] == "friction/F1/1"
    assert contents.incomplete_steps == ()
    assert contents.plan.text.startswith('name = "calibration"')
    assert contents.sessions[0]["format"] == "elastocal.log/1"
