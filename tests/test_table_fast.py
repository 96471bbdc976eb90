"""The static table read in whole columns is the table the per-row reader makes.

formats/tables.py reads a static table column by column when every row passes the
checks, and falls back to the per-row reader (which names the first bad line and column)
otherwise. Both are compared here on the same text, value for value, and the screening is
shown to send every bad row to the per-row reader.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.formats.tables import (
    STATIC_COLUMNS,
    STATIC_OPTIONAL_COLUMNS,
    StaticTable,
    _fast_static_table,
    _parse_static_rows,
    _Rows,
    format_static_table,
    parse_static_table,
)
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()


def _text(**changes) -> str:
    table = simulate_static(ROBOT, CellTruth(), seed=5, plan=StaticPlan(n_poses=4, n_loads=2, repeats=2))
    if changes.get("u95"):
        table = StaticTable(table.source, table.pose, table.load, table.t, table.q, table.wrench, table.currents,
                            table.marker, table.xyz, table.line,
                            (("u95", np.linspace(1e-5, 3e-5, len(table))), ("temperature_c", np.full(len(table), 20.5))))
    text = format_static_table(table)
    if changes.get("spaces"):        # cells with blanks around them, blank records between rows
        lines = text.splitlines()
        text = "\n".join([lines[0]] + [" " + ln.replace(",", " , ") + "\n,,," for ln in lines[1:]]) + "\n"
    return text


def _both(text: str, robot=ROBOT):
    rows = _Rows(text, "<t>", required=STATIC_COLUMNS, known=STATIC_COLUMNS + STATIC_OPTIONAL_COLUMNS)
    extra = [c for c in STATIC_OPTIONAL_COLUMNS if c in rows.index]
    return _fast_static_table(rows, robot, extra), _parse_static_rows(rows, robot, extra)


@pytest.mark.parametrize("changes", [{}, {"u95": True}, {"spaces": True}])
@pytest.mark.parametrize("robot", [ROBOT, None])
def test_whole_columns_equal_the_per_row_reader(changes, robot):
    fast, slow = _both(_text(**changes), robot)
    assert fast is not None, "a valid table takes the whole-column way"
    for field in ("pose", "load", "marker", "t", "q", "wrench", "currents", "xyz", "line"):
        a, b = getattr(fast, field), getattr(slow, field)
        assert a.dtype == b.dtype and a.shape == b.shape, field
        np.testing.assert_array_equal(a, b, err_msg=field)
    assert [k for k, _ in fast.extra] == [k for k, _ in slow.extra]
    for (_, a), (_, b) in zip(fast.extra, slow.extra):
        np.testing.assert_array_equal(a, b)


def _spoil(text: str, row: int, column: str, value: str) -> str:
    lines = text.splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(column)] = value
    lines[row] = ",".join(cells)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("column, value, message", [
    ("q2", "", "empty value"), ("q2", "abc", "not a number"), ("q3", "9.0", "outside the joint limits"),
    ("x", "1500.0", "millimetres"), ("t", "1e12", "not a plausible time"), ("fx", "", "partly empty"),
    ("i4", "1e5", "not a plausible motor current"), ("marker", "R9", "unknown marker"), ("mz", "inf", "finite"),
    ("u95", "0.5", "u95"), ("pose", "", "empty value"),
])
def test_a_bad_row_is_named_by_the_per_row_reader(column, value, message):
    text = _spoil(_text(u95=True), 7, column, value)
    rows = _Rows(text, "<t>", required=STATIC_COLUMNS, known=STATIC_COLUMNS + STATIC_OPTIONAL_COLUMNS)
    fast = _fast_static_table(rows, ROBOT, [c for c in STATIC_OPTIONAL_COLUMNS if c in rows.index])
    assert fast is None, "the screen must send the bad row to the per-row reader"
    with pytest.raises(InputError, match=message) as info:
        parse_static_table(text, ROBOT, source="<t>")
    assert info.value.row == 8, str(info.value)      # the header is line 1


@functools.cache
def _run_table_text() -> str:
    """The simulated run table's text, made once (the simulation is the costly part; read-only)."""
    from elastocal.formats.tables import format_run_table
    from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs

    return format_run_table(simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=2,
                                          friction=FrictionPlan(samples=40)))


def _run_text(drop: tuple[str, ...] = ()) -> str:
    lines = [ln.split(",") for ln in _run_table_text().splitlines()]
    keep = [i for i, c in enumerate(lines[0]) if c not in drop]
    return "\n".join(",".join(ln[i] for i in keep) for ln in lines) + "\n"


def _both_runs(text: str, robot=ROBOT):
    from elastocal.formats.tables import RUN_COLUMNS, _fast_run_table, _parse_run_rows

    rows = _Rows(text, "<r>", required=("run", "direction", "load", "t", "q1", "q2", "q3", "q4", "q5", "q6"),
                 known=RUN_COLUMNS)
    return _fast_run_table(rows, robot), _parse_run_rows(rows, robot)


@pytest.mark.parametrize("drop", [(), ("dq1", "dq2", "dq3", "dq4", "dq5", "dq6", "marker", "x", "y", "z")])
@pytest.mark.parametrize("robot", [ROBOT, None])
def test_run_table_whole_columns_equal_the_per_row_reader(drop, robot):
    fast, slow = _both_runs(_run_text(drop), robot)
    assert fast is not None
    for field in ("run", "direction", "load", "t", "q", "dq", "currents", "wrench", "marker", "xyz", "line"):
        a, b = getattr(fast, field), getattr(slow, field)
        assert a.dtype == b.dtype and a.shape == b.shape, field
        np.testing.assert_array_equal(a, b, err_msg=field)


@pytest.mark.parametrize("column, value, message", [
    ("direction", "UP", "direction must be one of"), ("t", "", "empty value"), ("dq2", "50", "too fast"),
    ("i1", "", "partly empty"), ("marker", "R9", "unknown marker"), ("x", "0.5", "partly empty"),
    ("q1", "7.5", "outside the joint limits"), ("run", "", "empty value"),
])
def test_a_bad_run_row_is_named_by_the_per_row_reader(column, value, message):
    from elastocal.formats.tables import parse_run_table

    row = 7
    text = _spoil(_run_text(), row, column, value)
    from elastocal.formats.tables import RUN_COLUMNS, _fast_run_table

    rows = _Rows(text, "<r>", required=("run", "direction", "load", "t"), known=RUN_COLUMNS)
    assert _fast_run_table(rows, ROBOT) is None
    with pytest.raises(InputError, match=message) as info:
        parse_run_table(text, ROBOT, source="<r>")
    assert info.value.row == row + 1, str(info.value)
