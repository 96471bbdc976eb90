"""Strict reading of the static and run tables: every malformed input gets one
line naming file, line and column."""

import csv
import io

import numpy as np
import pytest

from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.formats.tables import (
    format_run_table,
    format_static_table,
    parse_run_table,
    parse_static_table,
    read_static_table,
    run_table_from_arrays,
)
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
TABLE = simulate_static(ROBOT, CellTruth(), seed=11, plan=StaticPlan(n_poses=2, n_loads=2, repeats=2))
TEXT = format_static_table(TABLE)


def rows():
    return list(csv.reader(io.StringIO(TEXT)))


def to_text(r):
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(r)
    return out.getvalue()


def edit(line, column, value):
    """Set ``column`` on file line ``line`` (the header is line 1)."""
    r = rows()
    r[line - 1][r[0].index(column)] = value
    return to_text(r)


def parse(text):
    return parse_static_table(text, ROBOT, source="static.csv")


def test_valid_table_round_trips():
    again = parse(TEXT)
    np.testing.assert_array_equal(again.xyz, TABLE.xyz)
    np.testing.assert_array_equal(again.currents, TABLE.currents)
    assert list(again.marker) == list(TABLE.marker)
    assert len(again) == 2 * 3 * 2 * 3


def test_reads_from_file(tmp_path):
    path = tmp_path / "static.csv"
    path.write_text(TEXT)
    assert len(read_static_table(path, ROBOT)) == len(TABLE)


def test_missing_file_names_it(tmp_path):
    with pytest.raises(InputError, match=r"nope\.csv: cannot read"):
        read_static_table(tmp_path / "nope.csv", ROBOT)


def test_unknown_marker():
    with pytest.raises(InputError) as e:
        parse(edit(3, "marker", "R9"))
    assert str(e.value) == "static.csv, line 3, column marker: unknown marker 'R9'; the robot has R1, R2, R3"


def test_missing_unloaded_reference():
    r = rows()
    kept = [r[0]] + [row for row in r[1:] if not (row[0] == "2" and row[1] == "0")]
    with pytest.raises(InputError) as e:
        parse(to_text(kept))
    assert "pose 2 has no unloaded reference (load 0)" in str(e.value)
    assert str(e.value).startswith("static.csv, line ")
    assert "column load" in str(e.value)


def test_marker_without_reference():
    r = rows()
    kept = [r[0]] + [row for row in r[1:] if not (row[0] == "1" and row[1] == "0" and row[-4] == "R2")]
    with pytest.raises(InputError, match=r"column marker: marker R2 at pose 1 has no unloaded reference"):
        parse(to_text(kept))


def test_pose_with_one_load_state():
    r = rows()
    kept = [r[0]] + [row for row in r[1:] if not (row[0] == "2" and row[1] != "0")]
    with pytest.raises(InputError) as e:
        parse(to_text(kept))
    assert "pose 2 has only one load state" in str(e.value)
    assert "column load" in str(e.value)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "abc", ""])
def test_non_finite_or_missing_number(value):
    with pytest.raises(InputError) as e:
        parse(edit(5, "y", value))
    msg = str(e.value)
    assert msg.startswith("static.csv, line 5, column y: ")
    assert ("finite" in msg) or ("not a number" in msg) or ("empty value" in msg)


def test_degrees_where_radians_expected():
    r = rows()
    q2 = float(r[3][r[0].index("q2")])
    with pytest.raises(InputError) as e:
        parse(edit(4, "q2", str(float(np.degrees(q2)) + 20.0)))
    assert "static.csv, line 4, column q2:" in str(e.value)
    assert "degrees? angles in files are radians" in str(e.value)


def test_millimetres_where_metres_expected():
    r = rows()
    x = float(r[5][r[0].index("x")])
    with pytest.raises(InputError) as e:
        parse(edit(6, "x", repr(x * 1000.0 + 5000.0)))
    assert "static.csv, line 6, column x:" in str(e.value)
    assert "millimetres? positions are metres" in str(e.value)


def test_partial_wrench():
    with pytest.raises(InputError, match=r"line 8, column my: the wrench is partly empty"):
        parse(edit(8, "my", ""))


def test_missing_and_unknown_columns():
    r = rows()
    header = r[0]
    r2 = [[c for c, h in zip(row, header) if h != "i3"] for row in r]
    with pytest.raises(InputError, match=r"static.csv, line 1, column i3: missing column\(s\) i3"):
        parse(to_text(r2))
    r3 = [row + ["1"] for row in r]
    r3[0][-1] = "temperature"
    with pytest.raises(InputError, match=r"line 1: unknown column\(s\) temperature"):
        parse(to_text(r3))


def test_pose_changing_configuration():
    r = rows()
    q3 = float(r[6][r[0].index("q3")])
    with pytest.raises(InputError, match=r"line 7, column q3: pose \d changes its joint coordinates"):
        parse(edit(7, "q3", repr(q3 + 0.01)))


def test_ragged_row():
    r = rows()
    r[8] = r[8][:-1]
    with pytest.raises(InputError, match=r"static.csv, line 9: 24 fields, the header has 25"):
        parse(to_text(r))


# ---------------------------------------------------------------- run table
def run_text():
    n = 6
    q = np.tile([0.1, 0.2, -0.3, 0.0, 0.8, 0.0], (n, 1))
    q[:, 1] = np.linspace(0.1, 0.3, n)
    dq = np.zeros((n, 6))
    dq[:, 1] = 0.4                  # q2 moves 0.04 rad per 0.1 s
    t = run_table_from_arrays(run=["1"] * 3 + ["2"] * 3, direction=["UV"] * 3 + ["VU"] * 3, load=["0"] * n,
                              t=[0.0, 0.1, 0.2, 0.0, 0.1, 0.2], q=q, dq=dq, currents=np.ones((n, 6)),
                              marker=["R1"] * n, xyz=np.tile([1.0, 0.0, 1.5], (n, 1)))
    return format_run_table(t)


def test_run_table_round_trips():
    table = parse_run_table(run_text(), ROBOT, source="runs.csv")
    assert list(table.direction) == ["UV"] * 3 + ["VU"] * 3
    assert np.all(np.isnan(table.wrench))
    np.testing.assert_allclose(table.dq[:, 1], 0.4)


def run_edit(line, column, value):
    r = list(csv.reader(io.StringIO(run_text())))
    r[line - 1][r[0].index(column)] = value
    return to_text(r)


@pytest.mark.parametrize("line, column, value, message", [
    (2, "direction", "forward", "direction must be one of UV, VU, +, -"),
    (3, "dq2", "1.15", None),
    (3, "dq2", "25.0", "degrees per second"),
    (4, "t", "-1", "run 1: time goes backwards"),
    (2, "marker", "R7", "unknown marker 'R7'"),
    (2, "z", "1500.0", "millimetres"),
    (5, "q1", "nan", "not a finite number"),
    (6, "i4", "", "the current vector is partly empty"),
])
def test_bad_run_rows(line, column, value, message):
    text = run_edit(line, column, value)
    if message is None:
        parse_run_table(text, ROBOT, source="runs.csv")
        return
    with pytest.raises(InputError) as e:
        parse_run_table(text, ROBOT, source="runs.csv")
    assert str(e.value).startswith("runs.csv, line ")
    assert message in str(e.value)


def test_run_mixing_directions():
    r = list(csv.reader(io.StringIO(run_text())))
    r[2][r[0].index("direction")] = "VU"
    with pytest.raises(InputError, match=r"run 1 mixes directions UV, VU"):
        parse_run_table(to_text(r), ROBOT, source="runs.csv")
