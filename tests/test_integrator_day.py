"""Where elastocal's results leave it (the integrator's first day): each output stays
right in another tool's, a timer's or a colleague's hands. Small simulated data, seeded."""

import json

import pytest

from elastocal.cli import main


@pytest.fixture(scope="module")
def absolute_calibration(tmp_path_factory):
    """A geometry calibration of the simulated cell (seed 2) and a second day's table (seed 3)."""
    root = tmp_path_factory.mktemp("abs")
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "2", "--out", str(root / "a")]) == 0
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "3", "--out", str(root / "b")]) == 0
    assert main(["identify", "--robot", str(root / "a" / "robot.toml"), "--static", str(root / "a" / "static.csv"),
                 "--model", "joint_stiffness,kinematic_errors,tracker_frame", "--out", str(root / "cal.json")]) == 0
    return root


def test_validate_says_the_fit_data_when_the_hashes_match_and_reads_the_robot_from_the_calibration(
        absolute_calibration, capsys):
    root = absolute_calibration
    capsys.readouterr()
    cal = str(root / "cal.json")
    # no --robot: the calibration carries its description
    assert main(["validate", "--calibration", cal, "--static", str(root / "a" / "static.csv")]) == 0
    out = capsys.readouterr().out
    assert "poses of the fit data" in out and "not used in the fit" not in out
    assert main(["validate", "--calibration", cal, "--static", str(root / "a" / "static.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fit_data"] is True
    # another day's table: a validation
    other = str(root / "b" / "static.csv")
    assert main(["validate", "--calibration", cal, "--static", other]) == 0
    out = capsys.readouterr().out
    assert "poses not used in the fit" in out and "fit data" not in out
    assert main(["validate", "--robot", str(root / "a" / "robot.toml"), "--calibration", cal, "--static", other,
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fit_data"] is False


def test_one_word_per_idea_wrench_loads_flags_and_docs_pages(tmp_path, capsys):
    """`--wrench FX,FY,FZ[,MX,MY,MZ]` everywhere, one default of --loads-per-pose, report/view
    take the tracker prior and --exclude-outliers as diagnose does, every --help names a docs page."""
    import pathlib

    import numpy as np

    from elastocal.cli import COMMAND_DOCS, COMMANDS, build_parser
    from elastocal.commands import compensate
    from elastocal.errors import InputError

    np.testing.assert_array_equal(compensate._parse_wrench("0,0,1500"), [0, 0, 1500, 0, 0, 0])
    np.testing.assert_array_equal(compensate._parse_wrench("1,2,3,4,5,6"), [1, 2, 3, 4, 5, 6])
    with pytest.raises(InputError, match="3 or 6"):
        compensate._parse_wrench("1,2,3,4")
    plan_args = build_parser("plan")[0].parse_args(["plan", "--test-pose", "0,0,0,0,0,0", "--out", "p.toml"])
    sim_args = build_parser("sim")[0].parse_args(["sim", "static", "--out", "d"])
    assert plan_args.loads_per_pose in (None, sim_args.loads)       # None: resolved to the shared default
    from elastocal.commands._flags import DEFAULT_LOADS_PER_POSE
    assert sim_args.loads == DEFAULT_LOADS_PER_POSE
    for name in ("report", "view", "diagnose"):
        parser = build_parser(name)[0]
        args = parser.parse_args([name, "--robot", "r", "--static", "s", "--cell", "c.toml", "--tracker-position",
                                  "1,2,3", "--exclude-outliers"] + (["--out", "o.html"] if name == "report" else []))
        assert args.cell == "c.toml" and args.tracker_position == "1,2,3" and args.exclude_outliers
    root = pathlib.Path(__file__).parents[1]
    for name in COMMANDS:
        first = COMMAND_DOCS.get(name, "").split()[0] if COMMAND_DOCS.get(name) else ""
        assert first.startswith("docs/") and (root / first).is_file(), (name, COMMAND_DOCS.get(name))


def test_compensate_takes_a_three_number_wrench(tmp_path, capsys):
    """The README's `--wrench 0,0,1500` is accepted by compensate and means the 6-number one with no moment."""
    assert main(["sim", "static", "--seed", "0", "--poses", "4", "--loads-per-pose", "1", "--repeats", "1",
                 "--out", str(tmp_path / "s")]) == 0
    assert main(["identify", "--robot", str(tmp_path / "s" / "robot.toml"), "--static",
                 str(tmp_path / "s" / "static.csv"), "--out", str(tmp_path / "cal.json")]) == 0
    assert main(["sim", "path", "--out", str(tmp_path / "p"), "--step", "0.1"]) == 0
    import csv

    rows = list(csv.reader(open(tmp_path / "p" / "path.csv")))
    keep = [rows[0].index(c) for c in ("t", "q1", "q2", "q3", "q4", "q5", "q6")]
    with open(tmp_path / "plain.csv", "w", newline="") as f:
        csv.writer(f).writerows([[r[k] for k in keep] for r in rows])
    base = ["compensate", "--robot", str(tmp_path / "s" / "robot.toml"), "--calibration", str(tmp_path / "cal.json"),
            "--path", str(tmp_path / "plain.csv"), "--json"]
    capsys.readouterr()
    assert main([*base, "--wrench", "0,0,1500", "--out", str(tmp_path / "a.csv")]) == 0
    three = json.loads(capsys.readouterr().out)
    assert main([*base, "--wrench", "0,0,1500,0,0,0", "--out", str(tmp_path / "b.csv")]) == 0
    six = json.loads(capsys.readouterr().out)
    assert three["deflection"] == six["deflection"] and three["deflection"]["max"] > 1e-4
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()


def _plan(friction: bool) -> str:
    from elastocal.formats.plan import CheckSpec, FrictionSpec, LoadSpec, SettleSpec, plan_toml

    poses = {"P1": (0.2, 0.3, -0.4, 0.3, 1.0, 0.2), "P2": (0.5, 0.55, -0.2, 0.6, 1.2, 0.5)}
    f = (FrictionSpec("F1", start=(-0.3, 0.2, -0.5, -0.3, 0.6, -0.2), end=(0.3, 0.5, -0.2, 0.3, 0.9, 0.3),
                      speeds_rad_s=(0.2,)),) if friction else ()
    return plan_toml(poses=poses, loads=(LoadSpec("L1", force_n=(-635.0, 635.0, -635.0)),),
                     markers=("R1", "R2", "R3"), repeats=3, reading_s=0.04, speed_rad_s=0.8,
                     settle=SettleSpec(speed_rad_s=2e-3, spread_m=60e-6, window_s=0.15, timeout_s=20.0),
                     friction=f, check=CheckSpec(poses=("P1", "P2"), load="L1", friction="F1" if friction else None))


def _calibration(path, friction: bool) -> None:
    from elastocal.formats.calibration import calibration_from_fit, write_calibration

    params = {f"k{j}": {"value": 5e5, "std": 1e3, "unit": "N*m/rad"} for j in range(1, 7)}
    if friction:
        params.update({f"fc{j}": {"value": 20.0, "std": 1.0, "unit": "N*m"} for j in range(1, 7)})
    fit = {"model": ["joint_stiffness"] + (["coulomb_friction"] if friction else []), "torque": "current",
           "parameters": params, "residual": {"rms": 1e-5, "max": 3e-5, "n": 100}}
    write_calibration(path, calibration_from_fit("HH-150", fit))


def test_schedule_refuses_a_check_that_cannot_run_unattended_and_links_units_outside_systemd(tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text('[cell]\nname = "line 3"\nrobot = "hh150"\n')
    for friction in (False, True):
        (tmp_path / f"plan{friction}.toml").write_text(_plan(friction))
        _calibration(tmp_path / f"cal{friction}.json", friction)
    units = tmp_path / "units"
    base = ["schedule", "install", "--every", "7d", "--cell", str(cell), "--unit-dir", str(units)]
    capsys.readouterr()
    # loads only (the README's plan before): every step hangs a load, a timer has nobody to do it
    args = f"--calibration {tmp_path / 'calFalse.json'} --plan {tmp_path / 'planFalse.toml'}"
    assert main([*base, f"--check-args={args}"]) == 2
    err = capsys.readouterr().err
    assert "would exit 2 every time" in err and err.count("\n") == 1 and not units.exists()
    # a friction path but no friction in the calibration: nothing to compare the run with
    args = f"--calibration {tmp_path / 'calFalse.json'} --plan {tmp_path / 'planTrue.toml'}"
    assert main([*base, f"--check-args={args}"]) == 2
    assert "no friction" in capsys.readouterr().err and not units.exists()
    # the friction run of an unloaded cell checks a friction calibration: installed
    args = f"--calibration {tmp_path / 'calTrue.json'} --plan {tmp_path / 'planTrue.toml'}"
    assert main([*base, f"--check-args={args}", "--json"]) == 0
    enable = json.loads(capsys.readouterr().out)["enable"]
    # units/ is not on systemd's search path: linked by absolute path, not `enable NAME.timer`
    assert enable == [f"systemctl --user link {units.resolve() / 'elastocal-check.service'}",
                      f"systemctl --user enable --now {units.resolve() / 'elastocal-check.timer'}"]
    assert sorted(p.name for p in units.iterdir()) == ["elastocal-check.service", "elastocal-check.timer"]
    # --yes on a simulated cell: the prompts answered, every step runs
    args = f"--calibration {tmp_path / 'calFalse.json'} --plan {tmp_path / 'planFalse.toml'} --sim --yes"
    assert main([*base, f"--check-args={args}", "--force"]) == 0


def test_compensate_validate_runs_on_the_calibrated_robot(absolute_calibration, tmp_path, capsys):
    """A geometry calibration's compensation checked on the robot it describes: the exact
    compensation leaves microns, not the millimetres between the calibrated and the drawing's robot."""
    root = absolute_calibration
    assert main(["sim", "path", "--out", str(tmp_path / "p"), "--step", "0.05"]) == 0
    capsys.readouterr()
    assert main(["compensate", "--robot", str(root / "a" / "robot.toml"), "--calibration", str(root / "cal.json"),
                 "--path", str(tmp_path / "p" / "path.csv"), "--out", str(tmp_path / "c.csv"), "--validate",
                 "--json"]) == 0
    v = json.loads(capsys.readouterr().out)["validation"]
    assert "kinematic_errors" in v["truth"] and "joint_stiffness" in v["truth"]
    assert v["uncompensated"]["max"] > 1e-3            # the drawing's pose is millimetres away
    assert v["exact"]["max"] < 20e-6, v                # the calibrated robot, compensated exactly


def test_devices_on_a_dead_cell_names_every_device_and_says_what_it_is_doing(tmp_path, capsys):
    import dataclasses

    from elastocal.sims.serve import example_cell_config

    config = example_cell_config(can_channel="integrator-dead", seed=0)
    config = dataclasses.replace(config, drives=tuple(dataclasses.replace(d, timeout_s=0.05, retries=0)
                                                      for d in config.drives))
    (tmp_path / "cell.toml").write_text(config.to_toml())
    assert main(["devices", "--cell", str(tmp_path / "cell.toml"), "--identify-only"]) == 1
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1
    last = err[0]
    assert "8 of 8 devices could not be opened" in last
    for j in range(1, 7):
        assert f"drive J{j}" in last
    assert "tracker" in last and "controller" in last
    assert captured.out.count("FAILED") == 8        # each device, as it was tried


def test_sim_plant_reports_progress(tmp_path, capsys):
    """The plant's logs take a minute or two: a line per log on stderr as they are made; with
    --json stdout is the one object and nothing is said."""
    assert main(["sim", "plant", "--out", str(tmp_path / "p"), "--cells", "1", "--logs", "2", "--poses", "6",
                 "--drift-cell", "0"]) == 0
    err = capsys.readouterr().err.splitlines()
    lines = [line for line in err if line.startswith("sim plant: [")]
    assert [line.split()[3] for line in lines] == ["0/3", "1/3", "2/3", "3/3"], err
    assert "left" in lines[1] and "cell-01" in lines[1]
    assert main(["sim", "plant", "--out", str(tmp_path / "q"), "--cells", "1", "--logs", "2", "--poses", "6",
                 "--drift-cell", "0", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["logs"] == 2 and "sim plant: [" not in captured.err

def test_pictures_axes_labels_arrows_and_colours():
    """The report's absolute-error axis, the view's arrows, the history's colours and time axis."""
    import numpy as np
    from matplotlib.figure import Figure

    from elastocal.report.absolute import _error_axis
    from elastocal.report.drift_plot import _styles, _time_axis

    ax = Figure().subplots()
    _error_axis(ax, [np.array([8.4, 9.1, 9.8])])           # less than a decade: linear, from 0
    assert ax.get_yscale() == "linear" and ax.get_ylim()[0] == 0.0
    ax = Figure().subplots()
    _error_axis(ax, [np.array([1200.0, 800.0]), np.array([6.0, 9.0])])   # a geometry calibration
    assert ax.get_yscale() == "log" and ax.get_ylim() == (1.0, 10000.0)
    ticks = [t for t in ax.get_yticks() if 1.0 <= t <= 1e4]
    assert ticks == [1.0, 10.0, 100.0, 1000.0, 10000.0]
    # every series of the history's panels its own (colour, marker)
    names = [f"{k}{j}" for k in ("k", "fc", "fv", "fl", "da", "dd", "dalpha", "dq", "dbeta") for j in range(1, 7)]
    names += [f"d{a}_R{m}" for a in "xyz" for m in (1, 2, 3)]
    styles = _styles(names)
    assert len({(str(c), m) for c, m in styles}) == len(names)
    # one calibration: a week around it, not years
    ax = Figure().subplots()
    t = np.array([np.datetime64("2026-11-02T06:00", "ns")])
    _time_axis(ax, t)
    import matplotlib.dates as mdates

    lo, hi = (mdates.num2date(v) for v in ax.get_xlim())
    assert 6.9 < (hi - lo).total_seconds() / 86400 < 7.1


def test_the_report_says_which_rms_each_number_is(absolute_calibration, tmp_path, capsys, monkeypatch):
    """The headline's rms is per component (x, y, z), the per-pose plot's each marker's 3-D distance,
    √3 apart: both say so, and the plot's noise floor is drawn √3 times the headline's."""
    import re

    root = absolute_calibration
    page = tmp_path / "r.html"
    assert main(["report", "--robot", str(root / "a" / "robot.toml"), "--static", str(root / "a" / "static.csv"),
                 "--out", str(page)]) == 0
    html = page.read_text(encoding="utf-8")
    headline = re.search(r"µm rms per component \(x, y, z; the per-pose plot shows each marker's 3-D distance, "
                         r"√3 times larger\), max \d+ µm, noise floor ([\d.]+) µm", html)
    assert headline, html[:2000]
    assert "rms per marker (3-D distance) [µm]" in html and "noise floor (per marker, 3-D)" in html

    class Fit:        # what the plot reads of a fit: the per-pose rms and the floor
        noise_floor = 5e-6

        def per_pose(self):
            return [{"pose": "P1", "rms": 20e-6}, {"pose": "P2", "rms": 30e-6}]

    import numpy as np

    import elastocal.report.absolute as absolute_report

    drawn = []
    monkeypatch.setattr(absolute_report, "figure_svg", lambda fig, ident: drawn.append(fig) or "")
    absolute_report._pose_plot([("model", Fit(), "C0")], "fig-test")
    ax = drawn[0].axes[0]
    floor = [line for line in ax.lines if line.get_label() == "noise floor (per marker, 3-D)"]
    assert len(floor) == 1 and ax.get_ylabel() == "rms per marker (3-D distance) [µm]"
    assert np.allclose(floor[0].get_ydata(), 5.0 * np.sqrt(3))


def test_view_arrows_visible_with_heads_and_one_pose_first(tmp_path):
    import numpy as np

    from elastocal.commands.view import build_view
    from elastocal.report.view import ERROR_ARROW_M, arrow_heads, auto_magnify_errors, worst_pose

    assert main(["sim", "static", "--hidden", "link_compliance", "--seed", "1", "--poses", "6", "--out",
                 str(tmp_path / "d")]) == 0
    from elastocal.cli import build_parser

    args = build_parser("view")[0].parse_args(["view", "--robot", str(tmp_path / "d" / "robot.toml"), "--static",
                                               str(tmp_path / "d" / "static.csv")])
    view = build_view(args)
    e = auto_magnify_errors(view)
    longest = e * np.max(np.linalg.norm(view.models[0].residual, axis=1))
    assert 0.2 * ERROR_ARROW_M < longest <= ERROR_ARROW_M and e > 100.0   # ×100 drew them a few mm long
    assert worst_pose(view) == view.pose_ids[int(np.argmax(view.models[0].pose_rms))]
    seg = np.array([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], [[1.0, 1.0, 1.0], [1.0, 1.0, 1.2]]])
    heads = arrow_heads(seg)
    assert heads.shape == (4, 2, 3)
    for k, s in enumerate(np.concatenate([seg, seg])):
        np.testing.assert_allclose(heads[k, 0], s[1])                       # from the tip
        barb, axis = heads[k, 1] - heads[k, 0], s[1] - s[0]
        cos = -(barb @ axis) / (np.linalg.norm(barb) * np.linalg.norm(axis))
        assert abs(cos - np.cos(np.radians(30.0))) < 1e-9                  # back along the arrow, 30° off


def test_demo_lists_an_implausible_candidate_as_implausible():
    from types import SimpleNamespace

    from elastocal.commands.demo import candidate_line

    drift = SimpleNamespace(effect="thermal_drift", rms_after=22e-6, delta_bic=-40.0, significant=True,
                            evidence="a drift along time", implausible="a drift of 133 mm/h, faster than a room "
                                                                        "or a tracker warms (at most 5 mm/h)")
    line = candidate_line(3, drift, 24e-6)
    assert "implausible: a drift of 133 mm/h" in line and "ΔBIC" not in line
    plain = SimpleNamespace(**{**vars(drift), "implausible": None})
    assert "ΔBIC -40" in candidate_line(3, plain, 24e-6)


def test_device_urls_are_parsed_once_into_the_backends_frozen_parameters(monkeypatch):
    import dataclasses

    from elastocal.drivers import url_params
    from elastocal.drivers.force import NetFtParams
    from elastocal.drivers.guidance import GuidanceParams
    from elastocal.drivers.urls import DeviceUrl, parse_device_url
    from elastocal.errors import InputError

    cases = {
        "canopen://virtual/cell?node=5&bitrate=500000": url_params.CanopenParams("virtual", "cell", 5, 500_000),
        "modbus+tcp://127.0.0.1:1502?unit=3": url_params.ModbusTcpParams("127.0.0.1", 1502, 3),
        "modbus+rtu:///dev/pts/3?baud=9600&parity=e": url_params.ModbusRtuParams("/dev/pts/3", 9600, "E", 1),
        "tracker+tcp://127.0.0.1:7000": url_params.TrackerTcpParams("127.0.0.1", 7000),
        "tracker+serial:///dev/ttyUSB0": url_params.TrackerSerialParams("/dev/ttyUSB0", 115200),
        "tracker+emscon://10.0.0.2?initialize=0&reflector=RRR&reflector.R2=7":
            url_params.EmsconParams("10.0.0.2", 700, False, 120.0, "RRR", (("R2", "7"),)),
    }
    for text, expected in cases.items():
        settings = parse_device_url(text).settings
        assert settings == expected, text
        with pytest.raises(dataclasses.FrozenInstanceError):
            settings.host = "x"
    emscon = parse_device_url("tracker+emscon://h?reflector=RRR&reflector.R2=7").settings
    assert (emscon.reflector_for("R2"), emscon.reflector_for("R1")) == ("7", "RRR")
    assert isinstance(parse_device_url("rsi://0.0.0.0:59152?cycle_ms=12").settings, GuidanceParams)
    assert isinstance(parse_device_url("netft://192.168.1.1").settings, NetFtParams)
    # a changed address: the parameters follow
    assert parse_device_url("modbus+tcp://127.0.0.1:0?unit=2").with_port(1503).settings.port == 1503
    # checked once, at parse time, by the backend's class
    for bad, words in (("canopen://virtual/cell", "node id is missing"), ("tracker+tcp://127.0.0.1", "host and port"),
                       ("modbus+rtu:///dev/x?parity=Q", "parity"), ("tracker+emscon://h?initialize=2", "0 or 1"),
                       ("rsi://0.0.0.0:59152?cycle_ms=5", "cycle_ms")):
        with pytest.raises(InputError, match=words):
            parse_device_url(bad)
    # the backends parse nothing again: the URL's own readers are not called when a backend opens
    calls = []
    for name in ("param", "int_param", "float_param"):
        original = getattr(DeviceUrl, name)
        monkeypatch.setattr(DeviceUrl, name, lambda self, *a, _o=original, _n=name, **k: calls.append(_n) or _o(self, *a, **k))
    url = parse_device_url("modbus+tcp://127.0.0.1:1502?unit=3")
    calls.clear()
    from elastocal.drivers.endpoints import modbus_unit
    from elastocal.drivers.modbus_drive import link_key

    assert modbus_unit(url) == 3 and link_key(url) == ("modbus+tcp", "127.0.0.1", 1502) and calls == []


def test_a_silent_command_says_it_is_working_on_a_terminal():
    import io
    import threading

    from elastocal.commands._heartbeat import Heartbeat

    assert not Heartbeat("identify", stream=io.StringIO()).active      # not a terminal: nothing said
    assert not Heartbeat("calibrate", stream=io.StringIO(), force=False).active
    err = io.StringIO()
    spoke = threading.Event()

    class Err(io.StringIO):
        def write(self, text):
            n = err.write(text)
            spoke.set()
            return n

    with Heartbeat("identify", stream=Err(), after_s=0.01, every_s=0.05, force=True):
        assert spoke.wait(30.0)          # a silent command: the line comes (event, not a duration)
    assert err.getvalue().startswith("elastocal identify: working, ")


def test_stream_refuses_a_calibration_effect_it_does_not_model_before_starting(tmp_path, capsys):
    from elastocal.formats.calibration import calibration_from_fit, write_calibration

    params = {f"k{j}": {"value": 5e5, "std": 1e3, "unit": "N*m/rad"} for j in range(1, 7)}
    params.update({"cl2x": {"value": 2e-8, "std": 1e-9, "unit": "rad/(N*m)"}})
    fit = {"model": ["joint_stiffness", "link_compliance"], "torque": "current", "parameters": params,
           "residual": {"rms": 1e-5, "max": 3e-5, "n": 100}}
    write_calibration(tmp_path / "cal.json", calibration_from_fit("HH-150", fit))
    assert main(["sim", "path", "--out", str(tmp_path / "p"), "--step", "0.1"]) == 0
    capsys.readouterr()
    assert main(["stream", "--sim", "--yes", "--calibration", str(tmp_path / "cal.json"), "--path",
                 str(tmp_path / "p" / "path.csv"), "--out", str(tmp_path / "s.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "link_compliance (cl2x)" in err and "--without link_compliance" in err
    assert not (tmp_path / "s.mcap").exists()


def test_one_progress_line_for_every_command():
    """elastocal/progress.py: redrawn in place on a terminal, a line per unit to a file or pipe (per
    tenth when there are many), silent when quiet (--json); the procedure's bar is the same line."""
    import io

    from elastocal.acquisition.ui import progress_line as procedure_line
    from elastocal.progress import Progress, progress_line

    assert procedure_line is progress_line
    ticks = iter(range(100))
    pipe = io.StringIO()
    p = Progress("fleet identify", 40, stream=pipe, clock=lambda: float(next(ticks)))
    for done in range(41):
        p(done, f"log{done}.mcap", failed=done // 20)
    lines = pipe.getvalue().splitlines()
    assert len(lines) == 11 and lines[-1].startswith("fleet identify: [########################] 40/40")
    assert lines[-1].endswith(", 2 failed") and "0:05 elapsed, ~0:45 left" in lines[1]   # 4 of 40 in 5 s

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    tty = Terminal()
    p = Progress("sim plant", 3, stream=tty, clock=lambda: 0.0)
    p(1, "cell-01")
    p.done()
    assert tty.getvalue().count("\r\x1b[2K") == 2 and tty.getvalue().endswith("done  0:00 elapsed, ~0:00 left\n")
    quiet = io.StringIO()
    Progress("fleet check", 3, stream=quiet, quiet=True).done()
    assert quiet.getvalue() == ""
