"""Static identification against the simulated cell's known truth."""

import dataclasses

import numpy as np
import pytest

from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import build_dataset, identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, load_wrenches, random_poses, simulate_static
from elastocal.model.kinds import KinematicForm, TorqueSource, Weighting

ROBOT = bundled_robot()
TRUTH = CellTruth()
K = [f"k{j}" for j in range(1, 7)]
PLAN = StaticPlan(n_poses=12, n_loads=3, repeats=3)  # 12 poses, 4 load states, 3 markers, 3 repeats


def rel_err(fit, truth=TRUTH):
    return fit.values(K) / truth.stiffness - 1.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_current_based_exact_recovers_stiffness(seed):
    fit = identify_static(ROBOT, simulate_static(ROBOT, TRUTH, seed=seed, plan=PLAN))
    err = np.abs(rel_err(fit))
    assert np.all(err[:3] < 0.02), err
    assert np.all(err[3:] < 0.05), err
    assert fit.noise_floor is not None
    assert fit.rms <= 1.15 * fit.noise_floor
    assert fit.n == 12 * 3 * 3 * 3
    assert not fit.unidentifiable


@pytest.mark.heavy
@pytest.mark.acceptance
def test_reported_std_matches_spread_over_20_seeds():
    ks, stds, ratios = [], [], []
    for seed in range(100, 120):
        fit = identify_static(ROBOT, simulate_static(ROBOT, TRUTH, seed=seed, plan=PLAN))
        ks.append(fit.values(K))
        stds.append(fit.stds(K))
        ratios.append(fit.rms / fit.noise_floor)
    ks, stds = np.array(ks), np.array(stds)
    spread = ks.std(axis=0, ddof=1)
    factor = spread / stds.mean(axis=0)
    assert np.all(factor < 1.5) and np.all(factor > 1 / 1.5), factor
    assert max(ratios) <= 1.15, ratios
    # the noise floor is the residual of a complete model: the ratio centres on 1
    assert 0.9 < float(np.mean(ratios)) < 1.1


def test_noise_floor_matches_tracker_noise():
    # deflection = mean of 3 loaded minus mean of 3 reference readings: sqrt(2/3) * 10 µm,
    # plus current noise, less the degrees of freedom the 6 parameters take
    fit = identify_static(ROBOT, simulate_static(ROBOT, TRUTH, seed=4, plan=PLAN))
    ds = fit.dataset
    assert ds.sigma_tracker == pytest.approx(10e-6, rel=0.1)
    np.testing.assert_allclose(ds.sigma_current, 0.02, rtol=0.25)
    assert 8.0e-6 < fit.noise_floor < 9.5e-6


def test_static_friction_biases_force_based_high_not_current_based():
    truth = TRUTH.with_hidden("static_friction")
    table = simulate_static(ROBOT, truth, seed=5, plan=PLAN)
    current = rel_err(identify_static(ROBOT, table, torque=TorqueSource.CURRENT), truth)
    force = rel_err(identify_static(ROBOT, table, torque=TorqueSource.FORCE), truth)
    assert np.all(np.abs(current) < 0.05), current
    assert np.all(force > 0.04), force           # every joint looks stiffer than it is
    assert np.mean(force[:3]) > 0.10, force


def noise_free(truth=TRUTH):
    return dataclasses.replace(truth, tracker_noise_m=0.0, current_noise_a=0.0)


def test_exact_form_is_exact_and_first_order_is_not():
    truth = noise_free()
    table = simulate_static(ROBOT, truth, seed=6, plan=StaticPlan(n_poses=12, n_loads=3, repeats=1))
    exact = identify_static(ROBOT, table, form=KinematicForm.EXACT)
    first = identify_static(ROBOT, table, form=KinematicForm.FIRST_ORDER)
    np.testing.assert_allclose(exact.values(K), truth.stiffness, rtol=1e-6)
    assert exact.rms < 1e-9
    # first order leaves micrometres of model error that grow with the load
    assert 0.3e-6 < first.rms < 10e-6
    ds = first.dataset
    load_size = np.linalg.norm(ds.state_currents[ds.defl_state] - ds.state_currents[ds.defl_ref], axis=1)
    big = load_size > np.median(load_size)
    r = np.linalg.norm(first.residuals, axis=1)
    assert r[big].mean() > r[~big].mean()


def test_force_based_exact_is_exact_with_known_gravity_and_compensator():
    truth = noise_free()
    table = simulate_static(ROBOT, truth, seed=7, plan=StaticPlan(n_poses=12, n_loads=3, repeats=1))
    fit = identify_static(ROBOT, table, torque=TorqueSource.FORCE, form=KinematicForm.EXACT)
    np.testing.assert_allclose(fit.values(K), truth.stiffness, rtol=1e-5)


