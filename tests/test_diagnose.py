"""Diagnose: the hidden-effect suite (the verdict names what the simulator hid,
and adding it brings the residual to the noise floor), the null rate on
complete data, residual structure no candidate explains, run data, and the
``diagnose --json`` contract of docs/cli.md."""

import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.diagnose.static import diagnose_static
from elastocal.diagnose.runs import diagnose_runs
from elastocal.diagnose.verdict import VERDICT_DELTA_BIC, VERDICT_P
from elastocal.diagnose.where import where_it_fails
from elastocal.formats.robot_toml import bundled_robot, parse_robot
from elastocal.identify.static import build_dataset
from elastocal.sims.cell import HH150_STIFFNESS, HIDDEN_EFFECTS, CellTruth
from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, load_wrenches, random_poses, simulate_static
from elastocal.model.kinds import KinematicForm, TorqueSource

ROBOT = bundled_robot()
#: hidden effect -> torque source that can show it (static friction takes its
#: share before the currents are measured, so only forces show it)
TORQUE_FOR = {"link_compliance": TorqueSource.CURRENT, "thermal_drift": TorqueSource.CURRENT,
              "backlash": TorqueSource.CURRENT, "static_friction": TorqueSource.FORCE,
              "base_tilt": TorqueSource.CURRENT, "nonlinear_stiffness": TorqueSource.CURRENT}
#: the effect that names what the simulator hid (a tilting base is compliance located at the base)
NAMED = {"base_tilt": "link_compliance"}
SEEDS = (1, 2, 3, 4, 5)


#: hidden effects only absolute positions show: tests/test_absolute.py diagnoses them
ABSOLUTE_HIDDEN = {"kinematic_errors", "tracker_frame"}


def test_the_suite_covers_every_effect_the_simulator_can_hide():
    assert set(TORQUE_FOR) | ABSOLUTE_HIDDEN == set(HIDDEN_EFFECTS) - {"none"}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("hidden", sorted(TORQUE_FOR))
def test_hidden_effect_is_named_and_adding_it_reaches_the_noise_floor(hidden, seed):
    table = simulate_static(ROBOT, CellTruth().with_hidden(hidden), seed=seed)
    diag = diagnose_static(ROBOT, table, torque=TORQUE_FOR[hidden])
    named = NAMED.get(hidden, hidden)
    assert diag.verdict == named, [(c.effect, c.delta_bic, c.p_value) for c in diag.candidates]
    best = diag.candidates[0]
    assert best.effect == named and best.p_value < VERDICT_P and best.delta_bic < VERDICT_DELTA_BIC
    assert diag.steps[0].candidate is best and named in diag.final.model
    assert diag.final.rms < diag.fit.rms
    assert diag.final.rms <= 1.3 * diag.final.noise_floor       # and adding the effect fixes it
    assert diag.unexplained == ()
    if hidden in ("base_tilt", "link_compliance"):
        # a tilting base and bending links also move the absolute positions (the unloaded poses
        # under the robot's own weight): the absolute model carries the located springs, so the
        # absolute positions sit at their floor with nothing added (a play that never reverses is
        # a joint zero to them, so backlash may add kinematic_errors there)
        a = diag.absolute
        assert a.steps == () and a.base_at_floor, a.to_json()["absolute_final"]
    # candidates are ranked best first
    assert [c.delta_bic for c in diag.candidates] == sorted(c.delta_bic for c in diag.candidates)


@pytest.mark.heavy   # statistics over 20 seeds
@pytest.mark.acceptance
def test_complete_data_give_no_verdict_in_at_least_19_of_20_seeds():
    verdicts = []
    for seed in range(100, 120):
        diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth(), seed=seed))
        verdicts.append(diag.verdict)
        assert {c.effect for c in diag.candidates} == {"link_compliance", "thermal_drift", "backlash",
                                                             "nonlinear_stiffness"}
    assert sum(v is None for v in verdicts) >= 19, verdicts


def test_complete_force_based_data_give_no_verdict():
    for seed in (7, 8, 9):
        diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth(), seed=seed), torque=TorqueSource.FORCE)
        assert diag.verdict is None
        assert "static_friction" in {c.effect for c in diag.candidates}


def test_static_friction_is_invisible_to_currents_and_said_so():
    diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth().with_hidden("static_friction"), seed=4))
    assert diag.verdict is None
    assert diag.fit.rms <= 1.3 * diag.fit.noise_floor
    reasons = {n.effect: n.reason for n in diag.not_testable}
    assert "currents measure the torque the gears carry" in reasons["static_friction"]
    assert "static data hold no motion" in reasons["coulomb_friction"]


