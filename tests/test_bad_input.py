"""Bad input gets one line naming the input, exit 2 and nothing written: CSV fields over the
csv module's limit, malformed events in a valid log, implausible calibrations (sizes, units,
std, noise floor, unknown effects, a missing stiffness), logs held to the checks tables get,
duplicate columns, robot.toml and cell.toml values in the wrong unit."""

from __future__ import annotations

import csv
import io
import json
import math
import pathlib

import numpy as np
import pytest

from elastocal.acquisition.logreader import LogReader
from elastocal.acquisition.logwriter import write_log_from_tables
from elastocal.acquisition.recorder import Recorder
from elastocal.cli import main
from elastocal.formats.calibration import read_calibration
from elastocal.formats.robot_toml import bundled_robot
from elastocal.formats.tables import write_run_table, write_static_table
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, simulate_static
from elastocal.model.kinds import TorqueSource

ROBOT = bundled_robot()


def run_cli(capsys, argv: list[str]) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def assert_refused(rc: int, err: str, *needles: str) -> None:
    """Exit 2 with exactly one line on stderr, no traceback, holding every needle."""
    assert rc == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in err, (n, err)


def rewrite_log(src: pathlib.Path, dst: pathlib.Path, edit) -> None:
    """Copy a log message by message; ``edit(topic, payload)`` returns the new payload
    (any JSON value, or bytes written as they are) or the payload unchanged."""
    reader = LogReader(src)
    with Recorder(dst, clock=lambda: 1) as rec:
        for topic, m in reader.raw_messages():
            if topic == "/elastocal/session":
                continue
            new = edit(topic, json.loads(m.data))
            data = new if isinstance(new, bytes) else json.dumps(new).encode()
            rec.copy(topic, m.log_time, m.publish_time, data)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> pathlib.Path:
    d = tmp_path_factory.mktemp("bad")
    static = simulate_static(ROBOT, CellTruth(), seed=4, plan=StaticPlan(n_poses=3, n_loads=1, repeats=2))
    runs = simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=4, sweeps=None,
                         friction=FrictionPlan(speeds_rad_s=(0.05,), loads=(("0", (0.0,) * 6),), samples=60))
    (d / "robot.toml").write_text(ROBOT.to_toml())
    write_static_table(d / "static.csv", static)
    write_run_table(d / "runs.csv", runs)
    write_log_from_tables(d / "log.mcap", ROBOT, static=static, runs=runs)
    (d / "path.csv").write_text("t,q1,q2,q3,q4,q5,q6,fx,fy,fz,mx,my,mz\n"
                                + "".join(f"{0.1 * i},0.1,{0.2 + 0.01 * i},-0.5,0.0,1.0,0.0,0,0,-1000,0,0,0\n"
                                          for i in range(5)))
    assert main(["identify", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
                 "--out", str(d / "cal.json")]) == 0
    doc = json.loads((d / "cal.json").read_text())
    doc["parameters"]["k1"].update(value=5.6e5, std=5e3, determined=True)   # these few random poses do not determine k1
    (d / "cal.json").write_text(json.dumps(doc))
    (d / "cell.toml").write_text('[cell]\nname = "c"\nrobot = "hh150"\n')
    return d


def _csv_rows(path: pathlib.Path) -> list[list[str]]:
    return list(csv.reader(io.StringIO(path.read_text())))


def _write_rows(path: pathlib.Path, rows: list[list[str]]) -> None:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    path.write_text(out.getvalue())


# ------------------------------------------------------------- 6. tracebacks
@pytest.mark.parametrize("table, argv", [
    ("static.csv", ["identify", "--robot", "{d}/robot.toml", "--static", "{bad}"]),
    ("runs.csv", ["identify", "--robot", "{d}/robot.toml", "--runs", "{bad}",
                  "--model", "coulomb_friction,viscous_friction"]),
    ("path.csv", ["compensate", "--robot", "{d}/robot.toml", "--calibration", "{d}/cal.json", "--path", "{bad}",
                  "--out", "{tmp}/out.csv"]),
])
def test_a_csv_field_over_the_csv_limit_is_one_line(data, tmp_path, capsys, table, argv):
    rows = _csv_rows(data / table)
    rows[3][1] = "x" * 140_000
    bad = tmp_path / table
    _write_rows(bad, rows)
    rc, _, err = run_cli(capsys, [a.format(d=data, bad=bad, tmp=tmp_path) for a in argv])
    assert_refused(rc, err, f"{bad}, line 4: not a readable CSV record: a field longer than 131,072 characters")
    assert not (tmp_path / "out.csv").exists()


