"""Run data on the seven-joint cell (the HH-150 on a track, joint 1 prismatic): the compensator
sweeps move the compensator's joint (3 here), the UV/VU runs every joint, and the sim, the
MCAP log, identify, diagnose, the plan's [sweep] and the guided procedure take N joints; the
carriage's friction comes out in N and N*s/m.

Every identified value is checked against the simulator's truth within the uncertainty the fit
reports (sims/ computes the physics its own way, with Pinocchio)."""

from __future__ import annotations

import numpy as np
import pytest

from elastocal.acquisition.export import load_log
from elastocal.acquisition.logwriter import write_log_from_tables
from elastocal.diagnose.runs import diagnose_runs
from elastocal.formats.plan import SweepSpec, parse_plan, plan_toml
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.runs import identify_runs
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import FrictionPlan, SweepPlan, default_run_truth, simulate_runs

ROBOT = bundled_robot("hh150_track")
FRICTION = ("coulomb_friction", "viscous_friction", "load_dependent_friction")
#: a fitted value this many of its standard deviations from the truth is a failure (about 1 in
#: 16 000 for one normal value; 23 friction and compensator parameters per fit)
Z = 4.0


@pytest.fixture(scope="module")
def track_runs():
    truth = default_run_truth(CellTruth.for_robot(ROBOT))
    table = simulate_runs(ROBOT, truth, seed=11, sweeps=SweepPlan.for_robot(ROBOT, step_rad=0.02),
                          friction=FrictionPlan.for_robot(ROBOT, samples=120))
    return truth, table


def test_the_sweeps_move_the_compensator_joint_and_the_runs_every_joint(track_runs):
    _, table = track_runs
    assert table.n_joints == 7
    sweeps = np.isin(table.direction, ("+", "-"))
    moved = np.ptp(table.q[sweeps], axis=0)
    # within one sweep only joint 3 moves; across sweeps joint 4 takes its two values
    one = table.run == table.run[sweeps][0]
    assert np.argmax(np.ptp(table.q[one], axis=0)) == ROBOT.compensator.joint - 1 == 2
    assert np.count_nonzero(np.ptp(table.q[one], axis=0)) == 1 and moved[3] > 0
    assert np.all(table.q[sweeps, 0] == pytest.approx(3.0))     # the carriage mid-track [m]
    uv = table.direction == "UV"
    assert np.all(np.ptp(table.q[uv], axis=0) > 0)             # every joint moves on the UV runs
    assert 0.5 < np.ptp(table.q[uv, 0]) < 0.7                  # the carriage 0.6 m along its 6 m


def test_identify_runs_recovers_the_carriage_friction_in_newtons_and_the_compensator(track_runs):
    truth, table = track_runs
    fit = identify_runs(ROBOT, table, model=("compensator", *FRICTION), stiffness=truth.stiffness)
    params = {p.name: p for p in fit.parameters}
    want = truth.parameters(ROBOT)
    assert {"fc1", "fv1", "fl1", "fc7", "fv7", "fl7", "C", "l_c"} <= set(params)
    assert params["fc1"].unit == "N" and params["fv1"].unit == "N*s/m" and params["fl1"].unit == "1"
    assert params["fc2"].unit == "N*m" and params["fv2"].unit == "N*m*s/rad"
    for name, p in params.items():
        assert abs(p.value - want[name]["value"]) < Z * p.std, (name, p.value, p.std, want[name]["value"])
    # the carriage's Coulomb friction is the track's (sims/runs.py), not an arm joint's value
    assert params["fc1"].value == pytest.approx(400.0, rel=0.05)
    assert fit.noise_floor is not None and fit.rms < 1.1 * fit.noise_floor
    assert fit.stiffness is not None and fit.stiffness.source == "static fit"


def test_the_rigid_model_states_its_bias_on_the_compensator_joint(track_runs):
    _, table = track_runs
    sweeps = table.subset(np.isin(table.direction, ("+", "-")))
    fit = identify_runs(ROBOT, sweeps, model=("compensator",))
    note = fit.stiffness.note
    assert fit.stiffness.source == "rigid" and "joint-3 sweep torque" in note and "N/m" in note
    assert dict(fit.stiffness.bias_parameters)["C"] > 0


def test_diagnose_runs_finds_the_three_friction_terms_and_no_compensator(track_runs):
    truth, table = track_runs
    diag = diagnose_runs(ROBOT, table, stiffness=truth.stiffness)
    assert {s.effect for s in diag.steps} == set(FRICTION)
    assert diag.final.rms < 1.1 * diag.final.noise_floor
    # the description's compensator and gravity are right: candidates, never a finding
    found = {c.effect: c for c in diag.candidates}
    assert {"compensator", "gravity"} <= set(found)
    assert not found["compensator"].significant and not found["gravity"].significant
    assert [g.labels for g in diag.groups if g.by == "joint"][0] == tuple(f"j{j}" for j in range(1, 8))


def test_a_sweep_of_another_joint_is_refused_for_the_compensator(track_runs):
    """The compensator acts on joint 3: sweeps of joint 2 (the turret) cannot show it."""
    truth = CellTruth.for_robot(ROBOT)
    plan = SweepPlan.for_robot(ROBOT, step_rad=0.05, q3_values=(0.0,))
    turret = SweepPlan(q_base=plan.q_base, q2_start=-0.5, q2_end=0.5, q3_values=(0.0,), step_rad=0.05, joint=2)
    table = simulate_runs(ROBOT, truth, seed=3, sweeps=turret, friction=None)
    from elastocal.errors import InputError

    with pytest.raises(InputError, match="sweeps move joint 2; the compensator acts on joint 3"):
        identify_runs(ROBOT, table, model=("compensator",))