def test_an_effect_already_in_the_model_is_not_a_candidate():
    table = simulate_static(ROBOT, CellTruth().with_hidden("link_compliance"), seed=6)
    diag = diagnose_static(ROBOT, table, model=("joint_stiffness", "link_compliance"))
    assert "link_compliance" not in {c.effect for c in diag.candidates}
    assert diag.verdict is None and diag.fit.rms <= 1.3 * diag.fit.noise_floor


def test_unidentifiable_parameters_of_a_candidate_are_reported():
    diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth().with_hidden("backlash"), seed=2))
    cand = diag.candidates[0]
    assert cand.effect == "backlash" and cand.unidentifiable
    assert cand.rank == cand.n_model_parameters - len(cand.unidentifiable)
    assert cand.dof == 6 - len(cand.unidentifiable)
    assert {p.name for p in cand.parameters} | set(cand.unidentifiable) == {f"b{j}" for j in range(1, 7)}


def test_residual_structure_no_candidate_explains_is_reported():
    # the robot description puts marker R2 5 cm off: no effect of the table explains that
    text = ROBOT.to_toml().replace("R2 = [0.15, 0.0, 0.22]", "R2 = [0.15, 0.05, 0.22]")
    wrong = parse_robot(text)
    diag = diagnose_static(wrong, simulate_static(ROBOT, CellTruth(), seed=3))
    assert diag.verdict is None
    assert diag.excess_p_value < 1e-3
    assert any("marker R2" in u for u in diag.unexplained), diag.unexplained
    marker = diag.where.group("marker")
    assert marker.labels[int(np.argmax(marker.rms))] == "R2"


def test_where_it_fails_groups_by_pose_marker_load_joint_angle_and_time():
    table = simulate_static(ROBOT, CellTruth().with_hidden("link_compliance"), seed=8)
    diag = diagnose_static(ROBOT, table)
    w = diag.where
    assert {g.by for g in w.groups} == {"pose", "marker", "load", "q1", "q2", "q3", "q4", "q5", "q6",
                                        "load_size", "time"}
    for g in w.groups:
        assert g.n.sum() == diag.fit.n
        # the groups split the residual: their mean square is the total
        assert np.sum(g.rms**2 * g.n) / g.n.sum() == pytest.approx(diag.fit.rms**2)
        # per-group floors are what noise leaves: close to the fit's noise floor
        assert np.sqrt(np.sum(g.floor**2 * g.n) / g.n.sum()) == pytest.approx(diag.fit.noise_floor, rel=1e-6)
    after = diag.where_final
    assert np.all(after.group("pose").rms < w.group("pose").rms)
    assert after.group("pose").rms.max() < 1.5 * after.group("pose").floor.max()
    again = where_it_fails(ROBOT, diag.final)
    np.testing.assert_allclose(again.group("q2").rms, after.group("q2").rms)


def test_without_repeats_no_noise_floor_is_claimed_and_the_test_stays_honest():
    plan = StaticPlan(repeats=1)
    verdicts = []
    for seed in range(40, 50):
        diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth(), seed=seed, plan=plan))
        verdicts.append(diag.verdict)
        assert not diag.noise_known and diag.noise_floor is None
        obj = diag.to_json()
        assert obj["noise_floor"] is None and obj["final"]["noise_floor"] is None
        assert diag.where.noise_var is None and diag.unexplained == ()
    assert sum(v is None for v in verdicts) >= 9, verdicts
    diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth().with_hidden("link_compliance"), seed=40,
                                                  plan=plan))
    assert diag.verdict == "link_compliance"


def test_heavy_loads_show_the_complementary_stiffness_only_in_the_first_order_force_model():
    rng = np.random.default_rng(0)
    poses = random_poses(ROBOT, 12, rng)
    heavy = [2.5 * load_wrenches(3, rng) for _ in range(12)]
    table = simulate_static(ROBOT, CellTruth(), seed=0, poses=poses, wrenches=heavy)
    first = diagnose_static(ROBOT, table, torque=TorqueSource.FORCE, form=KinematicForm.FIRST_ORDER)
    assert first.verdict == "complementary_stiffness"
    cand = first.candidates[0]
    assert cand.dof == 1 and cand.parameters == () and cand.rms_after < first.fit.rms
    exact = diagnose_static(ROBOT, table, torque=TorqueSource.FORCE, form=KinematicForm.EXACT)
    assert exact.verdict is None and exact.fit.rms < cand.rms_after
    reasons = {n.effect: n.reason for n in exact.not_testable}
    assert "exact form already" in reasons["complementary_stiffness"]


