"""Run data get a noise floor, the stepwise verdict rule, and stand on their own.

The simulated runs (sims/runs.py) add white current noise to noise-free currents;
these tests simulate each cell once without noise and draw the noise per seed with
the same model (N(0, 0.02 A) per reading), so that 20 seeds cost one simulation.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.diagnose.runs import diagnose_runs
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.runmodel import REFERENCE_STIFFNESS, current_noise
from elastocal.identify.runs import identify_runs
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import FrictionPlan, SweepPlan, described_robot, hide_in_runs, simulate_runs

ROBOT = bundled_robot()
NOISE_A = CellTruth().current_noise_a
TRUE_C = np.array(CellTruth().compensator)
FRICTION_MODEL = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
SEEDS = range(20)
#: smaller plans than the defaults (the same physics), so that a clean table takes seconds
FRICTION_PLAN = FrictionPlan(samples=120)
SWEEP_PLAN = SweepPlan(step_rad=0.02)


def _clean(hidden: str, *, sweeps=SWEEP_PLAN, friction=FRICTION_PLAN):
    truth = replace(hide_in_runs(CellTruth(), hidden), current_noise_a=0.0)
    return simulate_runs(ROBOT, truth, seed=0, sweeps=sweeps, friction=friction)


def _noisy(table, seed: int, sigma_a: float = NOISE_A):
    rng = np.random.default_rng([18, 7, seed])
    return replace(table, currents=table.currents + rng.normal(0.0, sigma_a, size=table.currents.shape))


@pytest.fixture(scope="module")
def complete_friction():
    return _clean("friction")


@pytest.fixture(scope="module")
def sweeps_only():
    return _clean("none", friction=None)


# ------------------------------------------------------------------ the floor
def test_current_noise_from_second_differences(complete_friction):
    est = np.array([current_noise(_noisy(complete_friction, s)) for s in range(5)]) / NOISE_A
    # 1424 readings per joint: the estimate's own scatter is about 2.6 % (correlated differences)
    assert np.all(np.abs(est - 1.0) < 0.11), est
    assert abs(est.mean() - 1.0) < 0.02
    # a drive filter that averages two successive readings: the lag-3 differences see it
    rng = np.random.default_rng(3)
    e = rng.normal(0.0, NOISE_A, size=(len(complete_friction) + 1, 6))
    filtered = replace(complete_friction, currents=complete_friction.currents + (e[1:] + e[:-1]) / np.sqrt(2))
    assert np.all(np.abs(current_noise(filtered) / NOISE_A - 1.0) < 0.1)


@pytest.mark.parametrize("stiffness", ["static fit", "rigid"])
def test_complete_runs_sit_at_the_floor_and_name_nothing(complete_friction, stiffness):
    """Acceptance: complete runs rms/floor within 1 +- 0.1; verdict null in >= 19 of 20 seeds."""
    k = CellTruth().stiffness if stiffness == "static fit" else None
    ratios, verdicts, unexplained = [], [], []
    for seed in SEEDS:
        diag = diagnose_runs(ROBOT, _noisy(complete_friction, seed), model=FRICTION_MODEL, stiffness=k)
        assert diag.stiffness.source == stiffness
        ratios.append(diag.residual_rms / diag.noise_floor)
        verdicts.append(diag.verdict)
        unexplained.append(diag.unexplained_detail is not None)
    ratios = np.array(ratios)
    assert np.all(np.abs(ratios - 1.0) < 0.1), ratios
    assert abs(np.median(ratios) - 1.0) < 0.03
    assert sum(v is None for v in verdicts) >= 19, verdicts
    assert sum(unexplained) <= 1


def test_frictionless_cell_and_the_default_model_name_nothing():
    """A cell without friction and the default model (the description's compensator and masses):
    complete too: null verdict in >= 19 of 20 seeds, rms/floor within 1 +- 0.1."""
    clean = _clean("none")
    ratios, verdicts = [], []
    for seed in SEEDS:
        diag = diagnose_runs(ROBOT, _noisy(clean, seed), stiffness=CellTruth().stiffness)
        ratios.append(diag.residual_rms / diag.noise_floor)
        verdicts.append(diag.verdict)
    assert np.all(np.abs(np.array(ratios) - 1.0) < 0.1), ratios
    assert sum(v is None for v in verdicts) >= 19, verdicts


def test_default_model_finds_the_three_friction_terms_stepwise(complete_friction):
    diag = diagnose_runs(ROBOT, _noisy(complete_friction, 1), stiffness=CellTruth().stiffness)
    assert diag.verdict == "coulomb_friction"
    assert {s.effect for s in diag.steps} == set(FRICTION_MODEL)
    assert diag.final.rms < 1.1 * diag.final.noise_floor
    obj = diag.to_json()
    json.dumps(obj)
    assert obj["noise_floor"] > 0 and obj["unexplained"] is None
    assert [s["effect"] for s in obj["steps"]] == [s.effect for s in diag.steps]
    assert obj["final"]["model"][:1] == ["joint_stiffness"] and set(FRICTION_MODEL) <= set(obj["final"]["model"])
    assert obj["final"]["residual"]["rms"] == pytest.approx(diag.final.rms)


def _ripple_friction(table, amplitude_nm: float = 25.0, periods: float = 3.0):
    """Friction that follows each joint's angle (a gear ripple), outside every named law:
    ``sign(dq_j) a (1 + cos(periods q_j))``; no column of the named effects (constant,
    speed, load torque) follows the angle."""
    xi = ROBOT.torque_constants
    friction = np.sign(table.dq) * amplitude_nm * (1.0 + np.cos(periods * table.q))
    return replace(table, currents=table.currents - friction / xi)


def test_a_friction_law_outside_the_named_effects_ends_unexplained(complete_friction):
    """Acceptance: a friction law no named effect can express ends with unexplained, verdict null."""
    base = _ripple_friction(complete_friction)
    outcomes = []
    for seed in range(10):
        diag = diagnose_runs(ROBOT, _noisy(base, seed), model=FRICTION_MODEL, stiffness=CellTruth().stiffness)
        outcomes.append((diag.verdict, diag.unexplained_detail is not None))
        if seed == 0:
            assert diag.unexplained_detail.ratio > 1.3
            assert diag.unexplained[0].startswith("friction residual above its noise on joints")
            assert any("follows the angle of joint" in u for u in diag.unexplained)
            obj = diag.to_json()
            assert obj["verdict"] is None and obj["unexplained"]["unit"] == "N*m"
            assert obj["unexplained"]["follows"]
            from elastocal.report.html import render_report

            html = render_report(ROBOT, None, diag)
            assert "above the noise floor, and no candidate effect explains all of it" in html
            assert "no missing effect found" not in html
    assert sum(v is None and u for v, u in outcomes) >= 9, outcomes


# ------------------------------------------------------------------ runs on their own
@pytest.fixture(scope="module")
def hidden_compensator():
    """Sweeps and UV/VU runs of a cell whose robot.toml gives no compensator values."""
    return _clean("compensator"), described_robot(ROBOT, "compensator")


@pytest.mark.parametrize("nominal_stiffness", [None, 1.2])
def test_compensator_from_sweeps_alone_within_2_percent(hidden_compensator, nominal_stiffness):
    """Acceptance: C and l_c within 2 % from runs alone; diagnose names the compensator.
    robot.toml without a joint stiffness (rigid, bias stated), or with a catalogue value 20 % off."""
    clean, robot = hidden_compensator
    if nominal_stiffness is not None:
        k = CellTruth().stiffness * nominal_stiffness
        robot = replace(robot, joints=tuple(replace(j, stiffness=float(kj)) for j, kj in zip(robot.joints, k)))
    errors = []
    for seed in range(5):
        table = _noisy(clean, seed)
        fit = identify_runs(robot, table, model=("compensator",))
        values = {p.name: p for p in fit.parameters}
        got = np.array([values["C"].value, values["l_c"].value])
        errors.append(got / TRUE_C - 1.0)
        assert fit.stiffness.source == ("rigid" if nominal_stiffness is None else "robot.toml")
        assert fit.rms < 1.2 * fit.noise_floor
        diag = diagnose_runs(robot, table)
        assert diag.verdict == "compensator" and diag.steps[0].effect == "compensator"
        assert diag.unexplained_detail is None
    errors = np.array(errors)
    assert np.all(np.abs(errors) < 0.02), errors
    assert np.all(np.abs(errors) < 0.005)      # and well inside: the bias of the neglected deflection is small


def test_the_rigid_bias_statement_has_the_size_of_the_bias(hidden_compensator):
    """The rigid model states its bias for a robot of REFERENCE_STIFFNESS; the real bias (rigid against
    the true stiffness) has that sign and, scaled by the compliance, that size."""
    clean, robot = hidden_compensator
    table = _noisy(clean, 0)
    rigid = identify_runs(robot, table, model=("compensator",))
    true_k = identify_runs(robot, table, model=("compensator",), stiffness=CellTruth().stiffness)
    stated = dict(rigid.stiffness.bias_parameters)
    assert set(stated) == {"C", "l_c"} and rigid.stiffness.bias_torque_rms > 0
    r, t = ({p.name: p.value for p in f.parameters} for f in (rigid, true_k))
    actual = (r["C"] - t["C"]) / t["C"]
    # HH-150's arm joints are 1.4-1.8x stiffer than the reference: the bias is smaller, same sign
    assert np.sign(actual) == np.sign(stated["C"])
    assert 0.2 < actual / stated["C"] < 1.2
    obj = rigid.to_json()
    assert obj["stiffness"]["source"] == "rigid"
    assert obj["stiffness"]["bias"]["reference_stiffness"] == REFERENCE_STIFFNESS
    assert "rigid model" in obj["stiffness"]["note"]


def test_a_rigid_compensator_shift_within_its_bias_is_no_finding(sweeps_only):
    """Complete sweeps, the description's compensator right, no stiffness: the compensator the
    rigid model fits differs from nominal by its deflection bias only: never a step."""
    verdicts = []
    for seed in SEEDS:
        diag = diagnose_runs(ROBOT, _noisy(sweeps_only, seed))
        comp = next(c for c in diag.candidates if c.effect == "compensator")
        if comp.significant:
            assert "rigid model's bias" in comp.implausible
        verdicts.append(diag.verdict)
    assert sum(v is None for v in verdicts) >= 19, verdicts


def test_plus_minus_sweeps_serve_friction(sweeps_only):
    """+/- sweeps are the same path forward and backward: friction of joint 2 from sweeps alone."""
    truth = hide_in_runs(CellTruth(), "coulomb_friction")
    table = simulate_runs(ROBOT, truth, seed=4, sweeps=SWEEP_PLAN, friction=None)
    fit = identify_runs(ROBOT, table, model=("coulomb_friction", "viscous_friction", "compensator"))
    values = {p.name: p for p in fit.parameters}
    assert abs(values["fc2"].value - truth.coulomb[1]) < 4 * values["fc2"].std
    assert values["fc2"].std < 1.0
    # one speed: the viscous term of joint 2 cannot be told from Coulomb; the other joints did not move
    assert "fv2" in fit.unidentifiable and "fc1" not in values
    np.testing.assert_allclose([values["C"].value, values["l_c"].value], TRUE_C, rtol=0.02)
    assert fit.rms < 1.2 * fit.noise_floor


def test_cli_sweeps_alone_name_the_compensator(tmp_path, capsys):
    out = tmp_path / "c"
    assert main(["sim", "runs", "--hidden", "compensator", "--seed", "5", "--out", str(out)]) == 0
    assert "l_c" not in (out / "robot.toml").read_text()
    capsys.readouterr()
    args = ["--robot", str(out / "robot.toml"), "--runs", str(out / "runs.csv")]
    assert main(["diagnose", *args, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["verdict"] == "compensator" and obj["noise_floor"] > 0
    assert obj["stiffness"]["source"] == "rigid" and obj["final"]["residual"]["rms"] < 1.3 * obj["noise_floor"]
    assert main(["diagnose", *args]) == 0
    text = capsys.readouterr().out
    assert "1. compensator" in text and "rigid model" in text and "add it:" in text
    assert main(["identify", *args, "--model", "coulomb_friction,viscous_friction,compensator", "--json"]) == 0
    fit = json.loads(capsys.readouterr().out)
    for name, true in zip(("C", "l_c"), TRUE_C):
        assert abs(fit["parameters"][name]["value"] / true - 1.0) < 0.02
    assert fit["noise_floor"] > 0 and fit["residual"]["rms"] < 1.3 * fit["noise_floor"]


def test_two_hidden_run_effects_are_found_in_two_steps():
    """The compensator hidden from the description and Coulomb friction from the model:
    two steps, the verdict the first, the final model at the floor."""
    clean = _clean("compensator,coulomb_friction")
    robot = described_robot(ROBOT, "compensator,coulomb_friction")
    for seed in range(3):
        diag = diagnose_runs(robot, _noisy(clean, seed))
        assert {s.effect for s in diag.steps} == {"compensator", "coulomb_friction"}
        assert diag.verdict == diag.steps[0].effect
        assert diag.final.rms < 1.1 * diag.final.noise_floor and diag.unexplained_detail is None
        comp = next(s for s in diag.steps if s.effect == "compensator").candidate
        c = {p.name: p.value for p in comp.parameters}
        np.testing.assert_allclose([c["C"], c["l_c"]], TRUE_C, rtol=0.02)


def test_the_floor_follows_other_noise_levels_and_samplings():
    """Another noise level (0.05 A, joint 4 at 0.01 A) and other runs (three speeds, 90 samples):
    the floor follows the noise, complete runs sit at it."""
    clean = _clean("friction", sweeps=SweepPlan(step_rad=0.03, q3_values=(0.0,)),
                   friction=FrictionPlan(samples=90, speeds_rad_s=(0.03, 0.08, 0.2)))
    sigma = np.array([0.05, 0.05, 0.05, 0.01, 0.05, 0.05])
    ratios = []
    for seed in range(5):
        table = _noisy(clean, seed, sigma_a=sigma)
        est = current_noise(table)
        assert np.all(np.abs(est / sigma - 1.0) < 0.15)
        diag = diagnose_runs(ROBOT, table, model=FRICTION_MODEL, stiffness=CellTruth().stiffness)
        ratios.append(diag.residual_rms / diag.noise_floor)
        assert diag.verdict is None
    assert np.all(np.abs(np.array(ratios) - 1.0) < 0.1), ratios


def test_robot_toml_nominal_stiffness_key(tmp_path):
    """[[joint]] stiffness (docs/formats.md §1, optional): parsed, checked, written back; run data
    alone then place the sweeps with it."""
    from elastocal.errors import InputError
    from elastocal.formats.robot_toml import bundled_robot_path, parse_robot

    text = bundled_robot_path().read_text()
    k = CellTruth().stiffness
    parts = text.split("[[joint]]")
    with_k = parts[0] + "".join(f"[[joint]]\nstiffness = {float(kj)!r}" + p for kj, p in zip(k, parts[1:]))
    robot = parse_robot(with_k)
    np.testing.assert_array_equal(robot.nominal_stiffness, k)
    assert parse_robot(robot.to_toml()).nominal_stiffness.tolist() == k.tolist()
    assert ROBOT.nominal_stiffness is None
    bad = with_k.replace(f"stiffness = {float(k[1])!r}", "stiffness = -1.0", 1)
    with pytest.raises(InputError) as err:
        parse_robot(bad, source="robot.toml")
    assert "joint[2].stiffness" in str(err.value) and "positive" in str(err.value)
    table = _noisy(_clean("none", friction=None), 0)
    assert diagnose_runs(robot, table).stiffness.source == "robot.toml"