def _drop(key: str):
    def edit(topic, v):
        if topic == "/procedure/event" and isinstance(v, dict) and v.get("kind") == "reading":
            return {k: x for k, x in v.items() if k != key}
        return v
    return edit


def _null_event(topic, v):
    return None if topic == "/procedure/event" and isinstance(v, dict) and v.get("kind") == "reading" else v


EVENT_EDITS = {
    "no window_ns": (_drop("window_ns"), "window_ns' is a required property"),
    "no pose": (_drop("pose"), "'pose' is a required property"),
    "null payload": (_null_event, "None is not of type 'object'"),
    "window backwards": (lambda t, v: {**v, "window_ns": v["window_ns"][::-1]}
                         if t == "/procedure/event" and v.get("kind") == "reading" else v, "ends before it starts"),
    "q in text": (lambda t, v: {**v, "q": ["a"] * 6} if t == "/procedure/event" and v.get("kind") == "reading"
                  else v, "'a' is not of type 'number'"),
    "run without direction": (lambda t, v: {k: x for k, x in v.items() if k != "direction"}
                              if t == "/procedure/event" and v.get("kind") == "run_start" else v,
                              "'direction' is a required property"),
    "tracker marker a number": (lambda t, v: {**v, "marker": 5} if t == "/tracker" else v,
                                "is not a tracker sample"),
    "document null": (lambda t, v: None if t == "/elastocal/robot" else v, "not a valid elastocal.Document"),
}


