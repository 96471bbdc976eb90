"""The joint stiffness stays honest after the located compliance is selected
(identify/selection.py): over 100 seeds of a hidden link_compliance on the demo's
6 poses, the 95 % intervals of every k cover the truth about 95 % of the time.
Without the controls the same seeds cover k5 about a fifth of the time (the
demo's failure: cl3y below the test's threshold, k5 absorbing it at -5 %).

100 seeds make 0.95 +- 0.022 one binomial sigma; the bound 0.89 is 2.7 sigma."""

from dataclasses import replace

import numpy as np
import pytest

from elastocal.model.effects import get_effect
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import build_dataset, identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
K_NAMES = [f"k{j}" for j in range(1, 7)]
N_SEEDS = 100


@pytest.mark.heavy
@pytest.mark.acceptance
def test_stiffness_intervals_cover_truth_after_the_selection():
    truth = CellTruth().with_hidden("link_compliance")
    eff = get_effect("link_compliance")
    z, z_lean = [], []
    for seed in range(N_SEEDS):
        ds = build_dataset(simulate_static(ROBOT, truth, seed=seed, plan=StaticPlan(n_poses=6)))
        fit = identify_static(ROBOT, ds, model=("link_compliance",))
        z.append((fit.values(K_NAMES) - truth.stiffness) / fit.stds(K_NAMES))
        sel = fit.selections[0]
        assert not set(sel.controls) & set(sel.kept)
        assert fit.rms <= 1.3 * fit.noise_floor, seed
        # the same selection without its controls: the method before
        lean = identify_static(ROBOT, ds, model=(eff.restricted(replace(sel, controls=()).fitted()),))
        z_lean.append((lean.values(K_NAMES) - truth.stiffness) / lean.stds(K_NAMES))
    coverage = (np.abs(np.array(z)) < 1.959964).mean(axis=0)
    assert np.all(coverage >= 0.89), coverage
    assert np.all(np.abs(np.array(z).mean(axis=0)) < 0.75), np.array(z).mean(axis=0)
    lean_coverage = (np.abs(np.array(z_lean)) < 1.959964).mean(axis=0)
    assert lean_coverage.min() < 0.5, lean_coverage