def test_first_order_and_dataset_inputs_work():
    ds = build_dataset(simulate_static(ROBOT, CellTruth().with_hidden("thermal_drift"), seed=9))
    diag = diagnose_static(ROBOT, ds, form=KinematicForm.FIRST_ORDER)
    assert diag.form is KinematicForm.FIRST_ORDER and diag.verdict == "thermal_drift"


# ------------------------------------------------------------------ run data
@pytest.fixture(scope="module")
def runs_table():
    return simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=1)


def test_runs_missing_friction_is_named(runs_table):
    diag = diagnose_runs(ROBOT, runs_table, stiffness=HH150_STIFFNESS)
    assert diag.verdict == "coulomb_friction"
    c = diag.candidates[0]
    assert c.part == "uv/vu" and c.rms_after < 0.3 * c.rms_before
    fc = {p.name: p.value for p in c.parameters}
    assert set(fc) == {f"fc{j}" for j in range(1, 7)}


def test_runs_add_friction_terms_one_by_one_until_none_is_missing(runs_table):
    model = ("joint_stiffness",)
    named = []
    for _ in range(4):
        diag = diagnose_runs(ROBOT, runs_table, model=model, stiffness=HH150_STIFFNESS)
        if diag.verdict is None:
            break
        named.append(diag.verdict)
        model = (*model, diag.verdict)
    assert set(named) == {"coulomb_friction", "viscous_friction", "load_dependent_friction"}
    assert diag.verdict is None
    # the compensator and the gravity of the description are right: not significant
    assert {c.effect for c in diag.candidates} == {"compensator", "gravity"}
    assert not any(c.significant for c in diag.candidates)
    moving = np.isfinite(diag.friction.measured)
    assert diag.friction.after is None and np.all(np.isfinite(diag.friction.before[moving]))


def test_runs_refuse_what_they_cannot_show():
    one_speed = simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=2, sweeps=None,
                              friction=FrictionPlan(speeds_rad_s=(0.1,), samples=120))
    diag = diagnose_runs(ROBOT, one_speed, model=("coulomb_friction",))
    reasons = {n.effect: n.reason for n in diag.not_testable}
    assert "two or more speeds" in reasons["viscous_friction"]
    assert "no joint-2 sweep" in reasons["compensator"]
    assert "load_dependent_friction" in {c.effect for c in diag.candidates}


def test_runs_sweeps_without_a_stiffness_use_the_rigid_model_and_say_so(runs_table):
    diag = diagnose_runs(ROBOT, runs_table)
    assert {"compensator", "gravity"} <= {c.effect for c in diag.candidates}
    assert diag.stiffness.source == "rigid" and "neglected" in diag.stiffness.note
    assert diag.to_json()["stiffness"]["bias"]["torque_rms"] > 0
    with_k = diagnose_runs(ROBOT, runs_table, stiffness=HH150_STIFFNESS)
    assert with_k.stiffness.source == "static fit" and with_k.stiffness.values == tuple(HH150_STIFFNESS)


# ------------------------------------------------------------------ CLI
@pytest.fixture(scope="module")
def sim_dirs(tmp_path_factory):
    out = {}
    for hidden in ("none", "link_compliance"):
        d = tmp_path_factory.mktemp(hidden)
        assert main(["sim", "static", "--hidden", hidden, "--seed", "31", "--out", str(d)]) == 0
        out[hidden] = d
    return out