@pytest.mark.parametrize("name", sorted(EVENT_EDITS))
@pytest.mark.parametrize("command", ["export", "identify", "diagnose", "report", "check"])
def test_malformed_payloads_in_a_valid_log_are_one_line(data, tmp_path, capsys, name, command):
    edit, needle = EVENT_EDITS[name]
    bad = tmp_path / "bad.mcap"
    rewrite_log(data / "log.mcap", bad, edit)
    argv = {"export": ["export", bad, "--out", tmp_path / "out"],
            "identify": ["identify", bad, "--out", tmp_path / "cal.json"],
            "diagnose": ["diagnose", bad],
            "report": ["report", bad, "--out", tmp_path / "report.html"],
            "check": ["check", "--cell", data / "cell.toml", "--calibration", data / "cal.json", "--log", bad,
                      "--no-record"]}[command]
    rc, _, err = run_cli(capsys, argv)
    assert_refused(rc, err, str(bad), needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.mcap"]


def _edit_cal(data: pathlib.Path, tmp_path: pathlib.Path, edit) -> pathlib.Path:
    doc = json.loads((data / "cal.json").read_text())
    edit(doc)
    out = tmp_path / "cal.json"
    out.write_text(json.dumps(doc))
    return out


def _set_k(value):
    def edit(doc):
        doc["parameters"]["k2"]["value"] = value
    return edit


CAL_EDITS = {
    "k tiny": (_set_k(1e-300), "column parameters.k2.value: 1e-300 N*m/rad is not a plausible joint stiffness"),
    "k huge": (_set_k(1e300), "column parameters.k2.value: 1e+300 N*m/rad is not a plausible joint stiffness"),
    "no k2": (lambda d: d["parameters"].pop("k2"), "column parameters.k2: missing k2: a calibration with joint stiffness"),
    "std -1": (lambda d: d["parameters"]["k3"].update(std=-1), "column parameters.k3.std: a standard deviation"),
    "std text": (lambda d: d["parameters"]["k3"].update(std="x"), "column parameters.k3.std: std must be a finite"),
    "floor x": (lambda d: d["residual"].update(noise_floor="x"), "column residual.noise_floor: expected a finite"),
    "unknown effect": (lambda d: d["model"].append("gremlins"),
                       "column model: unknown effect 'gremlins' in the calibration"),
    "unknown unit": (lambda d: d["parameters"]["k1"].update(unit="furlong"),
                     "column parameters.k1.unit: unknown unit symbol 'furlong'"),
    "wrong kind of unit": (lambda d: d["parameters"]["k1"].update(unit="N*m"),
                           "column parameters.k1.unit: 'N*m' is not a unit of the same kind as 'N*m/rad'"),
    "parameter not an object": (lambda d: d["parameters"].update(k1=5), "column parameters.k1: expected an object"),
}


@pytest.mark.parametrize("name", sorted(CAL_EDITS))
@pytest.mark.parametrize("command", ["check", "compensate"])
def test_implausible_calibrations_are_refused_naming_file_and_key(data, tmp_path, capsys, name, command):
    edit, needle = CAL_EDITS[name]
    cal = _edit_cal(data, tmp_path, edit)
    argv = {"check": ["check", "--cell", data / "cell.toml", "--calibration", cal, "--static", data / "static.csv",
                      "--no-record"],
            "compensate": ["compensate", "--robot", data / "robot.toml", "--calibration", cal,
                           "--path", data / "path.csv", "--out", tmp_path / "out.csv"]}[command]
    rc, _, err = run_cli(capsys, argv)
    assert_refused(rc, err, f"{cal}, {needle}")
    assert not (tmp_path / "out.csv").exists()


def test_calibration_units_are_converted(data, tmp_path):
    """k in N*m/deg is converted to N*m/rad (a deflection 57x too large otherwise), and compensates as the SI file."""
    doc = json.loads((data / "cal.json").read_text())
    k_si = {n: p["value"] for n, p in doc["parameters"].items()}
    for n, p in doc["parameters"].items():
        p["value"] *= math.pi / 180
        p["std"] *= math.pi / 180
        p["unit"] = "N*m/deg"
    doc["parameters"]["k6"].update(value=k_si["k6"] / 1e3, std=doc["parameters"]["k6"]["std"] * 180 / math.pi / 1e3,
                                   unit="kN*m/rad")
    (tmp_path / "deg.json").write_text(json.dumps(doc))
    cal = read_calibration(tmp_path / "deg.json")
    for n, v in k_si.items():
        assert cal.value(n) == pytest.approx(v, rel=1e-12)
        assert cal.find(n).unit == "N*m/rad"
    out = {}
    for name in ("deg.json", "si.json"):
        src = tmp_path / name if name == "deg.json" else data / "cal.json"
        assert main(["compensate", "--robot", str(data / "robot.toml"), "--calibration", str(src), "--path",
                     str(data / "path.csv"), "--out", str(tmp_path / f"{name}.csv")]) == 0
        out[name] = np.loadtxt(tmp_path / f"{name}.csv", delimiter=",", skiprows=1)
    assert np.allclose(out["deg.json"], out["si.json"], rtol=1e-9, atol=1e-12)


# --------------------------------------------- 7. logs get the checks tables get
def _scale_events(key: str, factor: float, topic_kind: str = "reading"):
    def edit(topic, v):
        if topic == "/procedure/event" and v.get("kind") == topic_kind and key in v:
            return {**v, key: [x * factor for x in v[key]]}
        return v
    return edit


def _scale_tracker(factor: float):
    def edit(topic, v):
        if topic == "/tracker":
            return {**v, "x": v["x"] * factor, "y": v["y"] * factor, "z": v["z"] * factor}
        return v
    return edit


def _scale_drives(key: str, factor: float):
    def edit(topic, v):
        if topic.startswith("/drive/") and v.get(key) is not None:
            return {**v, key: v[key] * factor}
        return v
    return edit


LOG_UNITS = {
    "positions in mm": (_scale_tracker(1e3), "millimetres? positions are metres"),
    "angles in degrees": (_scale_events("q", 180 / math.pi), "degrees? angles in files are radians"),
    "currents in mA": (_scale_drives("current_a", 1e3), "not a plausible motor current"),
    "drive positions in degrees": (_scale_drives("position_rad", 180 / math.pi), "outside the joint limits"),
}


@pytest.mark.parametrize("name", sorted(LOG_UNITS))
def test_logs_get_the_checks_tables_get(data, tmp_path, capsys, name):
    edit, needle = LOG_UNITS[name]
    bad = tmp_path / "bad.mcap"
    rewrite_log(data / "log.mcap", bad, edit)
    for argv in (["export", bad, "--out", tmp_path / "out"], ["identify", bad],
                 ["check", "--cell", data / "cell.toml", "--calibration", data / "cal.json", "--log", bad,
                  "--no-record"]):
        rc, _, err = run_cli(capsys, argv)
        assert_refused(rc, err, str(bad), needle, "of the exported")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("table", ["static.csv", "runs.csv", "path.csv"])
def test_duplicate_column_names_are_refused(data, tmp_path, capsys, table):
    rows = _csv_rows(data / table)
    k = rows[0].index("q3")
    rows[0][k] = "q2"
    bad = tmp_path / table
    _write_rows(bad, rows)
    flag = {"static.csv": "--static", "runs.csv": "--runs"}.get(table)
    if flag:
        argv = ["identify", "--robot", data / "robot.toml", flag, bad]
    else:
        argv = ["compensate", "--robot", data / "robot.toml", "--calibration", data / "cal.json", "--path", bad,
                "--out", tmp_path / "out.csv"]
    rc, _, err = run_cli(capsys, argv)
    assert_refused(rc, err, f"{bad}, line 1, column q2: column q2 appears twice in the header")


# ------------------------------------------------- 7. robot.toml and cell.toml
def _robot_text(edit) -> str:
    text = ROBOT.to_toml()
    new = edit(text)
    assert new != text
    return new


ROBOT_EDITS = {
    "a in mm": (lambda t: t.replace("a = 0.35", "a = 350.0"), "joint[2].a: 350 m is longer than 10 m; millimetres?"),
    "d in mm": (lambda t: t.replace("d = 0.683", "d = 683.0"), "joint[1].d: 683 m is longer than 10 m"),
    "com in mm": (lambda t: t.replace("com = [0.6, 0.0, 0.12]", "com = [600.0, 0.0, 120.0]"),
                  "joint[2].com: the centre of mass is 600 m from the joint frame along x; millimetres?"),
    "alpha in degrees": (lambda t: t.replace("alpha = -1.5707963267948966", "alpha = -90.0", 1),
                         "joint[2].alpha: -90 rad is more than a full turn; degrees?"),
    "offset in degrees": (lambda t: t.replace("offset = 3.141592653589793", "offset = 180.0"),
                          "joint[3].offset: 180 rad is more than a full turn; degrees?"),
    "negative C": (lambda t: t.replace("C = 4771.4", "C = -4771.4"),
                   "compensator.C: C = -4771.4 N*m: a compensator's C is positive"),
    "compensator geometry in mm": (lambda t: t.replace("a = 0.6\n", "a = 600.0\n"), "compensator.a: 600 m"),
    "load point in mm": (lambda t: t.replace("load_point = [0.1, 0.0, 0.35]", "load_point = [100.0, 0.0, 350.0]"),
                         "tool.load_point: the load point"),
    "mass in grams": (lambda t: t.replace("mass = 160.0", "mass = 160000.0"), "joint[2].mass: 160000 kg"),
    "gravity in mm/s2": (lambda t: t.replace("gravity = [0.0, 0.0, -9.81]", "gravity = [0.0, 0.0, -9810.0]"),
                         "gravity: |gravity| = 9810 m/s^2"),
}


@pytest.mark.parametrize("name", sorted(ROBOT_EDITS))
def test_robot_values_in_the_wrong_unit_are_refused(data, tmp_path, capsys, name):
    edit, needle = ROBOT_EDITS[name]
    bad = tmp_path / "robot.toml"
    bad.write_text(_robot_text(edit))
    rc, _, err = run_cli(capsys, ["identify", "--robot", bad, "--static", data / "static.csv"])
    assert_refused(rc, err, f"{bad}, column {needle}")


CELL = '''[cell]
name = "c"
robot = "hh150"

[tracker]
url = "tracker+tcp://127.0.0.1:700"
markers = ["R1", "R2"]

[controller]
url = "modbus+tcp://127.0.0.1:502"
[controller.registers]
command  = { address = 0, type = "uint16", access = "write" }
sequence = { address = 1, type = "uint16", access = "write" }
pose     = { address = 2, type = "uint16", access = "write" }
path     = { address = 3, type = "uint16", access = "write" }
ack      = { address = 20, type = "uint16" }
status   = { address = 21, type = "uint16" }
error    = { address = 22, type = "uint16" }
[controller.poses]
1 = [0.0, 0.2, -0.4, 0.0, 0.5, 0.0]
[[controller.path]]
id = 1
u = [0.0, 0.2, -0.4, 0.0, 0.5, 0.0]
v = [0.0, 0.9, -0.4, 0.0, 0.5, 0.0]
'''

CELL_EDITS = {
    "rate 1e9": (lambda t: t.replace('markers = ["R1", "R2"]', 'markers = ["R1", "R2"]\nrate_hz = 1e9'),
                 "column tracker.rate_hz: 1e+09 Hz is not a plausible sampling rate"),
    "unknown marker": (lambda t: t.replace('"R2"]', '"R9"]'), "column tracker.markers: unknown marker 'R9'"),
    "pose in degrees": (lambda t: t.replace("1 = [0.0, 0.2, -0.4, 0.0, 0.5, 0.0]", "1 = [0.0, 11.5, -23.0, 0.0, 28.6, 0.0]"),
                        "column controller.poses.1: q2 = 11.5 is more than a full turn; degrees?"),
    "path end outside limits": (lambda t: t.replace("v = [0.0, 0.9,", "v = [0.0, 2.5,"),
                                "column controller.path[1].v: q2 = 2.5 rad is outside the joint limits"),
    "path end in degrees": (lambda t: t.replace("v = [0.0, 0.9,", "v = [0.0, 9.2,"),
                            "column controller.path[1].v: q2 = 9.2 is more than a full turn"),
}


@pytest.mark.parametrize("name", sorted(CELL_EDITS))
def test_cell_values_in_the_wrong_unit_are_refused(data, tmp_path, capsys, name):
    edit, needle = CELL_EDITS[name]
    good = tmp_path / "good.toml"
    good.write_text(CELL)
    assert main(["check", "--cell", str(good), "--calibration", str(data / "cal.json"), "--static",
                 str(data / "static.csv"), "--no-record"]) in (0, 3)
    capsys.readouterr()
    bad = tmp_path / "cell.toml"
    bad.write_text(edit(CELL))
    rc, _, err = run_cli(capsys, ["check", "--cell", bad, "--calibration", data / "cal.json", "--static",
                                  data / "static.csv", "--no-record"])
    assert_refused(rc, err, f"{bad}, {needle}")


# ------------------------------------------------- 8. effects compensate leaves out
def test_compensate_says_which_calibrated_effects_it_does_not_model(data, tmp_path, capsys):
    doc = json.loads((data / "cal.json").read_text())
    doc["model"].append("link_compliance")
    doc["parameters"].update({"cl2x": {"value": 2e-8, "std": 1e-9, "unit": "rad/(N*m)"},
                              "cl3y": {"value": 1e-8, "std": 1e-9, "unit": "rad/(N*m)"}})
    (tmp_path / "lc.json").write_text(json.dumps(doc))
    argv = ["compensate", "--robot", data / "robot.toml", "--path", data / "path.csv", "--json"]
    rc, out, err = run_cli(capsys, argv + ["--calibration", data / "cal.json", "--out", tmp_path / "a.csv"])
    assert rc == 0 and err == "" and json.loads(out)["unmodelled"] == {}
    # refused by name before anything is written, unless left out knowingly
    rc, out, err = run_cli(capsys, argv + ["--calibration", tmp_path / "lc.json", "--out", tmp_path / "b.csv"])
    assert rc == 2 and "link_compliance (cl2x, cl3y)" in err and "--without link_compliance" in err
    assert not (tmp_path / "b.csv").exists()
    rc, out, err = run_cli(capsys, argv + ["--calibration", tmp_path / "lc.json", "--out", tmp_path / "b.csv",
                                           "--without", "link_compliance"])
    assert rc == 0
    assert json.loads(out)["unmodelled"] == {"link_compliance": ["cl2x", "cl3y"]}
    assert err == (f"note: compensate does not model link_compliance (cl2x, cl3y in {tmp_path / 'lc.json'}): "
                   "the compensated path leaves its deflection uncorrected\n")


# ----------------------------------------- 9. non-convergence, appended logs, --write-cell
def test_a_load_too_large_names_file_line_and_column(data, tmp_path, capsys):
    rows = _csv_rows(data / "path.csv")
    rows[3][rows[0].index("fy")] = "-4e7"
    bad = tmp_path / "path.csv"
    _write_rows(bad, rows)
    rc, _, err = run_cli(capsys, ["compensate", "--robot", data / "robot.toml", "--calibration", data / "cal.json",
                                  "--path", bad, "--out", tmp_path / "out.csv"])
    assert_refused(rc, err, f"{bad}, line 4, column fy: the static model does not converge under the wrench")
    assert not (tmp_path / "out.csv").exists()
    bare = tmp_path / "bare.csv"
    _write_rows(bare, [r[:7] for r in _csv_rows(data / "path.csv")])
    rc, _, err = run_cli(capsys, ["compensate", "--robot", data / "robot.toml", "--calibration", data / "cal.json",
                                  "--path", bare, "--out", tmp_path / "out.csv", "--wrench", "0,0,-1e8,0,0,0"])
    assert_refused(rc, err, "--wrench: the static model does not converge", "at sample 1 of")


@pytest.mark.parametrize("tail", ["copy", "garbage"])
def test_bytes_appended_to_a_log_are_noted(data, tmp_path, capsys, tail):
    log = (data / "log.mcap").read_bytes()
    extra = log if tail == "copy" else bytes(range(256)) * 3
    bad = tmp_path / "log.mcap"
    bad.write_bytes(log + extra)
    rc, out, err = run_cli(capsys, ["identify", data / "log.mcap", "--json"])
    assert rc == 0 and err == ""
    reference = json.loads(out)["parameters"]
    for argv in (["identify", bad, "--json"], ["export", bad, "--out", tmp_path / f"out-{tail}"]):
        rc, out, err = run_cli(capsys, argv)
        assert rc == 0
        assert err == (f"note: {bad} has {len(extra)} bytes after the end of its MCAP data (a second copy or "
                       "garbage appended to the file?); they were ignored\n")
        if argv[0] == "identify":
            assert json.loads(out)["parameters"] == reference


def test_sim_serve_write_cell_refuses_to_overwrite_without_force(tmp_path, capsys):
    cell = tmp_path / "served.toml"
    cell.write_text("# mine\n")
    rc, _, err = run_cli(capsys, ["sim", "serve", "--write-cell", cell, "--duration", "0.2"])
    assert_refused(rc, err, f"{cell}: already exists", "--force")
    assert cell.read_text() == "# mine\n"
    rc, _, err = run_cli(capsys, ["sim", "serve", "--write-cell", cell, "--duration", "0.2", "--force", "--json"])
    assert rc == 0, err
    assert "[cell]" in cell.read_text() and not list(tmp_path.glob(".*partial*"))


# ------------------------------------------- 10. unattended checks, friction drift
def _check_plan(friction: bool = True, check_poses: bool = True) -> str:
    from elastocal.formats.plan import CheckSpec, FrictionSpec, LoadSpec, SettleSpec, plan_toml

    poses = {"P1": (0.2, 0.3, -0.4, 0.3, 1.0, 0.2), "P2": (0.5, 0.55, -0.2, 0.6, 1.2, 0.5)}
    spec = (FrictionSpec("F1", start=(-0.2, 0.3, -0.5, -0.1, 0.6, -0.1), end=(0.0, 0.4, -0.4, 0.1, 0.7, 0.1),
                         speeds_rad_s=(0.2,), loads=("0",) if check_poses else ("L1",)),)
    return plan_toml(poses=poses, loads=(LoadSpec("L1", force_n=(-635.0, 635.0, -635.0)),),
                     markers=("R1", "R2", "R3"), repeats=2, reading_s=0.04, speed_rad_s=0.8,
                     settle=SettleSpec(speed_rad_s=2e-3, spread_m=60e-6, window_s=0.15, timeout_s=20.0),
                     friction=spec, check=CheckSpec(poses=("P1", "P2") if check_poses else (), load="L1",
                                                    friction="F1" if friction else None))


def test_unattended_procedure_skips_what_needs_a_person(tmp_path):
    from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
    from elastocal.acquisition.logreader import read_log
    from elastocal.formats.plan import parse_plan
    from elastocal.acquisition.procedures import run_procedures
    from elastocal.errors import InputError
    from elastocal.sims.cell import SimCell

    timing = VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0)
    io = VirtualCellIO(SimCell(ROBOT, CellTruth()), seed=3, timing=timing)
    out = run_procedures(io, parse_plan(_check_plan()), tmp_path / "u.mcap", procedures=("check",), unattended=True)
    assert out.status == "completed" and out.skipped == ("check pose P1 under load L1", "check pose P2 under load L1")
    contents = read_log(tmp_path / "u.mcap")
    kinds = [e["kind"] for e in contents.events]
    assert "prompt" not in kinds and kinds.count("run_start") == 2
    # what the robot can do alone: each check pose read unloaded, nothing under load
    readings = [e for e in contents.events if e["kind"] == "reading"]
    assert {(e["pose"], e["load"]) for e in readings} == {("P1", "0"), ("P2", "0")} and len(readings) == 2 * 2 * 3
    assert [e["text"] for e in contents.events if e["kind"] == "unattended"] == [
        "no person at the cell: the cell is taken as unloaded; skipped check pose P1 under load L1; "
        "check pose P2 under load L1"]
    # a check of no pose whose friction run is under a load: nothing left without a person
    with pytest.raises(InputError, match="no step of check runs without a person at the cell"):
        run_procedures(VirtualCellIO(SimCell(ROBOT, CellTruth()), seed=3, timing=timing),
                       parse_plan(_check_plan(check_poses=False)), tmp_path / "v.mcap",
                       procedures=("check",), unattended=True)
    assert not (tmp_path / "v.mcap").exists()


