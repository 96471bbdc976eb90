"""The readers of the user's files refuse bad input with one line naming the
file, the line and the key or column: bytes that are not UTF-8, unknown keys
in robot.toml, a calibration without its robot, run tables whose joint speeds
are not rad/s or lack a column, absurd times and loads."""

from __future__ import annotations

import csv
import io
import json
import pathlib

import numpy as np
import pytest

from elastocal.formats.plan import LoadSpec, load_plan, plan_toml
from elastocal.cli import main
from elastocal.compensation.files import read_path
from elastocal.drivers.config import load_cell_config
from elastocal.errors import InputError
from elastocal.formats.calibration import (
    CalibratedParameter,
    Calibration,
    DataFile,
    Residual,
    calibration_from_json,
    read_calibration,
    write_calibration,
)
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path, load_robot, parse_robot
from elastocal.formats.tables import (
    format_run_table,
    format_static_table,
    parse_run_table,
    parse_static_table,
    read_run_table,
    read_static_table,
    run_table_from_arrays,
)
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import FrictionPlan, SweepPlan, default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, simulate_static
from elastocal.model.kinds import CompensatorKind, TorqueSource

ROBOT = bundled_robot()
URDF_ROBOT = bundled_robot("hh150_urdf")
NOT_UTF8 = b"name = \"HH-150\"\n# caf\xe9 \xff\xfe\n"      # latin-1 on line 2
BOM = b"\xef\xbb\xbf"

STATIC = simulate_static(ROBOT, CellTruth(), seed=3, plan=StaticPlan(n_poses=2, n_loads=1, repeats=2))
RUNS = simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=5,
                     sweeps=SweepPlan(q3_values=(0.0,), q2_start=0.0, q2_end=0.4, step_rad=0.02),
                     friction=FrictionPlan(speeds_rad_s=(0.05,), loads=(("0", (0.0,) * 6),)))


def _calibration(robot: str | None = "HH-150") -> dict:
    doc = Calibration(robot=robot or "", created="2026-11-22T10:00:00Z", model=("joint_stiffness",),
                      torque=TorqueSource.CURRENT,
                      parameters=tuple(CalibratedParameter(f"k{j}", 5e5, unit="N*m/rad") for j in range(1, 7)),
                      residual=Residual(rms=8e-6, max=3e-5, n=10)).to_json()
    if robot is None:
        del doc["robot"]
    return doc


def _plan_text() -> str:
    return plan_toml(poses=[(0.2, 0.3, -0.4, 0.3, 1.0, 0.2)], loads=(LoadSpec("L1", mass_kg=60.0),),
                     markers=("R1",))


def _rows(text: str) -> list[list[str]]:
    return list(csv.reader(io.StringIO(text)))


def _text(rows: list[list[str]]) -> str:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    return out.getvalue()


def _scale_column(text: str, prefix: str, factor: float) -> str:
    rows = _rows(text)
    cols = [k for k, c in enumerate(rows[0]) if c.startswith(prefix)]
    for r in rows[1:]:
        for k in cols:
            if r[k]:
                r[k] = repr(float(r[k]) * factor)
    return _text(rows)


# ------------------------------------------------------------ 1. UTF-8 and BOM
READERS = {
    "robot.toml": load_robot,
    "cell.toml": load_cell_config,
    "plan.toml": load_plan,
    "cal.json": read_calibration,
    "static.csv": lambda p: read_static_table(p, ROBOT),
    "runs.csv": lambda p: read_run_table(p, ROBOT),
    "path.csv": lambda p: read_path(p, ROBOT),
}


