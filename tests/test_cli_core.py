"""The command line of the core: sim static, identify (docs/cli.md contract)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from elastocal.cli import main


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert main(["sim", "static", "--hidden", "none", "--seed", "21", "--out", str(out)]) == 0
    return out


def test_sim_static_writes_robot_table_and_truth(dataset):
    truth = json.loads((dataset / "truth.json").read_text())
    assert truth["hidden"] == "none" and truth["seed"] == 21
    assert truth["parameters"]["k1"] == {"value": 559000.0, "unit": "N*m/rad"}
    assert truth["parameters"]["C"]["value"] == 4771.4
    header = (dataset / "static.csv").read_text().splitlines()[0].split(",")
    assert header == ("pose,load,t,q1,q2,q3,q4,q5,q6,fx,fy,fz,mx,my,mz,i1,i2,i3,i4,i5,i6,marker,x,y,z").split(",")
    assert (dataset / "robot.toml").read_text().startswith('name = "HH-150"')


def test_identify_json_is_exactly_one_object(dataset, capsys):
    rc = main(["identify", "--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv"),
               "--json"])
    assert rc == 0
    out = capsys.readouterr().out
    obj = json.loads(out)  # exactly one JSON object, nothing else
    assert obj["model"] == ["joint_stiffness"] and obj["torque"] == "current"
    assert set(obj["parameters"]) == {f"k{j}" for j in range(1, 7)}
    assert obj["parameters"]["k2"]["unit"] == "N*m/rad"
    assert obj["residual"]["unit"] == "m" and obj["residual"]["n"] == 324
    assert obj["residual"]["rms"] <= 1.15 * obj["noise_floor"]
    truth = json.loads((dataset / "truth.json").read_text())["parameters"]
    for j in range(1, 4):
        assert obj["parameters"][f"k{j}"]["value"] == pytest.approx(truth[f"k{j}"]["value"], rel=0.02)


def test_identify_out_writes_calibration(dataset, tmp_path, capsys):
    cal = tmp_path / "cal.json"
    rc = main(["identify", "--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv"),
               "--torque", "force", "--form", "first-order", "--out", str(cal)])
    assert rc == 0
    doc = json.loads(cal.read_text())
    assert doc["format"] == "elastocal.calibration/1"
    assert doc["robot"] == "HH-150" and doc["torque"] == "force"
    assert doc["created"].endswith("Z")
    assert doc["data"][0]["path"].endswith("static.csv") and len(doc["data"][0]["sha256"]) == 64
    assert {"rms", "max", "n"} <= set(doc["residual"]) <= {"rms", "max", "n", "noise_floor"}
    assert doc["residual"]["noise_floor"] > 0
    assert "k6" in doc["parameters"]
    assert "residual" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["identify", "--static", "x.csv"], "--robot: missing --robot"),
    (["identify", "--robot", "{d}/robot.toml", "--static", "{d}/missing.csv"], "missing.csv: cannot read"),
    (["identify", "--robot", "{d}/robot.toml", "--static", "{d}/static.csv", "--model", "joint_stiffness,gearbox"],
     "--model: unknown effect 'gearbox'"),
    (["identify", "--robot", "{d}/robot.toml", "--static", "{d}/static.csv", "--model", "viscous_friction"],
     "--model: viscous_friction: friction acts during motion"),
    (["sim", "static", "--hidden", "gremlins", "--out", "{d}/x"], "--hidden: the simulator cannot hide 'gremlins'"),
])
def test_bad_input_is_one_line_and_exit_2(dataset, capsys, argv, message):
    argv = [a.replace("{d}", str(dataset)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and "Traceback" not in err


def test_usage_error_exits_2(capsys):
    assert_exit = None
    try:
        main(["identify", "--torque", "magic"])
    except SystemExit as exc:
        assert_exit = exc.code
    assert assert_exit == 2
    assert "invalid choice" in capsys.readouterr().err


def test_python_dash_m_runs(dataset):
    proc = subprocess.run([sys.executable, "-m", "elastocal", "identify", "--robot", str(dataset / "robot.toml"),
                           "--static", str(dataset / "static.csv"), "--json"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert np.isfinite(json.loads(proc.stdout)["parameters"]["k1"]["value"])


def test_identify_from_runs_gives_compensator_and_friction(tmp_path, capsys):
    out = tmp_path / "runs"
    assert main(["sim", "runs", "--hidden", "friction", "--seed", "3", "--out", str(out)]) == 0
    capsys.readouterr()
    rc = main(["identify", "--robot", str(out / "robot.toml"), "--runs", str(out / "runs.csv"), "--json",
               "--model", "compensator,coulomb_friction,viscous_friction,load_dependent_friction"])
    assert rc == 0
    obj = json.loads(capsys.readouterr().out)
    truth = json.loads((out / "truth.json").read_text())["parameters"]
    assert obj["residual"]["unit"] == "N*m"
    for name in ("C", "l_c", "fc2", "fv2"):
        assert obj["parameters"][name]["value"] == pytest.approx(truth[name]["value"], rel=0.05), name
    # friction from runs alone without naming a run effect is refused with the reason
    assert main(["identify", "--robot", str(out / "robot.toml"), "--runs", str(out / "runs.csv")]) == 2
    assert "run data alone do not give the joint stiffness" in capsys.readouterr().err


def test_identify_static_and_runs_together(dataset, tmp_path, capsys):
    out = tmp_path / "runs"
    assert main(["sim", "runs", "--hidden", "friction", "--seed", "4", "--out", str(out)]) == 0
    capsys.readouterr()
    rc = main(["identify", "--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv"),
               "--runs", str(out / "runs.csv"), "--json", "--model",
               "joint_stiffness,coulomb_friction,viscous_friction,load_dependent_friction"])
    assert rc == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["residual"]["unit"] == "m" and obj["torque_residual"]["unit"] == "N*m"
    assert {"k1", "fc1", "fv6", "fl3"} <= set(obj["parameters"])
    assert obj["model"][0] == "joint_stiffness" and "viscous_friction" in obj["model"]


def test_a_closed_output_pipe_is_no_traceback(tmp_path):
    """`elastocal … | head`: the reader goes away before the output is written."""
    import subprocess
    import sys

    assert main(["sim", "static", "--seed", "1", "--poses", "4", "--out", str(tmp_path)]) == 0
    read_end, write_end = os.pipe()
    os.close(read_end)                      # no reader at all: the first write fails with EPIPE
    try:
        proc = subprocess.run([sys.executable, "-m", "elastocal", "identify", "--robot", str(tmp_path / "robot.toml"),
                               "--static", str(tmp_path / "static.csv"), "--json"],
                              stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert proc.returncode == 1
    assert proc.stderr == ""


def test_streaming_commands_shorten_the_switch_interval_and_restore_it(monkeypatch):
    import elastocal.commands.devices as devices
    from elastocal.cli import STREAMING_SWITCH_INTERVAL_S

    seen = []
    monkeypatch.setattr(devices, "run", lambda args: seen.append(sys.getswitchinterval()) or 0)
    before = sys.getswitchinterval()
    assert main(["devices", "--cell", "x.toml"]) == 0
    assert seen == [pytest.approx(min(before, STREAMING_SWITCH_INTERVAL_S), rel=1e-6)]
    assert sys.getswitchinterval() == before
