"""Unknown tool points (docs/absolute.md): markers off by tens of centimetres from robot.toml
are found by the tool-point pre-fit before the full model, which then ends where it ends
knowing the true markers; a marker is refused by name only when no placement explains its
readings."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path
from elastocal.formats.tables import write_static_table
from elastocal.identify.absolute import identify_absolute
from elastocal.identify.registration import PLAUSIBLE_RMS_M, register
from elastocal.identify.static import build_dataset
from elastocal.identify.toolpoints import PREFIT_RMS_M
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
MODEL = ("joint_stiffness", "kinematic_errors", "tracker_frame")
PLAN = StaticPlan(n_poses=12, n_loads=2, repeats=2)
#: how far [std] the fit through the pre-fit may end from the fit knowing the true markers: the two
#: start from robot.toml's markers 10-30 cm apart, so their models are linearised about other tool
#: points (their stds differ by ~0.2 %) and they end a few thousandths of a std apart (30 seeds: median
#: 0.002, max 0.010); a twentieth of a std is invisible to any use of the fit and still fails a pre-fit
#: that stops short (a marker left a millimetre off moves its correction by hundreds of std, each 2-3 um)
SAME_FIT_STD = 0.05


def _moved_markers(seed: int, low: float = 0.10, high: float = 0.30) -> dict[str, np.ndarray]:
    """Each marker's true offset from robot.toml: a random direction, low..high metres."""
    rng = np.random.default_rng(1000 + seed)
    out = {}
    for m in ROBOT.marker_names:
        d = rng.normal(size=3)
        out[m] = d / np.linalg.norm(d) * rng.uniform(low, high)
    return out


def _true_robot(offsets: dict[str, np.ndarray]):
    return replace(ROBOT, tool=replace(ROBOT.tool, flange_p_markers=tuple(
        (m, tuple(float(x) for x in np.array(p) + offsets[m])) for m, p in ROBOT.tool.flange_p_markers)))


def _case(seed: int):
    offsets = _moved_markers(seed)
    true = _true_robot(offsets)
    table = simulate_static(true, CellTruth().with_hidden("kinematic_errors"), seed=seed, plan=PLAN)
    return offsets, true, table


def _same_as_knowing_the_markers(seed: int) -> float:
    """max |fit - fit knowing the true markers| / std over every parameter (marker corrections
    counted from robot.toml's positions in both)."""
    offsets, true, table = _case(seed)
    nominal = register(ROBOT, build_dataset(table))
    assert nominal is None or nominal.rms > PREFIT_RMS_M        # robot.toml's markers do not explain the data
    fit = identify_absolute(ROBOT, table, model=MODEL)
    knowing = identify_absolute(true, table, model=MODEL)
    assert fit.tool_prefit is not None and knowing.tool_prefit is None
    assert fit.unidentifiable == knowing.unidentifiable
    assert fit.rms == pytest.approx(knowing.rms, rel=1e-4)       # both converged (rms std ~ rms / sqrt(2n))
    got = {p.name: p for p in fit.parameters}
    worst = 0.0
    for p in knowing.parameters:
        shift = offsets[p.name[3:]]["xyz".index(p.name[1])] if p.name.startswith(("dx_", "dy_", "dz_")) else 0.0
        worst = max(worst, abs(got[p.name].value - (p.value + shift)) / p.std)
    # the calibrated robot puts the markers where the fit knowing them does
    a, b = fit.calibrated_robot(ROBOT), knowing.calibrated_robot(true)
    q = ROBOT.lower + 0.3 * (ROBOT.upper - ROBOT.lower)
    np.testing.assert_allclose(a.positions(a.theta(q), ROBOT.marker_names), b.positions(b.theta(q), ROBOT.marker_names),
                               rtol=0, atol=1e-6)
    return worst


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_markers_off_by_tens_of_centimetres_are_found_before_the_full_model(seed):
    assert _same_as_knowing_the_markers(seed) < SAME_FIT_STD


@pytest.mark.heavy
@pytest.mark.acceptance
def test_found_over_many_seeds():
    """30 seeds, markers 10-30 cm off: every fit within SAME_FIT_STD of the fit knowing the markers."""
    worst = [_same_as_knowing_the_markers(seed) for seed in range(3, 33)]
    assert max(worst) < SAME_FIT_STD, worst


def _with_loose_marker(seed: int, marker: str = "R2"):
    """A table whose ``marker`` readings follow no point of the tool: each pose's reading is
    shifted by its own random 10-30 cm (a reflector on a cable, or another body's)."""
    offsets, true, table = _case(seed)
    rng = np.random.default_rng(seed)
    xyz = table.xyz.copy()
    for pose in np.unique(table.pose):
        rows = (table.pose == pose) & (table.marker == marker)
        d = rng.normal(size=3)
        xyz[rows] += d / np.linalg.norm(d) * rng.uniform(0.10, 0.30)
    return replace(table, xyz=xyz)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_marker_no_placement_explains_is_refused_by_name(seed):
    table = _with_loose_marker(seed)
    with pytest.raises(InputError, match=r"marker R2's readings fit no placement on the tool.*without it R1, R3 "
                                         r"fit to") as err:
        identify_absolute(ROBOT, table, model=MODEL)
    assert "\n" not in str(err.value)


def test_readings_of_no_tool_are_refused_naming_the_table():
    offsets, true, table = _case(0)
    rng = np.random.default_rng(5)
    scrambled = replace(table, xyz=table.xyz + rng.normal(0.0, 0.3, size=table.xyz.shape))
    with pytest.raises(InputError, match=r"no placement of the markers on the tool explains the readings"):
        identify_absolute(ROBOT, scrambled, model=MODEL)


def test_without_kinematic_errors_the_moved_markers_are_named():
    offsets, true, table = _case(1)
    with pytest.raises(InputError, match=r"tool-point pre-fit moves R1 \d.* cm.*add kinematic_errors"):
        identify_absolute(ROBOT, table, model=("joint_stiffness", "tracker_frame"))


def test_markers_a_centimetre_off_keep_the_old_start():
    """Within the registration's reach (rms below PREFIT_RMS_M) the full model starts from
    robot.toml's markers as before: nothing changes for a tool measured to a few mm."""
    true = _true_robot({m: v / np.linalg.norm(v) * 0.003 for m, v in _moved_markers(0).items()})
    table = simulate_static(true, CellTruth().with_hidden("kinematic_errors"), seed=0, plan=PLAN)
    assert register(ROBOT, build_dataset(table)).rms < PREFIT_RMS_M < PLAUSIBLE_RMS_M
    assert identify_absolute(ROBOT, table, model=MODEL).tool_prefit is None


def test_the_cli_fits_with_the_found_markers_and_names_a_loose_one(tmp_path, capsys):
    offsets, true, table = _case(2)
    write_static_table(tmp_path / "static.csv", table)
    robot = str(bundled_robot_path())
    assert main(["identify", "--robot", robot, "--static", str(tmp_path / "static.csv"), "--model", ",".join(MODEL),
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    found = out["tool_prefit"]["flange_p_markers"]
    for m, p in ROBOT.tool.flange_p_markers:           # within a few mm of the truth (the geometry absorbs the rest)
        assert np.linalg.norm(np.array(found[m]) - (np.array(p) + offsets[m])) < 0.005
    write_static_table(tmp_path / "loose.csv", _with_loose_marker(2))
    assert main(["identify", "--robot", robot, "--static", str(tmp_path / "loose.csv"), "--model", ",".join(MODEL),
                 "--json"]) == 2
    err = capsys.readouterr().err.strip()
    assert "marker R2's readings fit no placement" in err and "\n" not in err
