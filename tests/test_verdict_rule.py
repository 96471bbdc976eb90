"""The verdict rule of docs/cli.md: a candidate is the verdict only when its own test
gives p < 0.01 AND adding it lowers BIC by more than 10 — either alone is not enough."""

from dataclasses import replace

import pytest

from elastocal.diagnose.static import diagnose_static
from elastocal.diagnose.runs import diagnose_runs
from elastocal.diagnose.verdict import VERDICT_DELTA_BIC, VERDICT_P
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import CellTruth
from elastocal.sims.runs import default_run_truth, simulate_runs
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
CASES = [(1e-3, -50.0, True), (1e-3, -5.0, False), (0.05, -50.0, False), (0.05, -5.0, False),
         (VERDICT_P, -50.0, False), (1e-3, VERDICT_DELTA_BIC, False)]


def test_the_thresholds_are_those_of_cli_md():
    assert (VERDICT_P, VERDICT_DELTA_BIC) == (0.01, -10.0)


@pytest.fixture(scope="module")
def static_candidate():
    table = simulate_static(ROBOT, CellTruth().with_hidden("link_compliance"), seed=3, plan=StaticPlan(n_poses=8))
    diag = diagnose_static(ROBOT, table)
    assert diag.verdict == "link_compliance"
    return diag.candidates[0]


@pytest.fixture(scope="module")
def run_candidate():
    diag = diagnose_runs(ROBOT, simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=1),
                         stiffness=CellTruth().stiffness)
    assert diag.verdict == "coulomb_friction"
    return diag.candidates[0]


@pytest.mark.parametrize("p, delta_bic, significant", CASES)
def test_static_candidates_need_both_tests(static_candidate, p, delta_bic, significant):
    assert replace(static_candidate, p_value=p, delta_bic=delta_bic).significant is significant


@pytest.mark.parametrize("p, delta_bic, significant", CASES)
def test_run_candidates_need_both_tests(run_candidate, p, delta_bic, significant):
    assert replace(run_candidate, p_value=p, delta_bic=delta_bic).significant is significant


def test_a_candidate_without_a_p_value_is_never_the_verdict(static_candidate):
    assert replace(static_candidate, p_value=None, delta_bic=-1e6).significant is False