def test_diagnose_json_contract(sim_dirs, capsys):
    d = sim_dirs["link_compliance"]
    capsys.readouterr()
    rc = main(["diagnose", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"), "--json"])
    assert rc == 0
    obj = json.loads(capsys.readouterr().out)  # exactly one JSON object, nothing else
    assert obj["model"] == ["joint_stiffness"]
    assert set(obj["residual"]) == {"rms", "max", "n", "unit"} and obj["residual"]["unit"] == "m"
    assert obj["residual"]["n"] == 324 and obj["noise_floor"] > 0
    for c in obj["candidates"]:
        assert {"effect", "rms_after", "delta_bic", "p_value", "evidence"} <= set(c)
    assert [c["delta_bic"] for c in obj["candidates"]] == sorted(c["delta_bic"] for c in obj["candidates"])
    first = obj["candidates"][0]
    assert obj["verdict"] == "link_compliance" == first["effect"]
    assert first["p_value"] < 0.01 and first["delta_bic"] < -10
    assert first["rms_after"] < obj["residual"]["rms"] / 2
    assert "torsion" in first["evidence"] or "bending" in first["evidence"]


def test_diagnose_json_null_verdict_on_complete_data(sim_dirs, capsys):
    d = sim_dirs["none"]
    capsys.readouterr()
    assert main(["diagnose", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["verdict"] is None
    first = obj["candidates"][0]
    assert not (first["p_value"] < 0.01 and first["delta_bic"] < -10)


def test_diagnose_human_output(sim_dirs, capsys):
    d = sim_dirs["link_compliance"]
    capsys.readouterr()
    assert main(["diagnose", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv")]) == 0
    out = capsys.readouterr().out
    assert "the model misses something" in out
    assert "1. link_compliance" in out
    assert "add it: elastocal identify --robot" in out and "--model joint_stiffness,link_compliance" in out
    d = sim_dirs["none"]
    assert main(["diagnose", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv")]) == 0
    assert "residual at the noise floor; no missing effect found" in capsys.readouterr().out


def test_diagnose_bad_model_is_one_line_exit_2(sim_dirs, capsys):
    d = sim_dirs["none"]
    capsys.readouterr()
    rc = main(["diagnose", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
               "--model", "joint_stiffness,coulomb_friction"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "coulomb_friction" in err and "no motion" in err


def test_runs_where_it_fails_by_joint_pair_and_q2(runs_table):
    diag = diagnose_runs(ROBOT, runs_table, model=("coulomb_friction", "viscous_friction"),
                         stiffness=HH150_STIFFNESS)
    assert diag.verdict == "load_dependent_friction"
    groups = {g.by: g for g in diag.groups}
    assert set(groups) == {"joint", "uv/vu pair", "sweep q2", "sweep"}
    assert groups["joint"].labels == tuple(f"j{j}" for j in range(1, 7))
    # the four UV/VU pairs and the two +/- sweeps (the same path forward and backward too)
    assert len(groups["uv/vu pair"].labels) == 6 and all("/" in lab for lab in groups["uv/vu pair"].labels)
    assert sum(lab.startswith("sweep") for lab in groups["uv/vu pair"].labels) == 2
    # the missing load-dependent friction is worst on the pairs under load
    pair = groups["uv/vu pair"]
    assert pair.floor is not None and np.all(pair.floor > 0)
    loaded = [r for lab, r in zip(pair.labels, pair.rms) if lab.split("/")[0].endswith("-1")]
    unloaded = [r for lab, r in zip(pair.labels, pair.rms) if lab.split("/")[0].endswith("-0")]
    assert len(loaded) == len(unloaded) == 2 and min(loaded) > max(unloaded)
    obj = diag.to_json()
    assert obj["where"]["joint"]["unit"] == "N*m"
    json.dumps(obj)


@pytest.mark.parametrize("static_hidden, runs_hidden, verdict, data", [
    ("none", "friction", "coulomb_friction", "runs"),
    ("link_compliance", "none", "link_compliance", "static"),
    ("none", "none", None, None),
])
def test_diagnose_json_with_static_and_runs_covers_both(sim_dirs, tmp_path, capsys, static_hidden, runs_hidden,
                                                        verdict, data):
    d = sim_dirs[static_hidden]
    r = tmp_path / "runs"
    assert main(["sim", "runs", "--hidden", runs_hidden, "--seed", "3", "--out", str(r)]) == 0
    capsys.readouterr()
    assert main(["diagnose", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
                 "--runs", str(r / "runs.csv"), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["verdict"] == verdict
    assert {c["data"] for c in obj["candidates"]} == {"static", "runs"}
    assert obj["residual"]["unit"] == "m" and obj["runs"]["residual"]["unit"] == "N*m"
    if verdict is None:
        assert not any(c["significant"] for c in obj["candidates"])
    else:
        assert obj["candidates"][0]["effect"] == verdict and obj["candidates"][0]["data"] == data
    flags = [c["significant"] for c in obj["candidates"]]
    assert flags == sorted(flags, reverse=True)            # significant ones first
