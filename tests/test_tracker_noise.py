"""The tracker's noise law (model/tracker_noise.py, identify/trackernoise.py): a constant plus a
part growing with range, along and across the beam; stated in cell.toml ``[tracker] noise``,
estimated from repeats where they are enough, used for the weights, the floor and the outlier
test (docs/diagnose.md, "The tracker's noise"). The noise of the simulated data is drawn in
tests/helpers/tracker_law.py from the law written out with numpy; every generator is seeded."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from elastocal.diagnose.static import diagnose_static
from elastocal.drivers.config import parse_cell_config
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.outliers import find_outliers, tracker_noise_of
from elastocal.identify.trackernoise import estimate_tracker_noise
from elastocal.model.tracker_noise import TrackerNoise, parse_tracker_noise
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static
from tracker_law import ACROSS, ALONG, add_tracker_noise

ROBOT = bundled_robot()
QUIET = replace(CellTruth(), tracker_noise_m=0.0)      # the law's noise is added by the helper
TRUE_LAW = TrackerNoise(ALONG[0], ALONG[1], ACROSS[0], ACROSS[1])
#: a steeper law (a tracker whose angle encoders dominate at range): the far readings' noise is
#: twice the near ones', where one sigma for all readings cries wolf
STEEP = ((1.0e-6, 1.0e-6), (1.0e-6, 5.0e-6))


@pytest.fixture(scope="module")
def clean_table():
    return simulate_static(ROBOT, QUIET, seed=3)


def test_covariance_is_the_stated_law_along_and_across_the_beam():
    law = TrackerNoise.from_stated((10e-6, 2e-6), (30e-6, 6e-6), coverage=2.0)
    p = np.array([[0.0, 3.0, 4.0]])                       # 5 m from the head, beam along (0, .6, .8)
    cov = law.covariance(p)[0]
    u = p[0] / 5.0
    assert u @ cov @ u == pytest.approx(((10e-6 + 2e-6 * 5) / 2) ** 2, rel=1e-12)
    across = np.array([1.0, 0.0, 0.0])
    assert across @ cov @ across == pytest.approx(((30e-6 + 6e-6 * 5) / 2) ** 2, rel=1e-12)
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    # a head elsewhere in the points' frame: the same reading 5 m from it
    assert np.allclose(law.covariance(p + 1.0, tracker_p_head=np.ones(3))[0], cov)


def test_cell_toml_states_the_law_and_round_trips():
    text = ('[cell]\nname = "c"\nrobot = "hh150"\n[tracker]\nurl = "tracker+tcp://127.0.0.1:7000"\n'
            'markers = ["R1"]\nnoise = { along = [15e-6, 6e-6], across = [30e-6, 12e-6], k = 2 }\n')
    cell = parse_cell_config(text, source="cell.toml")
    law = cell.tracker.noise
    assert law.along_m == pytest.approx(7.5e-6) and law.across_per_m == pytest.approx(6e-6)
    again = parse_cell_config(cell.to_toml(), source="again.toml").tracker.noise
    assert again.sigma_across(4.0) == pytest.approx(law.sigma_across(4.0), rel=1e-12)


@pytest.mark.parametrize("doc,message", [
    ({"along": [1e-5, 1e-6]}, r"tracker\.noise\.across"),
    ({"along": [1e-5], "across": [1e-5, 1e-6]}, r"tracker\.noise\.along"),
    ({"along": [-1e-5, 0.0], "across": [1e-5, 1e-6]}, r"tracker\.noise\.along"),
    ({"along": [1e-5, 0.0], "across": [1e-5, 1e-6], "k": 0}, r"tracker\.noise\.k"),
    ({"along": [1e-5, 0.0], "across": [1e-5, 1e-6], "sigma": 1}, "unknown key 'sigma'"),
    ({"along": [0.0, 0.0], "across": [1e-5, 1e-6]}, "each have a part > 0"),
])
def test_a_bad_noise_table_is_refused_by_name(doc, message):
    with pytest.raises(InputError, match=message):
        parse_tracker_noise(doc, source="cell.toml")


def test_the_law_is_estimated_from_the_repeats(clean_table):
    """Along and across at the near and far ends of the readings within 25 % of the truth
    on each of 5 seeds (432 repeat groups of 3: the sigmas are known to a few percent)."""
    r = np.linalg.norm(clean_table.xyz, axis=1)
    near, far = np.percentile(r, 5), np.percentile(r, 95)
    for seed in range(5):
        law = estimate_tracker_noise(add_tracker_noise(clean_table, seed))
        for rr in (near, far):
            assert law.sigma_along(rr) == pytest.approx(TRUE_LAW.sigma_along(rr), rel=0.25), (seed, rr)
            assert law.sigma_across(rr) == pytest.approx(TRUE_LAW.sigma_across(rr), rel=0.25), (seed, rr)
    single = simulate_static(ROBOT, QUIET, seed=3, plan=StaticPlan(n_poses=4, repeats=1))
    assert estimate_tracker_noise(single) is None                   # nothing repeated: nothing to estimate
    assert tracker_noise_of(single, TRUE_LAW) is TRUE_LAW           # the cell's law then


def test_the_outlier_test_under_the_law_keeps_its_false_alarm_rate(clean_table):
    """Complete data with a steep range law, 60 seeds: one sigma for all readings (the median
    group's) flags far readings in many datasets; the law flags a dataset at most at the test's
    nominal rate (ALPHA = 1e-3 per dataset), and still finds a reading knocked by 0.15 mm."""
    old, new = 0, 0
    for seed in range(60):
        table = add_tracker_noise(clean_table, seed, *STEEP)
        old += bool(find_outliers(table))
        new += bool(find_outliers(table, noise=tracker_noise_of(table)))
    assert old >= 10, old            # the failure the law removes (this data can show it)
    assert new <= 2, new
    table = add_tracker_noise(clean_table, 0, *STEEP)
    far = int(np.argmax(np.linalg.norm(table.xyz, axis=1)))
    xyz = table.xyz.copy()
    xyz[far] += np.array([0.0, 0.15e-3, 0.0])
    bumped = replace(table, xyz=xyz)
    found = find_outliers(bumped, noise=tracker_noise_of(bumped))
    assert [o.row for o in found] == [far]


def test_without_repeats_the_cells_law_sets_weights_and_floor():
    """One reading per state: no repeats, so the level comes from the cell's law; the floor is
    then known and the complete model's verdict null (3 seeds)."""
    plan = StaticPlan(repeats=1)
    for seed in range(3):
        table = add_tracker_noise(simulate_static(ROBOT, QUIET, seed=seed, plan=plan), seed)
        assert not diagnose_static(ROBOT, table).noise_known              # no level without the law
        diag = diagnose_static(ROBOT, replace(table, tracker_noise=TRUE_LAW))
        assert diag.noise_known and diag.fit.noise_floor is not None
        assert diag.verdict is None and not diag.unexplained, (seed, diag.unexplained)
        truth = _true_floor(diag, TRUE_LAW)
        assert 0.8 < diag.absolute.base.noise_floor / truth < 1.25, seed
        assert diag.absolute.base.rms < 1.25 * diag.absolute.base.noise_floor, seed


def _true_floor(diag, law: TrackerNoise) -> float:
    """What the true law leaves on the absolute fit: the mean readings' variance less the
    fitted parameters' share, ``sqrt(trace(Sigma) (n - p) / n / n)``."""
    fit = diag.absolute.base
    ds = fit.dataset
    cov = law.covariance(fit.measured) / ds.abs_n[..., None, None]
    return float(np.sqrt(np.trace(cov, axis1=-2, axis2=-1).sum() * (fit.n - fit.n_params) / fit.n / fit.n))


@pytest.mark.heavy
@pytest.mark.acceptance
def test_acceptance_range_law_and_no_missing_effect_over_40_seeds():
    """The acceptance of the tracker's noise law: range-dependent tracker noise, nothing missing: verdict null, no
    outliers in >= 95 % of 40 seeds, the floor within 0.8-1.25x what the true law leaves."""
    ratios, with_outliers, verdicts = [], 0, []
    for seed in range(40):
        table = add_tracker_noise(simulate_static(ROBOT, QUIET, seed=100 + seed), seed)
        diag = diagnose_static(ROBOT, table)
        verdicts.append(diag.verdict)
        with_outliers += bool(diag.outliers)
        ratios.append(diag.absolute.base.noise_floor / _true_floor(diag, TRUE_LAW))
    assert verdicts.count(None) == 40, verdicts
    assert with_outliers <= 2, with_outliers
    assert 0.8 < min(ratios) and max(ratios) < 1.25, (min(ratios), max(ratios))
    print(json.dumps({"floor_ratio": [min(ratios), float(np.median(ratios)), max(ratios)],
                      "with_outliers": with_outliers}))
