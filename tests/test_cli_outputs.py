"""Output files of the commands: refused when they exist (unless --force), never
one of the inputs, checked before any work (a refused command writes nothing),
bad paths as one-line errors; notes about truncated logs; third-party log records
kept off stderr; errors naming the flag at fault."""

from __future__ import annotations

import json
import logging
import pathlib
import shutil

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.errors import DeviceError


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def _snapshot(folder: pathlib.Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> pathlib.Path:
    d = tmp_path_factory.mktemp("cli-outputs")
    assert main(["sim", "static", "--seed", "1", "--poses", "6", "--out", str(d / "s")]) == 0
    assert main(["identify", "--robot", str(d / "s" / "robot.toml"), "--static", str(d / "s" / "static.csv"),
                 "--out", str(d / "s" / "cal.json")]) == 0
    return d


@pytest.fixture
def s(data, tmp_path) -> pathlib.Path:
    """A private copy of the static dataset (robot.toml, static.csv, log.mcap, truth.json, cal.json)."""
    shutil.copytree(data / "s", tmp_path / "s")
    return tmp_path / "s"


def _identify(s: pathlib.Path, *extra: str) -> int:
    return main(["identify", "--robot", str(s / "robot.toml"), "--static", str(s / "static.csv"), *extra])


# ---------------------------------------------------------------- existing outputs and --force
def test_identify_refuses_an_existing_out_and_force_overwrites(s, capsys):
    before = _snapshot(s)
    (s / "cal.json").write_text("{}", encoding="utf-8")
    capsys.readouterr()
    assert _identify(s, "--out", str(s / "cal.json")) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"{s / 'cal.json'}: already exists; choose another --out, or --force to overwrite it" in err
    assert (s / "cal.json").read_text(encoding="utf-8") == "{}"
    assert _identify(s, "--out", str(s / "cal.json"), "--force") == 0
    assert json.loads((s / "cal.json").read_text(encoding="utf-8"))["robot"] == "HH-150"
    assert json.loads(_snapshot(s)["cal.json"])["parameters"] == json.loads(before["cal.json"])["parameters"]
    assert not [p for p in s.iterdir() if "partial" in p.name]


def test_an_input_is_never_an_output_even_with_force(s, capsys):
    table = (s / "static.csv").read_bytes()
    assert _identify(s, "--out", str(s / "static.csv"), "--force") == 2
    err = _one_line(capsys.readouterr().err)
    assert "static.csv: is also an input (--static)" in err
    assert (s / "static.csv").read_bytes() == table


@pytest.mark.parametrize("target", ["nodir/c.json", "DIR", "/proc/elastocal-test.json"])
def test_bad_output_paths_are_one_line_errors(s, tmp_path, capsys, target):
    out = tmp_path / "nodir" / "c.json" if target == "nodir/c.json" else (s if target == "DIR" else target)
    assert _identify(s, "--out", str(out)) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"elastocal identify: {out}: ")
    assert not (tmp_path / "nodir").exists()


def test_report_refuses_an_existing_out(s, capsys):
    page = s / "report.html"
    page.write_text("mine", encoding="utf-8")
    assert main(["report", "--robot", str(s / "robot.toml"), "--static", str(s / "static.csv"),
                 "--out", str(page)]) == 2
    assert "already exists" in _one_line(capsys.readouterr().err)
    assert page.read_text(encoding="utf-8") == "mine"


# ---------------------------------------------------------------- compensate: all or nothing
@pytest.fixture
def path_csv(s) -> pathlib.Path:
    from elastocal.compensation.files import write_path
    from elastocal.compensation.ik import yang_path
    from elastocal.formats.robot_toml import load_robot

    write_path(s / "path.csv", yang_path(load_robot(s / "robot.toml"), step_m=0.1))
    return s / "path.csv"


def _compensate(s: pathlib.Path, path_csv: pathlib.Path, *extra: str) -> int:
    return main(["compensate", "--robot", str(s / "robot.toml"), "--calibration", str(s / "cal.json"),
                 "--path", str(path_csv), "--wrench", "0,0,-1500,0,0,0", *extra])


def test_compensate_writes_nothing_when_one_output_is_bad(s, path_csv, capsys):
    before = _snapshot(s)
    assert _compensate(s, path_csv, "--out", str(s / "ok.csv"), "--krl", str(s / "nodir" / "x.src")) == 2
    err = _one_line(capsys.readouterr().err)
    assert str(s / "nodir" / "x.src") in err
    assert _snapshot(s) == before  # ok.csv was not written


def test_compensate_never_overwrites_its_path(s, path_csv, capsys):
    plan = path_csv.read_bytes()
    assert _compensate(s, path_csv, "--out", str(path_csv), "--force") == 2
    assert "is also an input (--path)" in _one_line(capsys.readouterr().err)
    assert path_csv.read_bytes() == plan


