"""Where a table's noise level comes from, in the contract's order (docs/cli.md, "Absolute-only
tables"): repeated readings, else the readings' ``u95`` / ``sx, sy, sz`` columns, else a tracker
noise law named in cell.toml or robot.toml (cell.toml first), else none. Simulated absolute-only
tables of the bundled arm (seeded); every case checks the floor it gives, not only the label."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.formats.robot_toml import bundled_robot, parse_robot
from elastocal.formats.tables import read_static_table, write_static_table
from elastocal.identify.absolute import identify_absolute
from elastocal.identify.dataset import build_dataset
from elastocal.model.kinds import NoiseSource
from elastocal.model.tracker_noise import TrackerNoise
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
GEOMETRY = ("kinematic_errors", "tracker_frame")
SIGMA = CellTruth().tracker_noise_m           # the simulated tracker's noise per coordinate [m]
#: a law ten times the simulated tracker's noise: where it is used, the floor shows it
LOUD = TrackerNoise(10 * SIGMA, 0.0, 10 * SIGMA, 0.0, source="a loud law")
QUIET = TrackerNoise(SIGMA, 0.0, SIGMA, 0.0, source="the simulated tracker's law")


def unloaded(table):
    t = table.subset(table.load == "0")
    return dataclasses.replace(t, wrench=np.full_like(t.wrench, np.nan), currents=np.full_like(t.currents, np.nan))


def single(table):
    """One reading per pose and marker (the first): no repeats."""
    first = np.unique(np.char.add(np.char.add(table.pose, "/"), table.marker), return_index=True)[1]
    return table.subset(np.isin(np.arange(len(table)), first))


def with_columns(table, sigma: float):
    return dataclasses.replace(table, extra=tuple((c, np.full(len(table), sigma)) for c in ("sx", "sy", "sz")))


@pytest.fixture(scope="module")
def repeated():
    truth = CellTruth().with_hidden("kinematic_errors")
    return unloaded(simulate_static(ROBOT, truth, seed=11, plan=StaticPlan(n_poses=30, n_loads=1, repeats=3)))


def floor(table) -> float | None:
    return identify_absolute(ROBOT, table, model=GEOMETRY).noise_floor


def test_repeats_come_first(repeated):
    ds = build_dataset(dataclasses.replace(with_columns(repeated, 10 * SIGMA), tracker_noise=LOUD))
    assert ds.noise_source is NoiseSource.REPEATS
    assert 0.85 * SIGMA < ds.sigma_tracker < 1.15 * SIGMA          # 180 degrees of freedom: +-8 % is 1 std
    plain = floor(repeated)
    assert floor(dataclasses.replace(with_columns(repeated, 10 * SIGMA), tracker_noise=LOUD)) == \
        pytest.approx(plain, rel=1e-6)


def test_few_repeats_take_the_stated_laws_shape_at_the_repeats_level(repeated):
    few = repeated.subset(np.isin(repeated.pose, [str(p) for p in range(1, 5)]))
    loud, quiet = (build_dataset(dataclasses.replace(few, tracker_noise=law)) for law in (LOUD, QUIET))
    assert loud.noise_source is NoiseSource.REPEATS and "scaled to the repeats' level" in loud.tracker_noise.source
    # too few repeats for a law of their own: the stated law, scaled to what the repeats show
    np.testing.assert_allclose(loud.reading_cov, quiet.reading_cov, rtol=1e-9)
    assert floor(dataclasses.replace(few, tracker_noise=LOUD)) == pytest.approx(floor(few), rel=0.05)


def test_without_repeats_the_columns_come_before_the_law(repeated):
    one = single(repeated)
    stated = with_columns(one, SIGMA)
    assert build_dataset(dataclasses.replace(stated, tracker_noise=LOUD)).noise_source \
        is NoiseSource.UNCERTAINTY_COLUMNS
    by_columns = floor(stated)
    assert by_columns is not None
    assert floor(dataclasses.replace(stated, tracker_noise=LOUD)) == pytest.approx(by_columns, rel=1e-6)
    assert 1.8 < floor(with_columns(one, 2 * SIGMA)) / by_columns < 2.2       # the columns set it


def test_without_repeats_or_columns_the_law_sets_the_floor_else_none(repeated):
    one = single(repeated)
    ds = build_dataset(dataclasses.replace(one, tracker_noise=QUIET))
    assert ds.noise_source is NoiseSource.TRACKER_LAW and ds.sigma_tracker == pytest.approx(SIGMA, rel=1e-9)
    quiet, loud = floor(dataclasses.replace(one, tracker_noise=QUIET)), floor(dataclasses.replace(one, tracker_noise=LOUD))
    assert loud / quiet == pytest.approx(10.0, rel=1e-6)
    assert build_dataset(one).noise_source is NoiseSource.NONE and floor(one) is None


def robot_text(law_um: float) -> str:
    return ROBOT.to_toml() + (f"\n[tracker]\nnoise = {{ along = [{law_um}e-6, 0.0], across = [{law_um}e-6, 0.0], "
                              "k = 1 }\n")


def test_robot_toml_names_the_law_and_cell_toml_comes_first(repeated, tmp_path, capsys):
    robot = parse_robot(robot_text(10.0), source="robot.toml")
    assert robot.tracker_noise.along_m == pytest.approx(10e-6) and "robot.toml" in robot.tracker_noise.source
    again = parse_robot(robot.to_toml(), source="again.toml")
    assert again.tracker_noise.sigma_across(3.0) == pytest.approx(robot.tracker_noise.sigma_across(3.0), rel=1e-12)
    (tmp_path / "robot.toml").write_text(robot_text(10.0))
    write_static_table(tmp_path / "one.csv", single(repeated))
    assert read_static_table(tmp_path / "one.csv", robot).tracker_noise is robot.tracker_noise
    base = ["identify", "--robot", str(tmp_path / "robot.toml"), "--static", str(tmp_path / "one.csv"), "--json"]
    assert main(base) == 0
    by_robot = json.loads(capsys.readouterr().out)["noise_floor"]
    (tmp_path / "cell.toml").write_text(
        '[cell]\nname = "c"\nrobot = "hh150"\n[tracker]\nurl = "tracker+tcp://127.0.0.1:7000"\nmarkers = ["R1"]\n'
        'noise = { along = [100e-6, 0.0], across = [100e-6, 0.0], k = 1 }\n')
    assert main([*base, "--cell", str(tmp_path / "cell.toml")]) == 0
    by_cell = json.loads(capsys.readouterr().out)["noise_floor"]
    assert by_robot is not None and by_cell / by_robot == pytest.approx(10.0, rel=1e-6)


def test_a_bad_tracker_table_in_robot_toml_is_one_line():
    from elastocal.errors import InputError

    with pytest.raises(InputError, match=r"tracker\.sigma"):
        parse_robot(ROBOT.to_toml() + "\n[tracker]\nsigma = 1e-5\n", source="robot.toml")
    with pytest.raises(InputError, match=r"tracker\.noise\.across"):
        parse_robot(ROBOT.to_toml() + "\n[tracker]\nnoise = { along = [1e-5, 0.0] }\n", source="robot.toml")
