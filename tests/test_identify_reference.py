"""The static fit's numbers are what they were before its fast paths.

``tests/data/golden/identify_arrays.npz`` holds, for each case below, every array a
static fit returns (parameters and their covariance, predictions, residuals, the
absolute positions, the noise floor, the design, the noise blocks and the whitened
metric), made by this test from the code before the vectorised table averaging,
noise covariance, whitening and kinematics (``ELASTOCAL_WRITE_GOLDEN=1 python -m pytest
tests/test_identify_reference.py``). The fast code must give them to 1e-9 relative
(the last bits may move when a sum is reordered; nothing else may). A change meant to
change the fit regenerates them the same way and says why in its commit.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
from golden_tolerance import RELATIVE, UNIT_FLOOR, array_mismatch, array_tolerance

from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import identify_static
from elastocal.formats.tables import StaticTable
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static
from elastocal.model.kinds import KinematicForm, TorqueSource, Weighting

GOLDEN = pathlib.Path(__file__).parent / "data" / "golden" / "identify_arrays.npz"
WRITE = os.environ.get("ELASTOCAL_WRITE_GOLDEN") == "1"
#: arrays in metres
METRES = ("predicted", "residuals", "absolute_base")

#: name -> (hidden effect, plan, model, torque, form, weighting, u95 column)
CASES = {
    "exact_current": ("none", StaticPlan(n_poses=10), ("joint_stiffness",), "current", "exact", "gls", False),
    "exact_current_ols": ("none", StaticPlan(n_poses=10), ("joint_stiffness",), "current", "exact", "ols", False),
    "first_order_current": ("none", StaticPlan(n_poses=10), ("joint_stiffness",), "current", "first-order", "gls",
                            False),
    "exact_force": ("none", StaticPlan(n_poses=10), ("joint_stiffness",), "force", "exact", "gls", False),
    "first_order_force": ("none", StaticPlan(n_poses=10), ("joint_stiffness",), "force", "first-order", "gls",
                          False),
    "shared_currents": ("none", StaticPlan(n_poses=10, shared_currents=True), ("joint_stiffness",), "current",
                        "exact", "gls", False),
    "uneven_markers": ("none", StaticPlan(n_poses=12, n_loads=2, repeats=2, markers=("R1", "R3")),
                       ("joint_stiffness",), "current", "exact", "gls", False),
    "u95": ("none", StaticPlan(n_poses=10), ("joint_stiffness",), "current", "exact", "gls", True),
    "link_compliance": ("link_compliance", StaticPlan(n_poses=20), ("joint_stiffness", "link_compliance"),
                        "current", "exact", "gls", False),
    "backlash": ("backlash", StaticPlan(n_poses=10), ("joint_stiffness", "backlash"), "current", "exact", "gls",
                 False),
    "thermal_drift": ("thermal_drift", StaticPlan(n_poses=10), ("joint_stiffness", "thermal_drift"), "current",
                      "exact", "gls", False),
    "static_friction": ("static_friction", StaticPlan(n_poses=10), ("joint_stiffness", "static_friction"),
                        "force", "exact", "gls", False),
    "complementary_force": ("none", StaticPlan(n_poses=10), ("joint_stiffness", "complementary_stiffness"),
                            "force", "first-order", "gls", False),
}


def _table(hidden: str, plan: StaticPlan, u95: bool, seed: int) -> StaticTable:
    robot = bundled_robot()
    table = simulate_static(robot, CellTruth().with_hidden(hidden), seed=seed, plan=plan)
    if not u95:
        return table
    rng = np.random.default_rng(seed + 100)
    values = rng.uniform(10e-6, 40e-6, len(table))
    return StaticTable(table.source, table.pose, table.load, table.t, table.q, table.wrench, table.currents,
                       table.marker, table.xyz, table.line, (("u95", values),))


def _arrays(name: str) -> dict[str, np.ndarray]:
    hidden, plan, model, torque, form, weighting, u95 = CASES[name]
    seed = 11 + sorted(CASES).index(name)
    fit = identify_static(bundled_robot(), _table(hidden, plan, u95, seed), model=model, torque=TorqueSource(torque),
                          form=KinematicForm(form), weighting=Weighting(weighting))
    out = {"beta": fit.beta, "beta_cov": fit.beta_cov, "predicted": fit.predicted, "residuals": fit.residuals,
           "absolute_base": fit.absolute_base, "design": fit.design,
           "scalars": np.array([fit.rms, fit.max, fit.rss, np.nan if fit.noise_floor is None else fit.noise_floor,
                                np.nan if fit.expected_rss is None else fit.expected_rss, fit.condition_number,
                                fit.iterations, fit.n_params,
                                np.nan if fit.rss_whitened is None else fit.rss_whitened]),
           "parameters": np.array([[p.value, p.std] for p in fit.parameters])}
    if fit.noise_blocks is not None:
        out["noise_rows"] = np.concatenate([r for r, _ in fit.noise_blocks])
        out["noise_cov"] = np.concatenate([c.reshape(-1) for _, c in fit.noise_blocks])
    if fit.whitening is not None:
        out["whitened_design"] = fit.whiten(fit.design)
        out["unwhitened_design"] = fit.unwhiten(fit.design)
    return {f"{name}/{k}": np.asarray(v, dtype=float) for k, v in out.items()}


def test_write_golden_arrays():
    if not WRITE:
        pytest.skip("ELASTOCAL_WRITE_GOLDEN=1 writes the reference arrays")
    arrays: dict[str, np.ndarray] = {}
    for name in CASES:
        arrays.update(_arrays(name))
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(GOLDEN, **arrays)


@pytest.mark.parametrize("name", sorted(CASES))
def test_fit_arrays_are_todays(name):
    if WRITE:
        pytest.skip("writing the reference arrays")
    golden = np.load(GOLDEN)
    now = _arrays(name)
    expected = {k for k in golden.files if k.startswith(name + "/")}
    assert set(now) == expected, f"{name}: the fit returns other arrays than the reference"
    for key, value in now.items():
        problem = array_mismatch(value, golden[key], _tolerance(golden, key))
        assert problem is None, f"{key}: {problem}"


def _tolerance(golden, key: str) -> np.ndarray:
    """The golden rule's tolerance of one reference array (see the module's docstring)."""
    case, what = key.split("/")
    ref = golden[key]
    if what == "beta":
        return array_tolerance(ref, std=np.sqrt(np.diag(golden[f"{case}/beta_cov"])))
    if what == "parameters":
        tol = array_tolerance(ref)
        tol[:, 0] = array_tolerance(ref[:, 0], std=ref[:, 1])
        return tol
    if what == "beta_cov":
        sd = np.sqrt(np.diag(ref))
        return RELATIVE * np.outer(sd, sd)
    return array_tolerance(ref, floor=UNIT_FLOOR["m"] if what in METRES else 0.0)


def test_the_array_comparison_can_fail():
    """A tenth of a std on a fitted parameter fails, the last digits of a kernel do not."""
    golden = np.load(GOLDEN)
    key = "exact_current/beta"
    std = np.sqrt(np.diag(golden["exact_current/beta_cov"]))
    ref = golden[key]
    assert array_mismatch(ref + 1e-9 * np.abs(ref), ref, _tolerance(golden, key)) is None
    moved = ref.copy()
    moved[2] += 0.1 * std[2]
    assert "(2,)" in array_mismatch(moved, ref, _tolerance(golden, key))
    res = golden["exact_current/residuals"]
    assert array_mismatch(res * (1 + 1e-5), res, _tolerance(golden, "exact_current/residuals"))