def test_a_check_without_terminal_runs_unattended(data, tmp_path, capsys, monkeypatch):
    """`check --sim` without a terminal (a scheduled run): the static poses, which need a person to
    hang the load, are skipped and said so; the friction runs are checked; nothing is asked."""
    from elastocal.sims.serve import example_cell_config

    from dataclasses import replace

    config = example_cell_config()
    config = replace(config, drives=tuple(replace(d, rate_hz=200.0) for d in config.drives),
                     controller=replace(config.controller, paths=tuple(
                         replace(p, u=(-0.2, 0.3, -0.5, -0.1, 0.6, -0.1), v=(0.0, 0.4, -0.4, 0.1, 0.7, 0.1))
                         if p.u == (-0.5, 0.2, -0.6, -0.3, 0.4, -0.2) else p for p in config.controller.paths)))
    (tmp_path / "cell.toml").write_text(config.to_toml())
    (tmp_path / "plan.toml").write_text(_check_plan())
    doc = json.loads((data / "cal.json").read_text())
    for j in range(1, 7):
        doc["parameters"][f"fc{j}"] = {"value": 50.0, "std": 1.0, "unit": "N*m"}
    doc["model"].append("coulomb_friction")
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    rc, out, err = run_cli(capsys, ["check", "--cell", tmp_path / "cell.toml", "--calibration", tmp_path / "cal.json",
                                    "--plan", tmp_path / "plan.toml", "--sim", "--out", tmp_path / "c.mcap",
                                    "--no-record", "--json"])
    assert rc in (0, 3), err
    obj = json.loads(out)
    assert obj["skipped"] == ["check pose P1 under load L1", "check pose P2 under load L1"]
    assert obj["deflection"] is None and obj["friction"]["joints"]
    assert obj["reasons"][-1] == ("not checked, no person at the cell (unattended): check pose P1 under load L1; "
                                  "check pose P2 under load L1")
    assert "aborted" not in err


