"""`elastocal check` (diagnose/check.py): an unchanged simulated cell holds, a
10 % drop of k2 or a friction change asks for recalibration; the statistics
are calibrated; the check procedure's log (VirtualCellIO) and tables given
directly both work through the CLI, with exit codes 0 / 3 / 2."""

import dataclasses
import json

import numpy as np
import pytest

from elastocal.acquisition.cellio import VirtualCellIO, VirtualTiming
from elastocal.acquisition.history import History
from elastocal.formats.plan import CheckSpec, FrictionSpec, LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_procedures
from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.formats.calibration import calibration_from_fit, write_calibration
from elastocal.diagnose.check import check_calibration, check_static
from elastocal.identify.runs import identify_runs
from elastocal.identify.static import identify_static
from elastocal.formats.tables import write_run_table, write_static_table
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, simulate_static

FRICTION = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
TRUTH = default_run_truth(CellTruth())
K2_DROP = dataclasses.replace(TRUTH, stiffness=TRUTH.stiffness * np.array([1.0, 0.9, 1.0, 1.0, 1.0, 1.0]))
FC3_UP = dataclasses.replace(TRUTH, coulomb=TRUTH.coulomb * np.array([1.0, 1.0, 1.5, 1.0, 1.0, 1.0]))
FC3_SLIGHTLY = dataclasses.replace(TRUTH, coulomb=TRUTH.coulomb * np.array([1.0, 1.0, 1.06, 1.0, 1.0, 1.0]))
CHECK_RUN = FrictionPlan(speeds_rad_s=(0.1,), loads=(("0", (0.0,) * 6),), samples=100)


@pytest.fixture(scope="module")
def calibration(robot):
    """The calibration of the unchanged cell: 12 random poses, and UV/VU runs for friction."""
    fit = identify_static(robot, simulate_static(robot, TRUTH, seed=1, plan=StaticPlan(n_poses=12, n_loads=2)))
    obj = fit.to_json()
    runs = identify_runs(robot, simulate_runs(robot, TRUTH, seed=2, sweeps=None, friction=FrictionPlan(samples=120)),
                         model=("joint_stiffness", *FRICTION))
    obj["parameters"].update(runs.to_json()["parameters"])
    obj["model"] = obj["model"] + list(FRICTION)
    return calibration_from_fit(robot.name, obj, created="2026-01-05T08:00:00Z")


def check_data(robot, truth, seed):
    static = simulate_static(robot, truth, seed=seed, plan=StaticPlan(n_poses=3, n_loads=1, repeats=3))
    runs = simulate_runs(robot, truth, seed=seed + 500, sweeps=None, friction=CHECK_RUN)
    return static, runs


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_unchanged_cell_holds_and_k2_drop_asks_for_recalibration(robot, calibration, seed):
    """Acceptance: same cell -> holds; joint 2 10 % softer -> recalibrate, naming k2."""
    static, runs = check_data(robot, TRUTH, seed)
    same = check_calibration(robot, calibration, static=static, runs=runs)
    assert same.verdict == "holds", same.reasons
    assert same.deflection.passed and same.friction.passed
    assert len(same.friction.joints) == 6
    static, runs = check_data(robot, K2_DROP, seed)
    softer = check_calibration(robot, calibration, static=static, runs=runs)
    assert softer.verdict == "recalibrate"
    assert not softer.deflection.passed and softer.friction.passed
    top = softer.deflection.changes[0]
    assert top.name == "k2" and top.relative == pytest.approx(-0.10, abs=0.025) and top.z < -5
    assert "k2" in softer.reasons[0] and "deflections differ" in softer.reasons[0]


