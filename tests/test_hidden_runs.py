"""Hidden-effect suite on run data: `elastocal sim runs --hidden EFFECT` for each
friction effect the simulator can switch on; diagnose names it from the
default model, and adding it brings the torque residual down to the noise."""

import json

import pytest

from elastocal.cli import main
from elastocal.diagnose.runs import diagnose_runs
from elastocal.formats.robot_toml import bundled_robot
from elastocal.formats.tables import read_run_table
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import hide_in_runs, simulate_runs

ROBOT = bundled_robot()
#: UV/VU half-difference noise of the simulated currents (0.02 A): what a complete model leaves [N·m]
NOISE_NM = 2.45


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("effect", ["coulomb_friction", "viscous_friction", "load_dependent_friction"])
def test_hidden_friction_is_named_and_adding_it_reaches_the_noise(effect, seed):
    table = simulate_runs(ROBOT, hide_in_runs(CellTruth(), effect), seed=seed)
    diag = diagnose_runs(ROBOT, table, model=("joint_stiffness",))
    assert diag.verdict == effect
    best = diag.candidates[0]
    assert best.effect == effect and best.p_value < 0.01 and best.delta_bic < -10
    assert best.rms_after < 1.3 * NOISE_NM < best.rms_before


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_no_friction_no_verdict(seed):
    table = simulate_runs(ROBOT, hide_in_runs(CellTruth(), "none"), seed=seed)
    diag = diagnose_runs(ROBOT, table, model=("joint_stiffness",))
    assert diag.verdict is None
    assert diag.residual_rms < 1.1 * NOISE_NM


def test_sim_runs_command_writes_table_log_and_truth(tmp_path, capsys):
    out = tmp_path / "runs"
    assert main(["sim", "runs", "--hidden", "viscous_friction", "--seed", "7", "--out", str(out), "--json"]) == 0
    written = json.loads(capsys.readouterr().out)
    assert set(written) == {"robot", "runs", "log", "truth"}
    truth = json.loads((out / "truth.json").read_text())
    assert truth["hidden"] == "viscous_friction" and truth["parameters"]["fv2"]["value"] == 1100.0
    assert "fc2" not in truth["parameters"]
    table = read_run_table(out / "runs.csv", ROBOT)
    assert set(table.direction) == {"UV", "VU", "+", "-"}
    # the log reads back to the same table
    from elastocal.acquisition.export import load_log

    _, static, runs = load_log(out / "log.mcap")
    assert static is None and len(runs) == len(table)
    assert main(["diagnose", "--robot", str(out / "robot.toml"), "--runs", str(out / "runs.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["verdict"] == "viscous_friction"
    assert main(["sim", "runs", "--hidden", "link_compliance", "--out", str(out)]) == 2
    assert "cannot hide 'link_compliance' in run data" in capsys.readouterr().err