def test_history_shows_friction_drift_and_plots_every_check(tmp_path, capsys):
    from elastocal.acquisition.history import History, drift_figure, drift_summary
    from elastocal.formats.calibration import CalibratedParameter as P, Calibration, Residual

    params = tuple(P(f"k{j}", 5e5, 5e2, "N*m/rad") for j in range(1, 7)) + (P("fc2", 90.0, 0.5, "N*m"),
                                                                           P("fv2", 600.0, 3.0, "N*m*s/rad"))
    cal = Calibration(robot="HH-150", created="2026-01-05T08:00:00Z",
                      model=("joint_stiffness", "coulomb_friction", "viscous_friction"), torque=TorqueSource.CURRENT,
                      parameters=params, residual=Residual(rms=8e-6, max=3e-5, n=100))
    t0 = 1_767_600_000 * 10**9
    db = tmp_path / "h.sqlite"
    with History(db) as h:
        cid = h.add_calibration(cal, time_ns=t0)
        h.add_check(calibration_id=cid, time_ns=t0 + 10**12, verdict="recalibrate", reasons=("friction",),
                    result={"verdict": "recalibrate", "deflection": None,
                            "friction": {"joints": {"2": {"measured": 143.1, "predicted": 90.0, "relative": 0.59}}}})
        h.add_check(calibration_id=cid, time_ns=t0 + 2 * 10**12, verdict="holds", reasons=("fine",),
                    result={"verdict": "holds", "deflection": {"rms_unexplained": 8e-6, "noise_floor": 7e-6,
                                                               "parameters": {}}, "friction": None})
        drift = h.drift()
    summary = drift_summary(drift)
    assert summary["fc2"]["latest"] == pytest.approx(90.0 * 143.1 / 90.0)
    assert summary["fc2"]["change"] == pytest.approx(0.59, abs=1e-3)
    assert summary["fv2"]["change"] == pytest.approx(0.59, abs=1e-3)
    assert summary["k2"]["change"] == 0.0
    rc, out, _ = run_cli(capsys, ["history", "--db", db])
    assert rc == 0 and "fc2   90 -> 143.1 N*m (+59.00 %)" in out
    fig = drift_figure(drift)
    for ax in fig.axes:                    # every check is marked on every panel
        assert sum(1 for line in ax.lines if line.get_linestyle() == "-" and len(line.get_xdata()) == 2
                   and line.get_xdata()[0] == line.get_xdata()[1]) >= 2
    checks_panel = fig.axes[-1]
    points = sum(len(c.get_offsets()) for c in checks_panel.collections)
    assert points == 2                     # the friction-only check too, on the axis