def test_unidentifiable_joint_is_reported_not_guessed():
    # only hung weights, and the turret axis vertical: no load ever twists joint 1
    rng = np.random.default_rng(8)
    poses = random_poses(ROBOT, 8, rng)
    wrenches = [load_wrenches(2, rng) for _ in poses]
    table = simulate_static(ROBOT, TRUTH, seed=8, poses=poses, wrenches=wrenches,
                            plan=StaticPlan(n_poses=8, n_loads=2, repeats=2))
    fit = identify_static(ROBOT, table, torque=TorqueSource.FORCE)
    assert fit.unidentifiable == ("k1",)
    assert [p.name for p in fit.parameters] == K[1:]
    assert fit.to_json()["unidentifiable"] == ["k1"]


def test_no_repeats_means_no_noise_floor():
    table = simulate_static(ROBOT, TRUTH, seed=9, plan=StaticPlan(n_poses=12, n_loads=3, repeats=1))
    fit = identify_static(ROBOT, table)
    assert fit.noise_floor is None
    assert fit.to_json()["noise_floor"] is None
    err = np.abs(rel_err(fit))
    assert np.all(err < 0.06), err


def test_drift_without_time_is_refused():
    table = simulate_static(ROBOT, TRUTH, seed=10, plan=StaticPlan(n_poses=4, n_loads=2, repeats=2))
    no_time = dataclasses.replace(table, t=np.full(len(table), np.nan))
    with pytest.raises(InputError, match=r"^model: thermal_drift: the static table has no times"):
        identify_static(ROBOT, no_time, model=("joint_stiffness", "thermal_drift"))


def test_friction_from_static_data_is_refused_with_reason():
    table = simulate_static(ROBOT, TRUTH, seed=10, plan=StaticPlan(n_poses=4, n_loads=2, repeats=2))
    with pytest.raises(InputError, match=r"coulomb_friction: friction acts during motion"):
        identify_static(ROBOT, table, model=("joint_stiffness", "coulomb_friction"))


def test_force_based_needs_wrench_and_current_based_needs_currents():
    table = simulate_static(ROBOT, TRUTH, seed=10, plan=StaticPlan(n_poses=4, n_loads=2, repeats=2))
    no_i = dataclasses.replace(table, currents=np.full((len(table), 6), np.nan))
    with pytest.raises(InputError, match="needs the currents"):
        identify_static(ROBOT, no_i)
    no_w = dataclasses.replace(table, wrench=np.full((len(table), 6), np.nan))
    with pytest.raises(InputError, match="needs the wrench"):
        identify_static(ROBOT, no_w, torque=TorqueSource.FORCE)


def test_dataset_averages_repeats_and_pairs_reference():
    table = simulate_static(ROBOT, TRUTH, seed=12, plan=StaticPlan(n_poses=3, n_loads=2, repeats=3))
    ds = build_dataset(table)
    assert ds.n_states == 3 * 3
    assert ds.n_deflections == 3 * 2 * 3
    d = 4
    s, r, m = ds.defl_state[d], ds.defl_ref[d], ds.markers[ds.defl_marker[d]]
    rows_l = (table.pose == ds.pose_ids[ds.state_pose[s]]) & (table.load == ds.state_load[s]) & (table.marker == m)
    rows_r = (table.pose == ds.pose_ids[ds.state_pose[r]]) & (table.load == "0") & (table.marker == m)
    np.testing.assert_allclose(ds.dP[d], table.xyz[rows_l].mean(axis=0) - table.xyz[rows_r].mean(axis=0))
    assert ds.defl_n[d] == 3 and ds.defl_n_ref[d] == 3


def test_the_weighting_asked_for_is_the_one_used_when_the_tracker_stands_anywhere():
    """A tracker placed anywhere turns the deflections to base axes by a first fit and a
    refined registration: both fits use the weighting asked for (plain least squares with
    ``ols``: no whitening), and the two weightings estimate the same stiffness."""
    robot = bundled_robot()
    table = simulate_static(robot, CellTruth(), seed=12, plan=StaticPlan(n_poses=10))
    assert build_dataset(table).tracker_rotation is None
    gls = identify_static(robot, table, weighting=Weighting.GLS)
    ols = identify_static(robot, table, weighting=Weighting.OLS)
    assert gls.whitening is not None and ols.whitening is None
    assert gls.rss_whitened is not None and ols.rss_whitened is None
    std = np.sqrt(np.diag(gls.beta_cov) + np.diag(ols.beta_cov))
    assert np.all(np.abs(gls.beta - ols.beta) < 4 * std)      # two unbiased estimates of one truth
    assert not np.allclose(np.diag(gls.beta_cov), np.diag(ols.beta_cov), rtol=1e-3, atol=0.0)