def test_friction_change_counts_only_when_significant_and_large(robot, calibration):
    static, runs = check_data(robot, FC3_UP, 21)
    res = check_calibration(robot, calibration, static=static, runs=runs)
    assert res.verdict == "recalibrate" and res.deflection.passed
    assert [j.joint for j in res.friction.failing()] == [3]
    assert "joint 3" in res.reasons[0]
    # +6 % of Coulomb friction on joint 3: measurable, but within the 20 % tolerance
    static, runs = check_data(robot, FC3_SLIGHTLY, 22)
    res = check_calibration(robot, calibration, static=static, runs=runs)
    assert res.verdict == "holds"
    j3 = next(j for j in res.friction.joints if j.joint == 3)
    assert 0.0 < j3.relative < 0.2
    strict = check_calibration(robot, calibration, static=static, runs=runs, friction_tolerance=0.0)
    assert strict.verdict == "recalibrate" and [j.joint for j in strict.friction.failing()] == [3]


def test_deflection_statistic_is_chi_square_when_nothing_changed(robot, calibration):
    """Over 16 unchanged checks the statistic averages its degrees of freedom
    and never reaches the alarm level."""
    ratios, p_values = [], []
    for seed in range(16):
        d = check_static(robot, calibration, simulate_static(robot, TRUTH, seed=700 + seed,
                                                             plan=StaticPlan(n_poses=3, n_loads=1)))
        ratios.append(d.chi2 / d.dof)
        p_values.append(d.p_value)
    assert 0.7 < np.mean(ratios) < 1.3, ratios
    assert min(p_values) > 1e-3


def test_check_refuses_data_it_cannot_judge(robot, calibration):
    no_repeats = simulate_static(robot, TRUTH, seed=5, plan=StaticPlan(n_poses=3, n_loads=1, repeats=1))
    with pytest.raises(InputError, match="repeated readings"):
        check_calibration(robot, calibration, static=no_repeats)
    friction_only = dataclasses.replace(calibration, parameters=tuple(p for p in calibration.parameters
                                                                      if not p.name.startswith("k")))
    with pytest.raises(InputError, match="no joint stiffness"):
        check_calibration(robot, friction_only, static=simulate_static(robot, TRUTH, seed=5,
                                                                       plan=StaticPlan(n_poses=3, n_loads=1)))
    with pytest.raises(InputError, match="^alpha: "):
        check_calibration(robot, calibration, static=no_repeats, alpha=2.0)
    res = check_calibration(robot, calibration, runs=check_data(robot, TRUTH, 6)[1])
    assert res.deflection is None and res.verdict == "holds"


# ------------------------------------------------------------------ CLI
@pytest.fixture()
def cell(tmp_path, calibration):
    (tmp_path / "cell.toml").write_text('[cell]\nname = "test cell"\nrobot = "hh150"\nhistory = "history.sqlite"\n')
    write_calibration(tmp_path / "cal.json", calibration)
    return tmp_path