# ------------------------------------------------- found by the fuzz suite
def test_an_error_quoting_a_line_break_stays_one_line(data, tmp_path, capsys):
    text = (data / "path.csv").read_text().replace(",fx,", ',"f\nx",', 1)
    bad = tmp_path / "path.csv"
    bad.write_text(text)
    rc, _, err = run_cli(capsys, ["compensate", "--robot", data / "robot.toml", "--calibration", data / "cal.json",
                                  "--path", bad, "--out", tmp_path / "out.csv"])
    assert_refused(rc, err, f"{bad}, line 1: unknown column(s) f\\nx")


def test_identify_writes_no_calibration_its_reader_would_refuse(data, tmp_path, capsys):
    """A robot description whose torque constants are 1e6 times too large gives stiffness beyond
    any joint's: refused naming the data, no cal.json."""
    text = ROBOT.to_toml()
    for xi in ("169.6355", "220.8436", "127.0724", "138.3101", "139.4627"):
        text = text.replace(f"torque_constant = {xi}", f"torque_constant = {xi}e6")
    (tmp_path / "robot.toml").write_text(text)
    rc, _, err = run_cli(capsys, ["identify", "--robot", tmp_path / "robot.toml", "--static", data / "static.csv",
                                  "--out", tmp_path / "cal.json"])
    assert_refused(rc, err, f"{data / 'static.csv'}: the fit gives k", "is not a plausible joint stiffness")
    assert not (tmp_path / "cal.json").exists()


