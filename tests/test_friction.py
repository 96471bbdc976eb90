"""Joint friction from simulated UV/VU runs (Yang eq. 48 and beyond)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from elastocal.errors import InputError
from elastocal.identify.friction import (
    friction_from_run_table,
    friction_samples,
    identify_friction,
    match_path,
)
from elastocal.formats.tables import run_table_from_arrays
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs

TOL = 0.05  # acceptance: friction coefficients within 5 %


@pytest.fixture(scope="module")
def truth():
    return default_run_truth(CellTruth())


@pytest.fixture(scope="module")
def runs(robot, truth):
    """UV/VU at two speeds and two loads, current noise on."""
    return simulate_runs(robot, truth, seed=21, sweeps=None)


def test_all_coefficients_within_5_percent(robot, truth, runs):
    fit = friction_from_run_table(runs, robot.torque_constants)
    assert fit.terms == ("coulomb", "viscous", "load_dependent")
    np.testing.assert_allclose(fit.coulomb, truth.coulomb, rtol=TOL)
    np.testing.assert_allclose(fit.viscous, truth.viscous, rtol=TOL)
    np.testing.assert_allclose(fit.load_dependent, truth.load_friction, rtol=TOL)
    # the reported uncertainty is honest: errors within 4 standard deviations
    true = np.column_stack([truth.coulomb, truth.viscous, truth.load_friction])
    assert np.all(np.abs(fit.values - true) < 4 * fit.std)
    assert fit.unidentified == ()
    params = fit.parameters()
    assert set(params) == {f"{p}{j}" for p in ("fc", "fv", "fl") for j in range(1, 7)}
    assert params["fv2"]["unit"] == "N*m*s/rad" and params["fc1"]["unit"] == "N*m" and params["fl3"]["unit"] == "1"
    # residual at the current noise: 0.02 A * xi / sqrt(2) per half difference
    np.testing.assert_allclose(fit.residual_rms, 0.02 * robot.torque_constants / np.sqrt(2), rtol=0.25)


def test_half_difference_is_the_friction_torque(robot, truth):
    """Y48 without noise: the matched half difference equals fc + fv |dq| + fl |tau|."""
    quiet = replace(truth, current_noise_a=0.0)
    plan = FrictionPlan(speeds_rad_s=(0.1,), loads=(("1", (900.0, -700.0, -1500.0, 200.0, -200.0, 250.0)),),
                        samples=30)
    table = simulate_runs(robot, quiet, seed=0, sweeps=None, friction=plan)
    s = friction_samples(table.q, table.dq, table.currents, table.run, table.direction, table.load,
                         robot.torque_constants)
    cell = SimCell(robot, quiet)
    uv = table.direction == "UV"
    tau = np.array([cell.equilibrium(q, w).gear_torque for q, w in zip(table.q[uv], table.wrench[uv])])
    expected = quiet.coulomb + quiet.viscous * np.abs(table.dq[uv]) + quiet.load_friction * np.abs(tau)
    np.testing.assert_allclose(s.friction, expected, rtol=1e-9)
    np.testing.assert_allclose(s.load_torque, tau, rtol=1e-9, atol=1e-9)


def test_one_speed_one_load_leaves_terms_out(robot, truth):
    plan = FrictionPlan(speeds_rad_s=(0.1,), loads=(("0", (0.0,) * 6),), samples=60)
    table = simulate_runs(robot, truth, seed=4, sweeps=None, friction=plan)
    fit = friction_from_run_table(table, robot.torque_constants, terms=("coulomb", "viscous"))
    # one speed: viscous cannot be told from Coulomb; it is left out, not guessed
    assert np.all(np.isnan(fit.viscous))
    assert set(fit.unidentified) == {f"fv{j}" for j in range(1, 7)}
    assert fit.values.shape == (6, 2)
    assert "fv1" not in fit.parameters() and "fc1" in fit.parameters()


def test_vu_sampled_elsewhere_and_speeds_from_time(robot, truth, runs):
    """VU samples need not coincide with UV samples; dq may be empty (finite differences)."""
    keep = np.ones(len(runs), dtype=bool)
    vu = np.flatnonzero(runs.direction == "VU")
    keep[vu[::3]] = False  # drop every third VU sample
    sub = runs.subset(keep)
    table = run_table_from_arrays(run=sub.run, direction=sub.direction, load=sub.load, t=sub.t, q=sub.q,
                                  currents=sub.currents, wrench=sub.wrench)
    fit = friction_from_run_table(table, robot.torque_constants)
    np.testing.assert_allclose(fit.coulomb, truth.coulomb, rtol=TOL)
    np.testing.assert_allclose(fit.viscous, truth.viscous, rtol=TOL)
    np.testing.assert_allclose(fit.load_dependent, truth.load_friction, rtol=TOL)


def test_match_path_interpolates():
    qb = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 1.0]])
    m = match_path(np.array([[0.25, 0.1], [1.5, 0.5], [3.0, 2.0]]), qb)
    np.testing.assert_array_equal(m.index, [0, 1, 1])
    np.testing.assert_allclose(m.fraction, [0.25, 0.5, 1.0])
    np.testing.assert_allclose(m.distance, [0.1, 0.0, np.sqrt(2)])
    np.testing.assert_allclose(m.interpolate(np.array([0.0, 10.0, 20.0])), [2.5, 15.0, 20.0])


def test_uv_without_vu_is_an_input_error(robot, runs):
    only = runs.subset(~((runs.direction == "VU") & (runs.load == "1")))
    with pytest.raises(InputError, match="UV run UV-0.05-1 \\(load 1\\) has no VU run"):
        friction_from_run_table(only, robot.torque_constants)
    with pytest.raises(InputError, match="no UV/VU runs"):
        friction_from_run_table(runs.subset(runs.direction == "+"), robot.torque_constants)
    with pytest.raises(InputError, match="unknown friction term"):
        identify_friction(friction_samples(runs.q, runs.dq, runs.currents, runs.run, runs.direction, runs.load,
                                           robot.torque_constants), terms=("coulomb", "stribeck"))


def _yang_fig15_runs(fc: float, fv: float, tau_load: float, noise_a: float, seed: int):
    """Joint 3 of Yang's Fig. 15, written from the motor's torque balance alone (no model
    code): UV turns it negative, the payload's torque acts the same way, and the drive
    supplies load and friction in the direction of motion, ``xi i = tau_load + f sign(dq)``."""
    rng = np.random.default_rng(seed)
    xi = np.ones(6)
    n = 80
    s = np.linspace(0.0, 1.0, n)
    rows = {k: [] for k in ("run", "direction", "load", "t", "q", "dq", "currents")}
    for speed in (0.05, 0.15):
        for direction, sgn in (("UV", -1.0), ("VU", 1.0)):
            q = np.zeros((n, 6))
            q[:, 2] = np.interp(s, (0.0, 1.0), (0.4, -0.4) if sgn < 0 else (-0.4, 0.4))
            dq = np.zeros((n, 6))
            dq[:, 2] = sgn * speed
            tau = np.zeros((n, 6))
            tau[:, 2] = tau_load                   # same sign as the motion on UV: friction acts with it
            i = (tau + (fc + fv * speed) * np.sign(dq)) / xi + rng.normal(0.0, noise_a, size=(n, 6))
            rows["run"] += [f"{direction}-{speed}"] * n
            rows["direction"] += [direction] * n
            rows["load"] += ["1"] * n
            rows["t"] += list(s * 0.8 / speed)
            rows["q"] += list(q)
            rows["dq"] += list(dq)
            rows["currents"] += list(i)
    table = run_table_from_arrays(**rows, wrench=np.zeros((len(rows["run"]), 6)), source="<fig15>")
    return table, xi


def test_friction_is_positive_when_the_drive_supplies_it_in_the_direction_of_motion():
    """Yang Fig. 15 in words: joint 3 turns negative on UV, friction acts with the payload,
    so UV's current is the larger in size; the fit gives positive friction."""
    table, xi = _yang_fig15_runs(fc=120.0, fv=300.0, tau_load=-900.0, noise_a=0.5, seed=3)
    uv, vu = table.direction == "UV", table.direction == "VU"
    assert np.mean(np.abs(table.currents[uv, 2])) > np.mean(np.abs(table.currents[vu, 2])) + 200.0
    fit = friction_from_run_table(table, xi, terms=("coulomb", "viscous"))
    std = fit.std[2]
    assert fit.coulomb[2] == pytest.approx(120.0, abs=4 * std[0]) and fit.coulomb[2] > 0
    assert fit.viscous[2] == pytest.approx(300.0, abs=4 * std[1]) and fit.viscous[2] > 0


