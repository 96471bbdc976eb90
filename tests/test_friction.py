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