def test_a_can_node_in_hex_is_read_as_the_drives_read_it():
    from elastocal.drivers.config import parse_cell_config
    from elastocal.errors import InputError

    text = ('[cell]\nrobot = "hh150"\n[[drive]]\njoint = 1\nurl = "canopen://virtual/x?node=0x10"\n'
            '[[drive]]\njoint = 2\nurl = "canopen://virtual/x?node=16"\n')
    with pytest.raises(InputError, match="joints 1 and 2 use the same CAN node 16"):
        parse_cell_config(text, source="cell.toml")


def test_a_corrupt_length_field_in_a_log_is_one_line_not_a_memory_error(data, tmp_path, capsys):
    """A bit flipped in a chunk's length field claims gigabytes: refused before anything is allocated."""
    import struct

    raw = bytearray((data / "log.mcap").read_bytes())
    pos = 8
    while raw[pos] != 0x06:                          # the first Chunk record
        pos += 9 + struct.unpack_from("<Q", raw, pos + 1)[0]
    field = pos + 9 + 8 + 8 + 8 + 4                  # start, end, uncompressed size, crc
    field += 4 + struct.unpack_from("<I", raw, field)[0]   # the compression name
    raw[field + 4] ^= 0x80                           # records length += 2**39
    bad = tmp_path / "log.mcap"
    bad.write_bytes(bytes(raw))
    rc, _, err = run_cli(capsys, ["export", bad, "--out", tmp_path / "out"])
    assert_refused(rc, err, f"{bad}: corrupt MCAP record near byte", "more than the rest of the file holds")
    bad.write_bytes(bytes(raw[:-100]))               # the same in a file without its end
    rc, _, err = run_cli(capsys, ["identify", bad])
    assert rc in (0, 2) and "Traceback" not in err and "MemoryError" not in err


@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_data_that_cannot_determine_the_model_exit_2_naming_the_table(data, tmp_path, capsys, command):
    """Too few deflections for the model's parameters is a refusal the data decide
    (UnidentifiableError): bad input, exit 2, one line naming the table, nothing written."""
    rows = _csv_rows(data / "static.csv")
    col = rows[0].index("marker")
    first_pose = rows[1][0]
    one = tmp_path / "one_marker.csv"
    _write_rows(one, [rows[0]] + [r for r in rows[1:] if r[0] == first_pose and r[col] == rows[1][col]])
    argv = [command, "--robot", data / "robot.toml", "--static", one]
    if command == "identify":
        argv += ["--out", tmp_path / "cal.json"]
    rc, out, err = run_cli(capsys, argv)
    assert_refused(rc, err, f"elastocal {command}: {one}: 3 deflection components cannot determine the model's 6 "
                            "parameters")
    assert out == "" and not (tmp_path / "cal.json").exists()
