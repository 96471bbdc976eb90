"""The static fit's numbers are what they were before its fast paths (issue 15, part 1).

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

from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import identify_static
from elastocal.formats.tables import StaticTable
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

GOLDEN = pathlib.Path(__file__).parent / "data" / "golden" / "identify_arrays.npz"
WRITE = os.environ.get("ELASTOCAL_WRITE_GOLDEN") == "1"
REL = 1e-9
#: arrays in metres, and the rounding of a position of about 1 m [m] (tests/test_golden_json.py's TINY)
METRES = ("predicted", "residuals", "absolute_base")
TINY_M = 1e-15

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
    fit = identify_static(bundled_robot(), _table(hidden, plan, u95, seed), model=model, torque=torque, form=form,
                          weighting=weighting)
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
        ref = golden[key]
        assert value.shape == ref.shape, key
        both_nan = np.isnan(ref) & np.isnan(value)
        scale = np.maximum(np.abs(ref), 1e-300)
        # entries that are rounding noise next to the array's largest are compared absolutely;
        # so are positions and deflections in metres, whose last bit is that of a 1 m position
        floor = 1e-13 * float(np.nanmax(np.abs(ref), initial=0.0))
        if key.split("/")[1] in METRES:
            floor = max(floor, TINY_M)
        err = np.where(both_nan, 0.0, np.abs(value - ref))
        assert np.all((err <= REL * scale) | (err <= floor)), (
            f"{key}: max relative change {float(np.nanmax(err / scale)):.3g}")