def test_check_command_on_tables_records_verdicts(robot, cell, capsys):
    for name, truth, seed in (("same", TRUTH, 31), ("soft", K2_DROP, 32)):
        static, runs = check_data(robot, truth, seed)
        write_static_table(cell / f"{name}.csv", static)
        write_run_table(cell / f"{name}-runs.csv", runs)
    base = ["check", "--cell", str(cell / "cell.toml")]
    # no calibration recorded yet
    assert main(base + ["--static", str(cell / "same.csv")]) == 2
    assert "history add" in capsys.readouterr().err
    assert main(["history", "add", "--cell", str(cell / "cell.toml"), "--calibration", str(cell / "cal.json")]) == 0
    capsys.readouterr()
    assert main(base + ["--static", str(cell / "same.csv"), "--runs", str(cell / "same-runs.csv"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["verdict"] == "holds" and obj["recorded"] == 1 and obj["calibration"] == 1
    assert obj["deflection"]["passed"] and obj["friction"]["passed"]
    assert main(base + ["--static", str(cell / "soft.csv"), "--runs", str(cell / "soft-runs.csv")]) == 3
    out = capsys.readouterr().out
    assert out.startswith("RECALIBRATE") and "k2" in out
    with History(cell / "history.sqlite") as h:
        checks = h.checks()
    assert [c.verdict for c in checks] == ["holds", "recalibrate"]
    assert checks[1].result["deflection"]["parameters"]["k2"]["relative"] == pytest.approx(-0.1, abs=0.025)
    # a calibration that is not in the history cannot be recorded against
    other = cell / "other.json"
    doc = json.loads((cell / "cal.json").read_text())
    doc["created"] = "2027-01-01T00:00:00Z"
    other.write_text(json.dumps(doc))
    assert main(base + ["--calibration", str(other), "--static", str(cell / "same.csv")]) == 2
    assert main(base + ["--calibration", str(other), "--static", str(cell / "same.csv"), "--no-record"]) == 0
    capsys.readouterr()



def test_check_of_a_calibration_file_finds_its_record_in_the_history(robot, cell, calibration, capsys):
    """A cal.json as identify writes it (with its absolute residual and the robot description) is
    found in the history it was recorded in: the check is recorded against it. (The history used to
    give back the calibration without those fields, so it was never found: exit 2.)"""
    import dataclasses

    from elastocal.formats.calibration import Residual

    full = dataclasses.replace(calibration, robot_description=robot.to_toml(),
                               absolute_residual=Residual(rms=2e-5, max=6e-5, n=108, noise_floor=1.9e-5))
    write_calibration(cell / "full.json", full)
    static, _ = check_data(robot, TRUTH, 33)
    write_static_table(cell / "same.csv", static)
    assert main(["history", "add", "--cell", str(cell / "cell.toml"), "--calibration", str(cell / "full.json")]) == 0
    capsys.readouterr()
    assert main(["check", "--cell", str(cell / "cell.toml"), "--calibration", str(cell / "full.json"),
                 "--static", str(cell / "same.csv"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["recorded"] == 1 and obj["calibration"] == 1
    with History(cell / "history.sqlite") as h:
        assert h.current().calibration == full and [c.calibration_id for c in h.checks()] == [1]

def _check_plan() -> str:
    poses = {"P1": (0.2, 0.3, -0.4, 0.3, 1.0, 0.2), "P2": (0.5, 0.55, -0.2, 0.6, 1.2, 0.5),
             "P3": (-0.3, 0.1, -0.6, -0.5, 0.8, -0.4)}
    friction = (FrictionSpec("F1", start=(-0.3, 0.2, -0.5, -0.3, 0.6, -0.2), end=(0.3, 0.5, -0.2, 0.3, 0.9, 0.3),
                             speeds_rad_s=(0.2,)),)
    return plan_toml(poses=poses, loads=(LoadSpec("L1", force_n=(-635.0, 635.0, -635.0)),),
                     markers=("R1", "R2", "R3"), repeats=3, reading_s=0.04, speed_rad_s=0.8,
                     settle=SettleSpec(speed_rad_s=2e-3, spread_m=60e-6, window_s=0.15, timeout_s=20.0),
                     friction=friction, check=CheckSpec(poses=("P1", "P2", "P3"), load="L1", friction="F1"))


def test_check_procedure_log_through_the_cli(robot, cell, capsys):
    """The check procedure (acquisition) recorded on the virtual cell, then
    `elastocal check --log`: unchanged holds (exit 0), k2 -10 % recalibrates (exit 3);
    the plan stored with the calibration is found again."""
    plan_text = _check_plan()
    (cell / "plan.toml").write_text(plan_text)
    assert main(["history", "add", "--cell", str(cell / "cell.toml"), "--calibration", str(cell / "cal.json"),
                 "--plan", str(cell / "plan.toml")]) == 0
    plan = parse_plan(plan_text)
    timing = VirtualTiming(drive_rate_hz=100.0, tracker_rate_hz=100.0)
    for name, truth in (("same", TRUTH), ("soft", K2_DROP)):
        io = VirtualCellIO(SimCell(robot, truth), seed=9, timing=timing)
        out = run_procedures(io, plan, cell / f"{name}.mcap", procedures=("check",))
        assert out.status == "completed"
    capsys.readouterr()
    base = ["check", "--cell", str(cell / "cell.toml"), "--json", "--log"]
    assert main(base + [str(cell / "same.mcap")]) == 0
    same = json.loads(capsys.readouterr().out)
    assert same["verdict"] == "holds" and same["friction"] is not None and same["log"].endswith("same.mcap")
    assert main(base + [str(cell / "soft.mcap")]) == 3
    soft = json.loads(capsys.readouterr().out)
    assert soft["verdict"] == "recalibrate"
    assert max(soft["deflection"]["parameters"].items(), key=lambda kv: abs(kv[1]["z"]))[0] == "k2"
    with History(cell / "history.sqlite") as h:
        assert h.current().plan == plan_text
        assert [c.log_path.endswith(".mcap") for c in h.checks()] == [True, True]
    # running the check procedure into an existing log is refused before any device is opened
    (cell / "exists.mcap").write_bytes(b"old")
    capsys.readouterr()
    assert main(["check", "--cell", str(cell / "cell.toml"), "--sim", "--yes", "--out", str(cell / "exists.mcap")]) == 2
    err = capsys.readouterr().err
    assert "exists.mcap: already exists; choose another --out, or --force to overwrite it" in err, err
    assert (cell / "exists.mcap").read_bytes() == b"old"


def test_check_command_input_errors(cell, capsys):
    base = ["check", "--cell", str(cell / "cell.toml"), "--calibration", str(cell / "cal.json"), "--no-record"]
    assert main(base) == 2                                      # no plan to run, no data
    assert "--plan" in capsys.readouterr().err
    (cell / "bad.csv").write_text("pose,load\n1,0\n")
    assert main(base + ["--static", str(cell / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and err.count("\n") == 1
    assert main(base + ["--static", str(cell / "bad.csv"), "--sim"]) == 2
    assert "not with --static" in capsys.readouterr().err


def test_yes_on_a_cell_nobody_simulates_is_refused_before_anything_is_written(cell, capsys):
    """`--yes` answers prompts only for simulated devices (`--sim`, or a cell `sim serve` wrote, whose
    load rig hangs the loads); on any other cell it is refused with one line, and the check's folder
    beside the history is not created."""
    (cell / "plan.toml").write_text(_check_plan())
    assert main(["history", "add", "--cell", str(cell / "cell.toml"), "--calibration", str(cell / "cal.json"),
                 "--plan", str(cell / "plan.toml")]) == 0
    capsys.readouterr()
    assert main(["check", "--cell", str(cell / "cell.toml"), "--yes"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--yes: --yes answers the prompts of simulated devices only" in err
    assert not (cell / "checks").exists()
    assert main(["check", "--cell", str(cell / "cell.toml"), "--yes", "--sim", "--unattended"]) == 2
    assert "give one" in capsys.readouterr().err and not (cell / "checks").exists()


def test_an_old_calibration_checks_friction_with_its_sign_turned(robot, calibration, tmp_path):
    """A calibration written under the old run model (friction of the other sign, no
    friction_sign field) reads with its friction turned, and the friction check of the
    unchanged cell holds as with the new file."""
    from elastocal.formats.calibration import read_calibration

    write_calibration(tmp_path / "new.json", calibration)
    doc = json.loads((tmp_path / "new.json").read_text(encoding="utf-8"))
    assert doc.pop("friction_sign") == "direction_of_motion"
    for name, p in doc["parameters"].items():
        if name.startswith(("fc", "fv", "fl")):
            p["value"] = -p["value"]
    (tmp_path / "old.json").write_text(json.dumps(doc), encoding="utf-8")
    old = read_calibration(tmp_path / "old.json")
    assert calibration.value("fc2") > 0 and old.value("fc2") == pytest.approx(calibration.value("fc2"))
    assert "sign converted" in old.find("fl3").note
    _, runs = check_data(robot, TRUTH, 21)
    res = check_calibration(robot, old, runs=runs)
    assert res.friction is not None and res.friction.passed and len(res.friction.joints) == 6