def _old_calibration(fc1: float) -> dict:
    return {"format": "elastocal.calibration/1", "robot": "HH-150", "created": "2026-11-22T10:00:00Z",
            "model": ["coulomb_friction"], "torque": "current",
            "parameters": {"fc1": {"value": fc1, "std": 2.0, "unit": "N*m"}},
            "residual": {"rms": 1.0, "n": 10}, "data": []}


def test_an_old_calibration_reads_with_its_friction_sign_turned(tmp_path):
    """Files written under xi i = tau_load - f sign(dq) hold minus the friction; they read
    with the physical sign and a note, and write back marked so they are not turned twice."""
    import json

    from elastocal.formats.calibration import FRICTION_SIGN, read_calibration, write_calibration

    path = tmp_path / "old.json"
    path.write_text(json.dumps(_old_calibration(-119.5)), encoding="utf-8")
    cal = read_calibration(path)
    p = cal.find("fc1")
    assert p.value == 119.5 and p.std == 2.0
    assert "sign converted" in p.note and "-119.5" in p.note
    write_calibration(tmp_path / "new.json", cal)
    doc = json.loads((tmp_path / "new.json").read_text(encoding="utf-8"))
    assert doc["friction_sign"] == FRICTION_SIGN and doc["parameters"]["fc1"]["value"] == 119.5
    again = read_calibration(tmp_path / "new.json")
    assert again.find("fc1").value == 119.5 and again == cal


def test_a_calibration_with_another_friction_sign_is_refused(tmp_path):
    import json

    from elastocal.formats.calibration import read_calibration

    doc = _old_calibration(120.0)
    doc["friction_sign"] = "against_motion"
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(InputError, match="friction_sign"):
        read_calibration(path)
