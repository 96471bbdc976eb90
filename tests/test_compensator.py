"""Compensator parameters from simulated joint-2 sweeps (Yang §4.1, Klimchik §III)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from elastocal.errors import InputError
from elastocal.identify.compensator import compensator_from_run_table, identify_compensator, sweep_means
from elastocal.formats.robot_toml import parse_robot
from elastocal.formats.tables import read_run_table
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import SweepPlan, default_run_truth, simulate_run_dataset, simulate_runs

TOL = 0.02  # acceptance: within 2 % of the truth


@pytest.fixture(scope="module")
def truth():
    return default_run_truth(CellTruth())


@pytest.fixture(scope="module")
def sweeps(robot, truth):
    """Forward/backward sweeps at two q3, friction and current noise on."""
    return simulate_runs(robot, truth, seed=5, friction=None)


def _massless(robot):
    return replace(robot, joints=tuple(replace(j, mass=0.0) for j in robot.joints))


def test_hydropneumatic_with_gravity_from_the_model(robot, truth, sweeps):
    fit = compensator_from_run_table(robot, sweeps)
    true = np.array(truth.compensator)
    assert fit.names == ("C", "l_c") and fit.gravity == "model"
    np.testing.assert_allclose(fit.values, true, rtol=TOL)
    np.testing.assert_allclose(fit.values, true, rtol=0.005)
    assert np.all(fit.std > 0) and np.all(fit.std / true < 0.005)
    # friction cancelled in the mean: what is left is current noise (0.02 A * 220.8 N*m/A / sqrt 2)
    assert fit.rms < 4.5
    # the measured balancing torque crosses zero near q2 = 3.3 deg (Yang §5)
    zero = fit.q2[np.argmin(np.abs(fit.balancing_torque))]
    assert abs(np.degrees(zero) - 3.3) < 1.0
    # the friction torque of joint 2 along the sweep: Coulomb + viscous + load-dependent, positive
    assert np.median(fit.friction) > truth.coulomb[1]


def test_deflection_correction_with_known_stiffness(robot, truth, sweeps):
    fit = compensator_from_run_table(robot, sweeps, stiffness=truth.stiffness)
    np.testing.assert_allclose(fit.values, truth.compensator, rtol=0.002)


def test_hydropneumatic_with_gravity_identified(robot, truth, sweeps):
    """Link masses unknown: gravity identified with the compensator from sweeps at two q3."""
    bare = _massless(robot)
    fit = compensator_from_run_table(bare, sweeps)
    assert fit.gravity == "identified"
    assert fit.gravity_values.shape == (4,)   # two mass moments for link 2, two for link 3 (+ wrist)
    np.testing.assert_allclose(fit.values, truth.compensator, rtol=TOL)
    assert np.all(np.abs(fit.values - truth.compensator) < 5 * fit.std)


def test_one_q3_excites_two_gravity_combinations(robot, truth):
    table = simulate_runs(robot, truth, seed=6, friction=None, sweeps=SweepPlan(q3_values=(0.0,), step_rad=0.02))
    fit = compensator_from_run_table(_massless(robot), table)
    assert fit.gravity_values.shape == (2,)
    np.testing.assert_allclose(fit.values, truth.compensator, rtol=TOL)


SPRING_ROBOT = """
name = "spring-arm"
[[joint]]
a = 0.0
alpha = 0.0
d = 0.675
lower = -3.2
upper = 3.2
torque_constant = 150.0
[[joint]]
a = 0.35
alpha = -1.5707963267948966
d = 0.0
offset = -1.5707963267948966
lower = -0.7
upper = 1.9
torque_constant = 220.0
mass = 150.0
com = [0.55, 0.0, 0.1]
[[joint]]
a = 1.15
alpha = 0.0
d = 0.0
offset = 3.141592653589793
lower = -3.3
upper = 0.9
torque_constant = 200.0
mass = 110.0
com = [0.1, -0.3, 0.0]
[[joint]]
a = 0.0
alpha = -1.5707963267948966
d = -1.2
lower = -6.1
upper = 6.1
torque_constant = 120.0
mass = 25.0
com = [0.0, 0.0, 0.1]
[[joint]]
a = 0.0
alpha = 1.5707963267948966
d = 0.0
lower = -2.0
upper = 2.0
torque_constant = 130.0
[[joint]]
a = 0.0
alpha = -1.5707963267948966
d = 0.0
lower = -6.1
upper = 6.1
torque_constant = 130.0
[tool]
load_point = [0.0, 0.0, 0.3]
[tool.markers]
R1 = [0.0, 0.0, 0.25]
[compensator]
kind = "spring"
a = 0.6965
L = 0.18472
alpha = 2.0
"""


def test_spring_compensator(truth):
    robot = parse_robot(SPRING_ROBOT)
    spring_truth = replace(truth, compensator=(5.0e4, 0.458))
    table = simulate_runs(robot, spring_truth, seed=8, friction=None,
                          sweeps=SweepPlan(q2_start=-0.5, q2_end=1.6, step_rad=0.02))
    fit = compensator_from_run_table(robot, table)
    assert fit.names == ("K_c", "s0")
    np.testing.assert_allclose(fit.values, spring_truth.compensator, rtol=TOL)
    params = fit.parameters()
    assert params["K_c"]["unit"] == "N/m" and params["s0"]["unit"] == "m"


def test_through_the_csv(robot, truth, tmp_path):
    simulate_run_dataset(robot, truth, seed=3, out_dir=tmp_path)
    table = read_run_table(tmp_path / "runs.csv", robot)
    fit = compensator_from_run_table(robot, table)
    np.testing.assert_allclose(fit.values, truth.compensator, rtol=TOL)


def test_needs_both_directions(robot, sweeps):
    forward = sweeps.subset(sweeps.direction == "+")
    with pytest.raises(InputError, match="forward \\(\\+\\) and backward"):
        compensator_from_run_table(robot, forward)


def test_needs_a_compensator_and_currents(robot, sweeps):
    no_comp = replace(robot, compensator=None)
    means = sweep_means(robot, sweeps.q, sweeps.currents, sweeps.direction, sweeps.load, sweeps.wrench)
    with pytest.raises(InputError, match="no \\[compensator\\]"):
        identify_compensator(no_comp, means)
    currents = sweeps.currents.copy()
    currents[:, 1] = np.nan
    with pytest.raises(InputError, match="i2"):
        sweep_means(robot, sweeps.q, currents, sweeps.direction, sweeps.load, sweeps.wrench)


def test_sweeps_grouped_by_run_or_by_contiguity(robot, sweeps):
    by_run = sweep_means(robot, sweeps.q, sweeps.currents, sweeps.direction, sweeps.load, sweeps.wrench,
                         run=sweeps.run)
    by_block = sweep_means(robot, sweeps.q, sweeps.currents, sweeps.direction, sweeps.load, sweeps.wrench)
    assert len(set(by_run.sweep.tolist())) == 2    # two q3 values
    np.testing.assert_array_equal(by_run.torque, by_block.torque)
    # held joints jittering by encoder noise (0.1 mrad) stay one sweep
    q = sweeps.q + np.random.default_rng(0).normal(0.0, 1e-4, sweeps.q.shape) * (np.arange(6) != 1)
    noisy = sweep_means(robot, q, sweeps.currents, sweeps.direction, sweeps.load, sweeps.wrench, run=sweeps.run)
    assert len(set(noisy.sweep.tolist())) == 2