@pytest.mark.parametrize("name", sorted(READERS))
def test_a_file_that_is_not_utf8_is_refused_naming_file_and_line(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(NOT_UTF8)
    with pytest.raises(InputError) as err:
        READERS[name](path)
    assert str(err.value) == f"{path}, line 2: not a UTF-8 text file (byte 0xe9 is not UTF-8)"


def test_a_urdf_that_is_not_utf8_is_refused_naming_the_robot_toml_key(tmp_path):
    (tmp_path / "r.urdf").write_bytes(b"<robot name='x'>\n<!-- \xff -->\n</robot>\n")
    text = bundled_robot_path("hh150_urdf").read_text().replace('urdf = "hh150.urdf"', 'urdf = "r.urdf"')
    (tmp_path / "robot.toml").write_text(text)
    with pytest.raises(InputError) as err:
        load_robot(tmp_path / "robot.toml")
    assert str(err.value) == (f"{tmp_path / 'robot.toml'}, column urdf: URDF {tmp_path / 'r.urdf'} is not a UTF-8 "
                              "text file (byte 0xff at line 2)")


@pytest.mark.parametrize("argv, name", [
    (["identify", "--robot", "{bad}", "--static", "{d}/static.csv"], "bad.toml"),
    (["devices", "--cell", "{bad}"], "bad.toml"),
    (["plan", "--robot", "{bad}", "--test-pose", "0,0.3,-0.4,0,1,0", "--load", "0,0,-600",
      "--out", "{d}/plan.toml"], "bad.toml"),
    (["compensate", "--robot", "{d}/robot.toml", "--calibration", "{bad}", "--path", "{d}/static.csv",
      "--out", "{d}/out.csv"], "bad.json"),
    (["history", "add", "--db", "{d}/h.sqlite", "--calibration", "{bad}"], "bad.json"),
])
def test_cli_reports_non_utf8_files_in_one_line_exit_2(sim_static, tmp_path, capsys, argv, name):
    bad = tmp_path / name
    bad.write_bytes(bytes(range(128, 256)) * 20)
    rc = main([a.format(bad=bad, d=sim_static) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert f"{bad}, line 1: not a UTF-8 text file (byte 0x80 is not UTF-8)" in err


def test_a_byte_order_mark_is_accepted_in_toml_and_json(tmp_path):
    robot = tmp_path / "robot.toml"
    robot.write_bytes(BOM + ROBOT.to_toml().encode())
    assert load_robot(robot).to_toml() == ROBOT.to_toml()
    cell = tmp_path / "cell.toml"
    cell.write_bytes(BOM + b'[cell]\nname = "c"\nrobot = "hh150"\n')
    assert load_cell_config(cell).name == "c"
    plan = tmp_path / "plan.toml"
    plan.write_bytes(BOM + _plan_text().encode())
    assert [p.id for p in load_plan(plan).static.poses] == ["P1"]
    cal = tmp_path / "cal.json"
    cal.write_bytes(BOM + json.dumps(_calibration()).encode())
    assert read_calibration(cal).robot == "HH-150"


# --------------------------------------------------- 2. unknown keys in robot.toml
@pytest.mark.parametrize("edit, key, reason", [
    (lambda t: t.replace("mass = 160.0", "mas = 160.0"), "joint[2].mas",
     "unknown key mas (did you mean mass?); known keys: name, type, a, alpha, d, theta, beta, offset, lower, upper, "
     "torque_constant, mass, com"),
    (lambda t: t.replace('name = "A3"\n', 'name = "A3"\nfoo = 1\n'), "joint[3].foo", "unknown key foo; known keys"),
    (lambda t: t.replace('name = "HH-150"\n', 'name = "HH-150"\nfoo = 1\n'), "foo",
     "unknown key foo; known keys: name, convention, gravity, urdf, urdf_xml, base_link, tip_link, joint, tool, "
     "compensator"),
    (lambda t: t.replace("[tool]\n", "[tool]\nflang = 1\n"), "tool.flang",
     "unknown key flang (did you mean flange?); known keys: load_point, markers, flange"),
    (lambda t: t.replace("[compensator]\n", "[compensator]\nL = 1.0\n"), "compensator.L",
     "unknown key L for a hydropneumatic compensator; known keys: kind, joint, a, b, h, C, l_c"),
    (lambda t: t.replace("[compensator]\n", "[compensator]\nlc = 1.0\n"), "compensator.lc",
     "unknown key lc (did you mean l_c?)"),
    (lambda t: t.replace("[[joint]]\n", "[[joint]]\n[joint.extra]\nx = 1\n", 1), "joint[1].extra",
     "unknown key extra"),
])
def test_unknown_robot_keys_are_refused_naming_the_key(edit, key, reason):
    text = edit(ROBOT.to_toml())
    assert text != ROBOT.to_toml()
    with pytest.raises(InputError) as err:
        parse_robot(text, source="robot.toml")
    assert str(err.value).startswith(f"robot.toml, column {key}: {reason}")


def test_a_spring_compensator_refuses_hydropneumatic_keys():
    text = ROBOT.to_toml().split("[compensator]")[0] + (
        '[compensator]\nkind = "spring"\njoint = 2\na = 0.3\nL = 0.8\nalpha = 0.1\nh = 0.1\n')
    with pytest.raises(InputError) as err:
        parse_robot(text, source="robot.toml")
    assert str(err.value) == ("robot.toml, column compensator.h: unknown key h for a spring compensator; "
                              "known keys: kind, joint, a, L, alpha, K_c, s0")
    spring = parse_robot(text.replace("h = 0.1\n", "K_c = 1.0e5\ns0 = 0.5\n"), source="robot.toml")
    assert spring.compensator.kind is CompensatorKind.SPRING and spring.compensator.nominal == (("K_c", 1.0e5), ("s0", 0.5))


def _without_compensator() -> str:
    return ROBOT.to_toml().split("[compensator]")[0]


@pytest.mark.parametrize("text, key, reason", [
    ("compensator = 5\n" + _without_compensator(), "compensator", "expected a table, got 5"),
    (_without_compensator().replace('name = "HH-150"', "name = 5"), "name", "expected the robot's name as text"),
])
def test_robot_tables_and_name_of_the_wrong_type_are_refused(text, key, reason):
    with pytest.raises(InputError) as err:
        parse_robot(text, source="robot.toml")
    assert str(err.value).startswith(f"robot.toml, column {key}: {reason}")


def test_joint_entries_that_are_not_tables_are_refused():
    top = 'name = "x"\njoint = [1, 2, 3, 4, 5, 6]\n[tool]\nload_point = [0.0, 0.0, 0.1]\n'
    with pytest.raises(InputError) as err:
        parse_robot(top, source="robot.toml")
    assert str(err.value) == "robot.toml, column joint[1]: expected a table, got 1"


def test_marker_names_are_free():
    text = ROBOT.to_toml().replace("[tool.markers]\n", "[tool.markers]\nmy_reflector_7 = [0.0, 0.1, 0.2]\n")
    assert "my_reflector_7" in parse_robot(text).marker_names


def test_every_robot_the_project_writes_still_parses(tmp_path):
    for robot in (ROBOT, URDF_ROBOT):
        again = parse_robot(robot.to_toml(), source="again.toml")
        assert again.to_toml() == robot.to_toml()
    for name in ("hh150", "hh150_urdf"):
        assert load_robot(bundled_robot_path(name)).name == "HH-150"
    assert main(["sim", "static", "--seed", "2", "--poses", "2", "--out", str(tmp_path)]) == 0
    assert load_robot(tmp_path / "robot.toml").name == "HH-150"


# ------------------------------------------------------ 3. the calibration's robot
@pytest.mark.parametrize("robot, reason", [
    (None, "missing: the calibration must name its robot"),
    ("", "expected the robot's name, got ''"),
    ("  ", "expected the robot's name, got '  '"),
])
def test_a_calibration_without_its_robot_is_refused(tmp_path, robot, reason):
    doc = _calibration(robot)
    if robot is not None:
        doc["robot"] = robot
    _assert_calibration_refused(tmp_path, doc, "robot", reason)


def _assert_calibration_refused(tmp_path, doc, key, reason):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        read_calibration(path)
    assert str(err.value).startswith(f"{path}, column {key}: {reason}")


@pytest.mark.parametrize("key, value, reason", [
    ("model", "joint_stiffness", "expected a list of effect names"),
    ("torque", "amps", "expected one of current, force, got 'amps'"),
    ("data", ["static.csv"], "expected a list of objects with path and sha256"),
    ("residual", 3, "expected an object, got 3"),
])
def test_calibration_fields_of_the_wrong_type_are_refused(tmp_path, key, value, reason):
    doc = _calibration()
    doc[key] = value
    _assert_calibration_refused(tmp_path, doc, key, reason)


@pytest.mark.parametrize("argv", [
    ["compensate", "--robot", "{d}/robot.toml", "--calibration", "{cal}", "--path", "{d}/static.csv",
     "--out", "{d}/out.csv"],
    ["history", "add", "--db", "{d}/h.sqlite", "--calibration", "{cal}"],
])
def test_cli_refuses_a_calibration_without_robot(sim_static, tmp_path, capsys, argv):
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(_calibration(None)))
    rc = main([a.format(cal=cal, d=sim_static) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert f"{cal}, column robot: missing: the calibration must name its robot" in err
    assert not (sim_static / "h.sqlite").exists()


def test_a_written_calibration_reads_back(tmp_path):
    doc = _calibration()
    doc["data"] = [{"path": "s.csv", "sha256": "0"}]
    cal = calibration_from_json(doc, "the test")
    assert cal.data == (DataFile("s.csv", "0"),) and cal.residual == Residual(rms=8e-6, max=3e-5, n=10)
    assert cal.find("k3") == CalibratedParameter("k3", 5e5, unit="N*m/rad")
    write_calibration(tmp_path / "cal.json", cal)
    assert read_calibration(tmp_path / "cal.json") == cal
    assert json.loads((tmp_path / "cal.json").read_text()) == doc


# ------------------------------------------------------------- 4. joint speeds
def test_simulated_runs_pass():
    again = parse_run_table(format_run_table(RUNS), ROBOT, source="runs.csv")
    np.testing.assert_array_equal(again.dq, RUNS.dq)


def _first_line(run: str) -> int:
    return int(RUNS.line[RUNS.run == run][0])


def test_speeds_in_degrees_per_second_are_refused():
    text = _scale_column(format_run_table(RUNS), "dq", 180.0 / np.pi)
    with pytest.raises(InputError) as err:
        parse_run_table(text, ROBOT, source="runs.csv")
    run = RUNS.run[0]
    assert str(err.value) == (f"runs.csv, line {_first_line(run)}, column dq2: run {run}: the speeds dq2 integrated "
                              "over t give 57.3 times the travel of q2 (0.4 rad), near 180/pi = 57.3; degrees per "
                              "second? speeds are rad/s")


def test_speeds_in_degrees_are_refused_in_a_run_of_every_joint():
    uv = RUNS.subset(RUNS.direction != "+").subset(RUNS.direction[RUNS.direction != "+"] != "-")
    text = _scale_column(format_run_table(uv), "dq", 180.0 / np.pi)
    with pytest.raises(InputError, match=r"runs\.csv, line 2, column dq1: run .*: the speeds dq1 .* 57\.3 times .*"
                                         r"degrees per second\? speeds are rad/s"):
        parse_run_table(text, ROBOT, source="runs.csv")


@pytest.mark.parametrize("prefix, factor, reason", [
    ("dq", -1.0, "give -1 times the travel of q2 (0.4 rad): dq2 has the opposite sign of the motion"),
    ("dq", 60 / (2 * np.pi), "give 9.55 times the travel of q2 (0.4 rad); speeds are rad/s and times seconds"),
    ("dq", 0.0, "give 0 times the travel of q2 (0.4 rad); speeds are rad/s and times seconds"),
    ("t", 1000.0, "give 1e+03 times the travel of q2 (0.4 rad); speeds are rad/s and times seconds"),
])
def test_speeds_inconsistent_with_the_motion_are_refused(prefix, factor, reason):
    text = _scale_column(format_run_table(RUNS), prefix, factor)
    with pytest.raises(InputError) as err:
        parse_run_table(text, ROBOT, source="runs.csv")
    run = RUNS.run[0]
    assert str(err.value) == f"runs.csv, line {_first_line(run)}, column dq2: run {run}: the speeds dq2 integrated " \
                             f"over t {reason}"


def test_noisy_speeds_of_held_and_moving_joints_pass():
    rng = np.random.default_rng(7)
    n = 400
    t = np.arange(n) * 0.01
    q = np.zeros((n, 6)) + rng.normal(0.0, 1e-3, (n, 6))          # joints held, noisy encoders
    q[:, 1] += 0.05 * t                                             # joint 2 moves 0.2 rad
    dq = rng.normal(0.0, 2e-2, (n, 6))                              # noisy speeds
    dq[:, 1] += 0.05
    table = run_table_from_arrays(run=["a"] * n, direction=["+"] * n, load=["0"] * n, t=t, q=q, dq=dq)
    again = parse_run_table(format_run_table(table), ROBOT, source="runs.csv")
    assert len(again) == n
    with pytest.raises(InputError, match=r"line 2, column dq2: .* degrees per second\?"):
        parse_run_table(_scale_column(format_run_table(table), "dq", 180 / np.pi), ROBOT, source="runs.csv")


def test_a_short_run_that_hardly_moves_is_not_judged():
    t = np.array([0.0, 0.1, 0.2])
    q = np.zeros((3, 6))
    q[:, 1] = [0.0, 0.002, 0.004]                                   # 4 mrad of travel: too little to judge
    dq = np.zeros((3, 6))
    dq[:, 1] = 0.02 * 180 / np.pi
    table = run_table_from_arrays(run=["a"] * 3, direction=["+"] * 3, load=["0"] * 3, t=t, q=q, dq=dq)
    assert len(parse_run_table(format_run_table(table), ROBOT, source="runs.csv")) == 3


# ------------------------------------------------------ 5. missing run columns
@pytest.mark.parametrize("drop, column, group", [
    ("dq2", "dq2", "the joint speed vector needs all of dq1,dq2,dq3,dq4,dq5,dq6"),
    ("i6", "i6", "the current vector needs all of i1,i2,i3,i4,i5,i6"),
    ("mz", "mz", "the wrench needs all of fx,fy,fz,mx,my,mz"),
    ("y", "y", "a followed marker needs all of marker,x,y,z"),
])
def test_a_missing_column_of_a_group_is_reported_on_the_header(drop, column, group):
    rows = _rows(format_run_table(RUNS))
    k = rows[0].index(drop)
    text = _text([r[:k] + r[k + 1:] for r in rows])
    with pytest.raises(InputError) as err:
        parse_run_table(text, ROBOT, source="runs.csv")
    assert str(err.value) == f"runs.csv, line 1, column {column}: missing column(s) {drop}: {group} (or none of them)"


def test_a_group_left_out_entirely_is_accepted():
    rows = _rows(format_run_table(RUNS))
    keep = [k for k, c in enumerate(rows[0]) if c not in ("marker", "x", "y", "z", "fx", "fy", "fz", "mx", "my", "mz")]
    table = parse_run_table(_text([[r[k] for k in keep] for r in rows]), ROBOT, source="runs.csv")
    assert np.all(np.isnan(table.wrench)) and set(table.marker) == {""}


# --------------------------------------------------- 6. absurd times and loads
def _static_edit(line: int, column: str, value: str) -> str:
    rows = _rows(format_static_table(STATIC))
    rows[line - 1][rows[0].index(column)] = value
    return _text(rows)


@pytest.mark.parametrize("column, value, reason", [
    ("t", "1e308", "1e+308 s is not a plausible time (more than 1e+10 s from its origin); milliseconds or "
                   "nanoseconds? times are seconds"),
    ("t", "1.7e18", "1.7e+18 s is not a plausible time"),
    ("fz", "1e300", "1e+300 N is not a plausible load; forces are N, moments N*m"),
])
def test_absurd_times_and_loads_are_refused(column, value, reason):
    line = 2 if column == "t" else int(STATIC.line[STATIC.load != "0"][0])
    with pytest.raises(InputError) as err:
        parse_static_table(_static_edit(line, column, value), ROBOT, source="static.csv")
    assert str(err.value).startswith(f"static.csv, line {line}, column {column}: {reason}")


def test_absurd_run_time_is_refused():
    rows = _rows(format_run_table(RUNS))
    rows[-1][rows[0].index("t")] = "1e308"
    with pytest.raises(InputError, match=rf"runs\.csv, line {len(rows)}, column t: 1e\+308 s is not a plausible"):
        parse_run_table(_text(rows), ROBOT, source="runs.csv")


def test_cli_diagnose_with_an_absurd_time_exits_2_without_warnings(sim_static, tmp_path, capsys):
    rows = _rows((sim_static / "static.csv").read_text())
    rows[5][rows[0].index("t")] = "1e308"
    bad = tmp_path / "static.csv"
    bad.write_text(_text(rows))
    rc = main(["diagnose", "--robot", str(sim_static / "robot.toml"), "--static", str(bad)])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "Warning" not in err
    assert f"{bad}, line 6, column t: 1e+308 s is not a plausible time" in err


@pytest.fixture(scope="module")
def sim_static(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("sim")
    assert main(["sim", "static", "--seed", "1", "--poses", "3", "--out", str(out)]) == 0
    return out


def test_fields_it_does_not_know_are_kept_and_the_history_keeps_the_whole_calibration(tmp_path):
    """Typed end to end: what the reader does not know survives a read, a write and a record
    in the history, and the history gives back the calibration it was given (the absolute
    residual and the robot description included: `check --calibration` finds its record)."""
    from elastocal.acquisition.history import History

    doc = _calibration()
    doc["parameters"]["k2"]["comment"] = {"by": "hand", "at": [1, 2]}
    doc["parameters"]["k3"].update(std=4e3, determined=False, note="not determined: a test")
    doc["residual"]["noise_floor"] = 7e-6
    doc["residual"]["seed"] = 3
    doc["data"] = [{"path": "log.mcap", "sha256": "ab" * 32, "bytes": 1024}]
    doc["absolute_residual"] = {"rms": 2e-5, "max": 5e-5, "n": 30, "noise_floor": 1.8e-5}
    doc["robot_description"] = ROBOT.to_toml()
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    cal = read_calibration(tmp_path / "cal.json")
    assert cal.find("k3").determined is False and cal.undetermined() == ("k3",)
    assert cal.residual.noise_floor == 7e-6 and cal.absolute_residual.n == 30
    assert cal.to_json() == doc
    assert list(cal.to_json()["parameters"]["k3"]) == ["value", "std", "unit", "determined", "note"]
    with History(tmp_path / "h.sqlite") as h:
        h.add_calibration(cal, time_ns=1)
        recorded = h.current().calibration
    assert recorded == cal and recorded.to_json() == cal.to_json()


def test_plan_toml_reads_back_what_it_was_given():
    """plan.toml written by tomli-w: every section and a description with quotes and a
    backslash (text a hand-written template pasted unescaped) read back as given."""
    from elastocal.formats.plan import CheckSpec, FrictionSpec, SettleSpec, SweepSpec, parse_plan

    q = [(0.2, 0.3, -0.4, 0.3, 1.0, 0.2), (0.1, 0.5, -0.2, 0.0, 0.8, -0.1)]
    loads = (LoadSpec("L1", mass_kg=60.0, description='a "60 kg" plate \\ bolted'),
             LoadSpec("L2", force_n=(-635.0, 635.0, -635.0), moment_nm=(0.0, 12.5, 0.0)))
    settle = SettleSpec(speed_rad_s=0.004, spread_m=3e-5, window_s=0.25, timeout_s=30.0)
    friction = (FrictionSpec("F1", start=q[0], end=q[1], speeds_rad_s=(0.1, 0.3), loads=("0", "L1"), repeats=2,
                             marker="R1"),)
    sweep = SweepSpec(q=q[0], q2_from=-0.5, q2_to=0.7, speed_rad_s=0.2, repeats=2, load="L1", marker="R2")
    check = CheckSpec(poses=("A",), load="L2", friction="F1")
    text = plan_toml(poses={"A": q[0], "B": q[1]}, loads=loads, markers=("R1", "R2"), name='cell "7"', repeats=4,
                     reading_s=0.1, speed_rad_s=0.25, settle=settle, friction=friction, sweep=sweep, check=check,
                     procedures=("static", "friction", "sweep", "check"), pose_loads={"B": ("L2",)},
                     expected={"evidence": np.float64(12.5), "poses": np.int64(2), "sub": {"k2": 1.5, "gone": None}})
    plan = parse_plan(text)
    assert plan.name == 'cell "7"' and plan.settle == settle and plan.loads == loads
    assert [(p.id, p.q, p.loads) for p in plan.static.poses] == [("A", q[0], ("L1", "L2")), ("B", q[1], ("L2",))]
    assert (plan.static.markers, plan.static.repeats, plan.static.reading_s, plan.static.speed_rad_s) == \
        (("R1", "R2"), 4, 0.1, 0.25)
    assert plan.friction == friction and plan.sweep == sweep and plan.check == check
    assert plan.procedures == ("static", "friction", "sweep", "check")
    import tomllib

    assert tomllib.loads(text)["expected"] == {"evidence": 12.5, "poses": 2, "sub": {"k2": 1.5}}


def test_robot_names_with_quotes_read_back():
    """robot.toml's text values are quoted by tomli-w: a name with quotes and a backslash
    reads back as written, and the plain ones keep the bytes calibration files embed."""
    import dataclasses

    odd = dataclasses.replace(ROBOT, name='HH-150 "left" \\ cell',
                              joints=tuple(dataclasses.replace(j, name=f'A{i} "{i}"')
                                           for i, j in enumerate(ROBOT.joints, 1)))
    again = parse_robot(odd.to_toml(), source="again.toml")
    assert again.name == odd.name and [j.name for j in again.joints] == [j.name for j in odd.joints]
    assert 'name = "HH-150"\n' in ROBOT.to_toml() and 'name = "A1"\n' in ROBOT.to_toml()