def test_the_log_holds_the_seven_joint_runs(track_runs, tmp_path):
    _, table = track_runs
    log = tmp_path / "runs.mcap"
    write_log_from_tables(log, ROBOT, runs=table)
    robot, static, runs = load_log(log)
    assert static is None and robot.n_joints == 7 and runs.n_joints == 7
    assert list(dict.fromkeys(runs.run)) == list(dict.fromkeys(table.run))
    np.testing.assert_allclose(runs.q, table.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(runs.currents, table.currents, rtol=1e-12, atol=1e-12)


def test_the_plan_sweep_names_its_joint():
    sweep = SweepSpec(q=(3.0, 0.0, 0.0, -0.5, 0.0, 0.5, 0.0), q2_from=-0.3, q2_to=1.2, speed_rad_s=0.1, joint=3)
    text = plan_toml(poses=[], loads=(), markers=(), sweep=sweep)
    assert "joint = 3" in text
    back = parse_plan(text, source="plan.toml").sweep
    assert back.joint == 3 and back.ends() == ((3.0, 0.0, -0.3, -0.5, 0.0, 0.5, 0.0),
                                               (3.0, 0.0, 1.2, -0.5, 0.0, 0.5, 0.0))
    six = SweepSpec(q=(0.0,) * 6, q2_from=-0.3, q2_to=1.2, speed_rad_s=0.1)
    assert "joint" not in plan_toml(poses=[], loads=(), markers=(), sweep=six)   # the default stays unwritten
    from elastocal.errors import InputError

    with pytest.raises(InputError, match="joint 8 of a sweep whose q has 7 joints"):
        parse_plan(text.replace("joint = 3", "joint = 8"), source="plan.toml")


@pytest.mark.slow
def test_the_guided_friction_pair_and_sweep_run_on_the_simulated_track_cell(tmp_path):
    """The plan's sweep of joint 3 and a UV/VU pair that moves the carriage, through the real
    drivers against the simulated seven-joint devices (wall-clock time)."""
    from dataclasses import replace

    from elastocal.acquisition.procedures import run_calibration
    from elastocal.drivers.config import PathSpec
    from elastocal.formats.plan import FrictionSpec, LoadSpec, SettleSpec
    from elastocal.sims.serve import SimulatedCell, example_cell_config

    u, v = (2.9, 0.1, 0.3, -0.4, 0.0, 0.6, 0.0), (3.1, 0.25, 0.4, -0.35, 0.05, 0.65, 0.05)
    w0 = (3.0, 0.0, 0.2, -0.5, 0.0, 0.5, 0.0)
    w1 = (3.0, 0.0, 0.45, -0.5, 0.0, 0.5, 0.0)
    config = example_cell_config(can_channel="track-runs", robot="hh150_track", move_speed_rad_s=2.0)
    config = replace(config, controller=replace(config.controller, paths=(PathSpec(1, u, v, 0.1),
                                                                          PathSpec(2, w0, w1, 0.1))))
    plan = parse_plan(plan_toml(poses=[], loads=(LoadSpec("L1", mass_kg=80.0),), markers=(),
                                friction=(FrictionSpec("F1", start=u, end=v, speeds_rad_s=(0.1,), loads=("L1",)),),
                                sweep=SweepSpec(q=w0, q2_from=0.2, q2_to=0.45, speed_rad_s=0.25, joint=3),
                                settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=10.0)), source="plan")
    log = tmp_path / "runs.mcap"
    with SimulatedCell(config) as sim:
        assert run_calibration(sim.config, plan, log, yes=True, world=sim.world).status == "completed"
    robot, static, runs = load_log(log)
    assert static is None and robot.n_joints == 7 and runs.n_joints == 7
    assert list(dict.fromkeys(runs.run)) == ["F1-1-UV", "F1-1-VU", "sweep-1+", "sweep-1-"]
    plus = runs.run == "sweep-1+"
    assert np.ptp(runs.q[plus][:, 2]) == pytest.approx(0.25, abs=3e-3)          # joint 3 swept
    assert np.max(np.ptp(runs.q[plus][:, [0, 1, 3, 4, 5, 6]], axis=0)) < 1e-6    # the others held
    # the carriage's friction from the UV/VU pair: the drive pushes harder forward (docs/physics.md),
    # a force in N (xi1 in N/A) of the size the simulated cell's track has
    uv, vu = runs.run == "F1-1-UV", runs.run == "F1-1-VU"
    mid = lambda rows: np.abs(runs.q[rows][:, 0] - 3.0) < 0.03  # noqa: E731
    xi1 = robot.torque_constants[0]
    f1 = xi1 * (runs.currents[uv][mid(uv), 0].mean() - runs.currents[vu][mid(vu), 0].mean()) / 2
    # Coulomb 400 N plus viscous 3000 N*s/m at up to 0.1 m/s (sims/data/sim_cell_track.toml)
    assert 350.0 < f1 < 900.0, f1