def test_compensate_refuses_existing_program_files_and_force_writes_all(s, path_csv, capsys):
    (s / "p.src").write_text("KEEP", encoding="utf-8")
    assert _compensate(s, path_csv, "--out", str(s / "o.csv"), "--krl", str(s / "p.src")) == 2
    assert "p.src: already exists" in _one_line(capsys.readouterr().err)
    assert not (s / "o.csv").exists() and (s / "p.src").read_text(encoding="utf-8") == "KEEP"
    assert _compensate(s, path_csv, "--out", str(s / "o.csv"), "--krl", str(s / "p.src"),
                       "--rapid", str(s / "p.mod"), "--force") == 0
    krl = (s / "p.src").read_text(encoding="utf-8")
    assert "DEF p(" in krl  # the program is named after the file, not after a temporary one
    assert "MODULE p" in (s / "p.mod").read_text(encoding="utf-8")
    assert not [p for p in s.iterdir() if "partial" in p.name]


# ---------------------------------------------------------------- sim
@pytest.mark.parametrize("flags", [["--hidden", "foo"], ["--poses", "0"], ["--poses", "-2"], ["--seed", "-1"],
                                   ["--repeats", "0"]])
def test_sim_validates_everything_before_writing(tmp_path, capsys, flags):
    out = tmp_path / "sx1"
    assert main(["sim", "static", *flags, "--out", str(out)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"elastocal sim: {flags[0]}: " in err
    assert not out.exists()


def test_sim_refuses_an_earlier_dataset_and_bad_folders(s, tmp_path, capsys):
    before = _snapshot(s)
    assert main(["sim", "static", "--seed", "2", "--poses", "4", "--out", str(s)]) == 2
    assert "robot.toml: already exists; choose another --out, or --force" in _one_line(capsys.readouterr().err)
    assert _snapshot(s) == before
    regular = tmp_path / "afile"
    regular.write_text("x", encoding="utf-8")
    for out in (regular, regular / "sub", pathlib.Path("/proc/elastocal-test")):
        assert main(["sim", "static", "--out", str(out)]) == 2
        assert _one_line(capsys.readouterr().err).startswith(f"elastocal sim: {out}: ")
    assert main(["sim", "static", "--seed", "2", "--poses", "4", "--out", str(s), "--force"]) == 0
    after = _snapshot(s)
    assert after["static.csv"] != before["static.csv"] and after["cal.json"] == before["cal.json"]


# ---------------------------------------------------------------- export
def test_export_refuses_then_replaces_another_logs_tables(s, tmp_path, capsys):
    from elastocal.acquisition.logwriter import write_log_from_tables
    from elastocal.formats.robot_toml import load_robot
    from elastocal.formats.tables import run_table_from_arrays

    out = tmp_path / "ex"
    assert main(["export", str(s / "log.mcap"), "--out", str(out)]) == 0
    first = _snapshot(out)
    assert set(first) == {"robot.toml", "static.csv"}
    capsys.readouterr()
    assert main(["export", str(s / "log.mcap"), "--out", str(out)]) == 2
    assert "robot.toml: already exists" in _one_line(capsys.readouterr().err)
    # a log holding runs only: the static.csv of the first log would be left beside its runs.csv
    n = 20
    q = np.tile([0.0, 0.3, -0.4, 0.0, 0.6, 0.0], (n, 1))
    q[:, 1] += np.linspace(0, 0.2, n)
    runs = run_table_from_arrays(run=["r1"] * n, direction=["+"] * n, load=["0"] * n, t=np.arange(n) * 0.1, q=q,
                                 dq=np.zeros((n, 6)) + np.eye(6)[1] * 0.2 / 1.9, currents=np.ones((n, 6)),
                                 wrench=np.zeros((n, 6)))
    runs_log = tmp_path / "runs.mcap"
    write_log_from_tables(runs_log, load_robot(s / "robot.toml"), runs=runs)
    (out / "robot.toml").unlink()
    first = _snapshot(out)
    assert main(["export", str(runs_log), "--out", str(out)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "static.csv" in err and "--force to remove it" in err
    assert _snapshot(out) == first
    assert main(["export", str(runs_log), "--out", str(out), "--force", "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["removed"] == [str(out / "static.csv")]
    assert sorted(p.name for p in out.iterdir()) == ["robot.toml", "runs.csv"]


# ---------------------------------------------------------------- truncated logs
def test_truncated_log_gets_a_note_and_json_stays_one_object(s, tmp_path, capsys):
    log = (s / "log.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log[: len(log) * 2 // 3])
    assert main(["identify", str(cut), "--json"]) == 0
    out, err = capsys.readouterr()
    json.loads(out)
    assert out.count("\n") == 1
    assert _one_line(err).startswith(f"note: {cut} ends without its MCAP summary")
    assert main(["identify", str(s / "log.mcap"), "--json"]) == 0
    assert capsys.readouterr().err == ""
    early = tmp_path / "early.mcap"
    early.write_bytes(log[:3000])
    for command in ("diagnose", "identify"):
        assert main([command, str(early)]) == 2
        err = _one_line(capsys.readouterr().err)
        assert err.startswith(f"elastocal {command}: {early}: ") and "--static" not in err


# ---------------------------------------------------------------- flags named right
def test_errors_name_the_flag_at_fault(s, tmp_path, capsys):
    assert main(["report", "--robot", str(s / "robot.toml"), "--static", str(s / "static.csv"),
                 "--out", str(tmp_path / "r.html"), "--add", "foo"]) == 2
    assert _one_line(capsys.readouterr().err).startswith("elastocal report: --add: unknown effect 'foo'")
    plan = ["plan", "--robot", str(s / "robot.toml"), "--test-pose", "0,0.3,0.2,0,0.5,0", "--load", "0,0,-1000",
            "--out", str(tmp_path / "px.toml"), "--candidates", "50"]
    assert main([*plan, "--f-max=-5"]) == 2
    assert _one_line(capsys.readouterr().err) == "elastocal plan: --f-max: must be > 0, got -5.0\n"
    assert main([*plan, "--friction-path=0,0,0,0,0,0;0,9,0,0,0,0"]) == 2
    assert _one_line(capsys.readouterr().err).startswith("elastocal plan: --friction-path: V: q2 = 9.0 rad")
    assert not (tmp_path / "px.toml").exists()


def test_geometry_names_the_joint_that_did_not_move(tmp_path, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("_geometry_tests", pathlib.Path(__file__).with_name("test_geometry.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    klimchik_run_table = module.klimchik_run_table
    runs = klimchik_run_table(tmp_path / "sweep.csv")
    assert main(["geometry", "--runs", str(runs), "--pivot", "P1", "--cylinder", "P01,P02", "--joint", "3"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("elastocal geometry: --joint: q3 takes 1 distinct value")


# ---------------------------------------------------------------- history and schedule
def test_history_add_refuses_another_robots_calibration(s, tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nname = "line"\nrobot = "hh150"\nhistory = "history.sqlite"\n', encoding="utf-8")
    doc = json.loads((s / "cal.json").read_text(encoding="utf-8"))
    doc["robot"] = "KR-270"
    other = tmp_path / "other.json"
    other.write_text(json.dumps(doc), encoding="utf-8")
    assert main(["history", "add", "--cell", str(cell), "--calibration", str(other)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"elastocal history: {other}: the calibration is for 'KR-270'")
    assert not (tmp_path / "history.sqlite").exists()
    assert main(["history", "add", "--cell", str(cell), "--calibration", str(s / "cal.json")]) == 0


def test_schedule_checks_the_check_arguments(tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nname = "line"\nrobot = "hh150"\nhistory = "history.sqlite"\n', encoding="utf-8")
    base = ["schedule", "install", "--every", "1d", "--cell", str(cell), "--crontab"]
    assert main([*base, "--check-args=--bogus"]) == 2
    assert _one_line(capsys.readouterr().err).startswith("elastocal schedule: --check-args: ")
    assert main([*base, "--check-args=--alpha x"]) == 2
    assert "--alpha" in _one_line(capsys.readouterr().err)
    assert main([*base, "--check-args=--sim --yes"]) == 0
    capsys.readouterr()
    bare = tmp_path / "bare.toml"
    bare.write_text('[cell]\nname = "line"\nrobot = "hh150"\n', encoding="utf-8")
    base[5] = str(bare)
    assert main(base) == 2
    assert "no --calibration" in _one_line(capsys.readouterr().err)
    missing = tmp_path / "cal.json"
    assert main([*base, f"--check-args=--calibration {missing}"]) == 2    # read at install, not at the first run
    assert _one_line(capsys.readouterr().err).startswith(f"elastocal schedule: {missing}: cannot read")
    golden = json.loads((pathlib.Path(__file__).parent / "data" / "golden" / "calibration_static.json").read_text())
    missing.write_text(json.dumps(golden["json"]), encoding="utf-8")       # a calibration file of the golden run
    assert main([*base, f"--check-args=--calibration {missing}"]) == 0


# ---------------------------------------------------------------- cli.main last resorts
def test_library_log_records_stay_off_stderr(monkeypatch, capsys, caplog):
    import elastocal.commands.identify as identify

    def run(args):
        logging.getLogger("pymodbus.logging").error("Connection to (127.0.0.1, 1) failed")
        logging.getLogger("canopen.sdo.client").warning("Transfer aborted by client with code 0x05040000")
        logging.getLogger("can").error("bus down")
        raise DeviceError("drive J1: no reply")

    monkeypatch.setattr(identify, "run", run)
    level = logging.getLogger("pymodbus").level
    caplog.clear()
    assert main(["identify", "x.mcap"]) == 1
    assert _one_line(capsys.readouterr().err) == "elastocal identify: DeviceError: drive J1: no reply\n"
    assert caplog.records == []  # no record was made, so none could reach stderr
    assert logging.getLogger("pymodbus").level == level
    logging.getLogger("can").error("after the command")  # restored: records are made again
    assert [r.getMessage() for r in caplog.records] == ["after the command"]


def test_an_unexpected_os_error_is_one_line_naming_the_file(monkeypatch, capsys):
    import elastocal.commands.identify as identify

    def run(args):
        open("/nonexistent-folder/elastocal.json", "w")

    monkeypatch.setattr(identify, "run", run)
    assert main(["identify", "x.mcap"]) == 2
    assert _one_line(capsys.readouterr().err) == \
        "elastocal identify: /nonexistent-folder/elastocal.json: No such file or directory\n"
