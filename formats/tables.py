"""The CSV tables of docs/formats.md §2 (static deflections) and §3 (runs).

Readers validate strictly and fail with one line naming file, line and column:
unknown marker, missing unloaded reference, a pose with one load state,
non-finite numbers, and values whose size betrays the wrong unit (degrees
where radians are expected, millimetres where metres are).

Why one module over 500 lines: this is the contract of both tables (docs/formats.md
§2-3) in one place: their columns, reading, the value checks that name file, line and
column, and writing; a change to a column is one change here.
"""

from __future__ import annotations

import csv
import io
import math
import operator
import pathlib
from dataclasses import dataclass, replace
from typing import Iterable, Iterator, Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.model.tracker_noise import TrackerNoise
from elastocal.formats.textfiles import read_text_file
from elastocal.model.robot import Robot



def joint_columns(prefix: str, n_joints: int) -> tuple[str, ...]:
    """``prefix1..prefixN``: the columns of one joint vector, base to tip (docs/formats.md
    "Columns follow N")."""
    return tuple(f"{prefix}{j}" for j in range(1, n_joints + 1))


#: the columns of the six-joint robot (the HH-150); other robots: :func:`joint_columns`
Q_COLS = joint_columns("q", 6)
DQ_COLS = joint_columns("dq", 6)
I_COLS = joint_columns("i", 6)
W_COLS = ("fx", "fy", "fz", "mx", "my", "mz")
XYZ_COLS = ("x", "y", "z")


def static_columns(n_joints: int = 6) -> tuple[str, ...]:
    """The static table's columns for a robot of ``n_joints`` joints."""
    return (("pose", "load", "t") + joint_columns("q", n_joints) + W_COLS + joint_columns("i", n_joints)
            + ("marker",) + XYZ_COLS)


def run_columns(n_joints: int = 6) -> tuple[str, ...]:
    """The run table's columns for a robot of ``n_joints`` joints."""
    return (("run", "direction", "load", "t") + joint_columns("q", n_joints) + joint_columns("dq", n_joints)
            + joint_columns("i", n_joints) + W_COLS + ("marker",) + XYZ_COLS)


STATIC_COLUMNS = static_columns(6)
#: optional columns of the static table (docs/formats.md §2): the tracker's per-point expanded
#: uncertainty U95 [m] (weights the fit) and the air it measured through [°C, hPa, %]
STATIC_OPTIONAL_COLUMNS = ("u95", "sx", "sy", "sz", "temperature_c", "pressure_hpa", "humidity_pct")
#: the reading's uncertainty: expanded (k = 2) or standard per axis [m]
UNCERTAINTY_COLUMNS = ("u95", "sx", "sy", "sz")
RUN_COLUMNS = run_columns(6)


def static_omissible(n_joints: int) -> tuple[str, ...]:
    """The columns an absolute-only table (docs/formats.md "Absolute-only tables") may leave out of
    its header: no load column is load 0 everywhere; no time, wrench or currents are empty ones."""
    return ("load", "t") + W_COLS + joint_columns("i", n_joints)

#: a marker coordinate beyond this is taken as millimetres [m]
MAX_POSITION_M = 20.0
#: a joint speed beyond this is taken as degrees per second [rad/s]
MAX_SPEED_RAD_S = 10.0
#: a current beyond this is not a motor current in amperes [A]
MAX_CURRENT_A = 2000.0
#: a time beyond this (317 years from its origin) is not seconds: milliseconds or nanoseconds of an epoch [s]
MAX_TIME_S = 1e10
#: a force or moment beyond this is not newtons or newton-metres [N, N·m]
MAX_WRENCH = 1e6
#: joint speeds checked against the motion of q over t (run tables): in each run, a joint that travels
#: at least MIN_TRAVEL_RAD has the integral of its dq over t compared with its travel; a ratio outside
#: SPEED_RATIO_OK is refused, as degrees per second when in DEGREE_RATIO (180/pi = 57.3)
MIN_TRAVEL_RAD = 0.01
SPEED_RATIO_OK = (1 / 3, 3.0)
DEGREE_RATIO = (30.0, 120.0)
DIRECTIONS = ("UV", "VU", "+", "-")


@dataclass(frozen=True, eq=False)
class StaticTable:
    """Rows of a static deflection table (docs/formats.md §2) as arrays."""

    source: str
    pose: np.ndarray      # (n,) str
    load: np.ndarray      # (n,) str; "0" is the unloaded reference
    t: np.ndarray         # (n,) s, NaN when empty
    q: np.ndarray         # (n, N) rad, m for a prismatic joint
    wrench: np.ndarray    # (n, 6) N, N·m; NaN when unknown
    currents: np.ndarray  # (n, N) A; NaN when empty
    marker: np.ndarray    # (n,) str
    xyz: np.ndarray       # (n, 3) m
    line: np.ndarray      # (n,) line number in the file (header = 1)
    #: optional columns present (STATIC_OPTIONAL_COLUMNS): name -> (n,) values, NaN when empty
    extra: tuple[tuple[str, np.ndarray], ...] = ()
    #: the tracker's noise law the cell states (cell.toml ``[tracker] noise``), if it does
    #: (model/tracker_noise.py): for weights, floor and outliers where the repeats cannot say
    tracker_noise: TrackerNoise | None = None

    def __len__(self) -> int:
        return len(self.pose)

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    @property
    def absolute_only(self) -> bool:
        """Every row is the unloaded state (load 0): a geometric calibration table of absolute
        positions (docs/formats.md "Absolute-only tables"), no deflections."""
        return bool(np.all(self.load == "0"))

    def optional(self, name: str) -> np.ndarray | None:
        """The optional column ``name`` (NaN where empty), None when the table has none."""
        return dict(self.extra).get(name)

    @property
    def has_currents(self) -> bool:
        return bool(len(self)) and bool(np.all(np.isfinite(self.currents)))

    @property
    def has_wrench(self) -> bool:
        loaded = self.load != "0"
        return bool(np.any(loaded)) and bool(np.all(np.isfinite(self.wrench[loaded])))

    @property
    def has_time(self) -> bool:
        return bool(len(self)) and bool(np.all(np.isfinite(self.t)))

    def subset(self, mask: np.ndarray) -> "StaticTable":
        return StaticTable(self.source, self.pose[mask], self.load[mask], self.t[mask], self.q[mask],
                           self.wrench[mask], self.currents[mask], self.marker[mask], self.xyz[mask],
                           self.line[mask], tuple((k, v[mask]) for k, v in self.extra), self.tracker_noise)


@dataclass(frozen=True, eq=False)
class RunTable:
    """Samples of slow motions (docs/formats.md §3) as arrays."""

    source: str
    run: np.ndarray        # (n,) str
    direction: np.ndarray  # (n,) str: UV, VU, + or -
    load: np.ndarray       # (n,) str
    t: np.ndarray          # (n,) s
    q: np.ndarray          # (n, N) rad (m for a prismatic joint)
    dq: np.ndarray         # (n, N) rad/s (m/s), NaN when empty
    currents: np.ndarray   # (n, N) A, NaN when empty
    wrench: np.ndarray     # (n, 6), NaN when empty
    marker: np.ndarray     # (n,) str, "" when empty
    xyz: np.ndarray        # (n, 3) m, NaN when empty
    line: np.ndarray       # (n,)

    def __len__(self) -> int:
        return len(self.run)

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    def subset(self, mask: np.ndarray) -> "RunTable":
        return RunTable(self.source, self.run[mask], self.direction[mask], self.load[mask], self.t[mask],
                        self.q[mask], self.dq[mask], self.currents[mask], self.wrench[mask],
                        self.marker[mask], self.xyz[mask], self.line[mask])


# ------------------------------------------------------------------ reading
def csv_records(text: str, source: str) -> Iterator[tuple[int, list[str]]]:
    """(line, fields) of each CSV record of ``text``, header first (line 1).

    The csv module's own errors (a field over its size limit of 131,072
    characters, a NUL byte, a quote left open at the end) become one
    :class:`InputError` naming the file and the line."""
    reader = csv.reader(io.StringIO(text))
    lineno = 1
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            line = max(reader.line_num, lineno)
            reason = str(exc)
            if "field larger than field limit" in reason:
                reason = (f"a field longer than {csv.field_size_limit():,} characters; not a table of numbers "
                          "(an unclosed quote?)")
            raise InputError(f"not a readable CSV record: {reason}", source=source, row=line) from None
        yield lineno, row
        lineno = reader.line_num + 1


def check_header(header: list[str], source: str) -> None:
    """Refuse a header that names one column twice (the last one would silently win)."""
    seen: set[str] = set()
    for name in header:
        if name in seen:
            raise InputError(f"column {name} appears twice in the header; each column once",
                             source=source, row=1, column=name)
        seen.add(name)


def table_joints(header: Iterable[str], robot: Robot | None, source: str) -> int:
    """N of a table: the robot's, when given, and the header's ``q1..qN`` must match it; else the
    header's. A mismatch is refused in one line naming both (docs/formats.md "Columns follow N")."""
    import re

    numbers = sorted(int(m.group(1)) for h in header if (m := re.fullmatch(r"q([1-9][0-9]*)", h.strip())))
    n = robot.n_joints if robot is not None else (numbers[-1] if numbers else 6)
    if numbers and numbers != list(range(1, n + 1)):
        have = ",".join(f"q{j}" for j in numbers) if len(numbers) < 4 else f"q1..q{numbers[-1]}"
        want = f"{n} joints (q1..q{n})"
        whose = f"the robot {robot.name!r} has {want}" if robot is not None else f"expected {want}"
        missing = [j for j in range(1, n + 1) if j not in numbers]
        column = f"q{missing[0]}" if missing else f"q{n + 1}"
        raise InputError(f"the table's joint columns are {have}; {whose}", source=source, row=1, column=column)
    return n


class _Rows:
    """CSV rows with the helpers that name file, line and column in errors."""

    def __init__(self, text: str, source: str, required, known, robot: Robot | None = None) -> None:
        """``required`` and ``known``: the columns, or functions of the table's N that give them."""
        self.source = source
        reader = csv_records(text, source)
        try:
            _, header = next(reader)
        except StopIteration:
            raise InputError("the file is empty", source=source) from None
        self.header = [h.strip() for h in header]
        check_header(self.header, source)
        self.n_joints = table_joints(self.header, robot, source)
        self.q_cols, self.dq_cols, self.i_cols = (joint_columns(p, self.n_joints) for p in ("q", "dq", "i"))
        required = required(self.n_joints) if callable(required) else required
        known = known(self.n_joints) if callable(known) else known
        missing = [c for c in required if c not in self.header]
        if missing:
            raise InputError(f"missing column(s) {', '.join(missing)}", source=source, row=1)
        unknown = [c for c in self.header if c not in known]
        if unknown:
            raise InputError(f"unknown column(s) {', '.join(unknown)}", source=source, row=1)
        self.index = {c: i for i, c in enumerate(self.header)}
        self.rows: list[tuple[int, list[str]]] = []
        width = len(self.header)
        for lineno, row in reader:
            cells = list(map(str.strip, row))
            if not any(cells):          # a blank record (no fields, or only blanks)
                continue
            if len(row) != width:
                raise InputError(f"{len(row)} fields, the header has {width}", source=source, row=lineno)
            self.rows.append((lineno, cells))
        if not self.rows:
            raise InputError("the table has no rows", source=source)

    def columns(self) -> dict[str, tuple[str, ...]]:
        """Each column's cells, top to bottom (one pass over the rows)."""
        cols = list(zip(*(cells for _, cells in self.rows)))
        return {c: cols[i] for c, i in self.index.items()}

    def check_groups(self, groups: Iterable[tuple[tuple[str, ...], str]]) -> None:
        """Columns that go together (a vector) are all in the header or none is."""
        for cols, what in groups:
            present = [c in self.index for c in cols]
            if any(present) and not all(present):
                missing = [c for c, p in zip(cols, present) if not p]
                raise InputError(f"missing column(s) {', '.join(missing)}: {what} needs all of {','.join(cols)} "
                                 "(or none of them)", source=self.source, row=1, column=missing[0])

    def text(self, lineno: int, row: list[str], col: str, *, required: bool = True) -> str:
        if col not in self.index:
            return ""
        value = row[self.index[col]]
        if required and not value:
            raise InputError("empty value", source=self.source, row=lineno, column=col)
        return value

    def number(self, lineno: int, row: list[str], col: str, *, required: bool = True) -> float:
        value = self.text(lineno, row, col, required=required)
        if not value:
            return math.nan
        try:
            x = float(value)
        except ValueError:
            raise InputError(f"not a number: {value!r}", source=self.source, row=lineno, column=col) from None
        if not math.isfinite(x):
            raise InputError(f"not a finite number: {value!r}", source=self.source, row=lineno, column=col)
        return x

    def group(self, lineno: int, row: list[str], cols: tuple[str, ...], what: str) -> list[float]:
        """All of ``cols`` or none of them."""
        values = [self.number(lineno, row, c, required=False) for c in cols]
        present = [not math.isnan(v) for v in values]
        if any(present) and not all(present):
            col = cols[present.index(False)]
            raise InputError(f"{what} is partly empty; give all of {','.join(cols)} or none",
                             source=self.source, row=lineno, column=col)
        return values


def _read_text(path: str | pathlib.Path) -> tuple[str, str]:
    path = pathlib.Path(path)
    return read_text_file(path), str(path)


def _check_joint_units(source: str, lineno: int, q: list[float], robot: Robot | None) -> None:
    for j, value in enumerate(q):
        col = f"q{j + 1}"
        if robot is not None:
            lo, hi = robot.joints[j].lower, robot.joints[j].upper
            margin = 1e-3
            if not lo - margin <= value <= hi + margin:
                unit, hint = robot.joints[j].unit, ""
                if unit == "m" and lo <= value / 1000.0 <= hi:
                    hint = "; millimetres? a prismatic joint's q is in metres"
                elif unit != "m" and lo <= math.radians(value) <= hi and abs(value) > 2 * math.pi:
                    hint = "; degrees? angles in files are radians"
                raise InputError(f"{value} {unit} is outside the joint limits [{lo:.4g}, {hi:.4g}]{hint}",
                                 source=source, row=lineno, column=col)
        elif abs(value) > 2 * math.pi:
            raise InputError(f"{value} is larger than 2*pi; degrees? angles in files are radians",
                             source=source, row=lineno, column=col)


def _check_position_units(source: str, lineno: int, xyz: list[float]) -> None:
    for col, value in zip(XYZ_COLS, xyz):
        if abs(value) > MAX_POSITION_M:
            raise InputError(f"{value} m is more than {MAX_POSITION_M:g} m from the base; millimetres? "
                             "positions are metres", source=source, row=lineno, column=col)


def _check_time(source: str, lineno: int, t: float) -> None:
    if abs(t) > MAX_TIME_S:
        raise InputError(f"{t:g} s is not a plausible time (more than {MAX_TIME_S:g} s from its origin); "
                         "milliseconds or nanoseconds? times are seconds", source=source, row=lineno, column="t")


def _check_wrench(source: str, lineno: int, wrench: list[float]) -> None:
    for col, value in zip(W_COLS, wrench):
        if abs(value) > MAX_WRENCH:
            unit = "N" if col.startswith("f") else "N*m"
            raise InputError(f"{value:g} {unit} is not a plausible load; forces are N, moments N*m",
                             source=source, row=lineno, column=col)


def _check_currents(source: str, lineno: int, currents: list[float]) -> None:
    for j, value in enumerate(currents, start=1):
        col = f"i{j}"
        if abs(value) > MAX_CURRENT_A:
            raise InputError(f"{value} A is not a plausible motor current; currents are amperes",
                             source=source, row=lineno, column=col)


def _numbers(cells: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """The cells of a column as numbers (NaN where empty) and where they are empty, or None
    when a cell is not a finite number (``float`` reads each cell, as the per-row reader does)."""
    empty = np.fromiter(map(operator.not_, cells), dtype=bool, count=len(cells))
    try:
        if empty.any():
            values = np.full(len(cells), math.nan)
            values[~empty] = np.array([c for c in cells if c], dtype=float)
        else:
            values = np.array(cells, dtype=float)
    except ValueError:
        return None
    if not np.all(np.isfinite(values[~empty])):
        return None
    return values, empty


def _fast_static_table(rows: _Rows, robot: Robot | None, extra_cols: list[str]) -> StaticTable | None:
    """The static table from its columns in whole-column operations (no Python work per row),
    or None when any row may fail a check of the per-row reader: that reader then runs and names
    the first bad row exactly as it always did. Every check of :func:`_parse_static_rows` is
    screened here with the same comparisons, so what this returns is what that returns."""
    cols = rows.columns()
    Q_COLS, I_COLS = rows.q_cols, rows.i_cols
    n = len(rows.rows)
    text = {}
    for c in ("pose", "load", "marker"):
        text[c] = np.array(cols[c] if c in cols else ("0",) * n, dtype=str)
        if not np.all(text[c] != ""):
            return None
    numbers = {}
    for c in ("t", *Q_COLS, *W_COLS, *I_COLS, *XYZ_COLS, *extra_cols):
        got = _numbers(cols[c] if c in cols else ("",) * n)
        if got is None:
            return None
        numbers[c] = got
    for required in (*Q_COLS, *XYZ_COLS):
        if numbers[required][1].any():
            return None
    for group in (W_COLS, I_COLS):            # all of a vector or none of it, row by row
        empty = np.column_stack([numbers[c][1] for c in group])
        if np.any(empty.any(axis=1) & ~empty.all(axis=1)):
            return None

    def values(group: tuple[str, ...]) -> np.ndarray:
        return np.column_stack([numbers[c][0] for c in group]).reshape(n, len(group))

    t, q, w, cur, xyz = numbers["t"][0], values(Q_COLS), values(W_COLS), values(I_COLS), values(XYZ_COLS)
    with np.errstate(invalid="ignore"):
        if np.any(np.abs(t) > MAX_TIME_S) or np.any(np.abs(w) > MAX_WRENCH) or np.any(np.abs(cur) > MAX_CURRENT_A):
            return None
        if np.any(np.abs(xyz) > MAX_POSITION_M):
            return None
        if not _joints_within(q, robot):
            return None
        if robot is not None and not np.all(np.isin(text["marker"], np.array(robot.marker_names, dtype=str))):
            return None
        for c in (c for c in extra_cols if c in UNCERTAINTY_COLUMNS):
            u = numbers[c][0]
            if not np.all(np.isnan(u) | ((0 <= u) & (u < 0.01))):
                return None
    line = np.fromiter((lineno for lineno, _ in rows.rows), dtype=int, count=n)
    return StaticTable(rows.source, text["pose"], text["load"], t, q, w, cur, text["marker"], xyz, line,
                       tuple((c, numbers[c][0]) for c in extra_cols))


def parse_static_table(text: str, robot: Robot | None = None, *, source: str = "<static.csv>") -> StaticTable:
    """Read and validate a static table (docs/formats.md §2): in whole-column operations when
    every row passes the checks (the usual case), else row by row to the first bad one."""
    rows = _Rows(text, source, required=lambda n: tuple(c for c in static_columns(n) if c not in static_omissible(n)),
                 known=lambda n: static_columns(n) + STATIC_OPTIONAL_COLUMNS, robot=robot)
    rows.check_groups([(W_COLS, "the wrench"), (rows.i_cols, "the current vector"),
                       (("sx", "sy", "sz"), "a per-axis uncertainty")])
    if "u95" in rows.index and "sx" in rows.index:
        raise InputError("give u95 or sx,sy,sz, not both: each is the reading's uncertainty", source=source,
                         row=1, column="sx")
    extra_cols = [c for c in STATIC_OPTIONAL_COLUMNS if c in rows.index]
    table = _fast_static_table(rows, robot, extra_cols)
    if table is None:
        table = _parse_static_rows(rows, robot, extra_cols)
    _check_static_structure(table)
    if robot is not None and robot.tracker_noise is not None:     # robot.toml's law; a cell.toml's replaces it
        table = replace(table, tracker_noise=robot.tracker_noise)
    return table


def _parse_static_rows(rows: _Rows, robot: Robot | None, extra_cols: list[str]) -> StaticTable:
    """The per-row reader: the first row that fails a check raises, naming its line and column."""
    source = rows.source
    Q_COLS, I_COLS = rows.q_cols, rows.i_cols
    extra: dict[str, list[float]] = {c: [] for c in extra_cols}
    markers = set(robot.marker_names) if robot is not None else None
    pose, load, t, q, w, cur, marker, xyz, line = [], [], [], [], [], [], [], [], []
    for lineno, row in rows.rows:
        pose.append(rows.text(lineno, row, "pose"))
        load.append(rows.text(lineno, row, "load"))
        tv = rows.number(lineno, row, "t", required=False)
        _check_time(rows.source, lineno, tv)
        t.append(tv)
        qv = [rows.number(lineno, row, c) for c in Q_COLS]
        _check_joint_units(rows.source, lineno, qv, robot)
        q.append(qv)
        wv = rows.group(lineno, row, W_COLS, "the wrench")
        _check_wrench(rows.source, lineno, wv)
        w.append(wv)
        iv = rows.group(lineno, row, I_COLS, "the current vector")
        _check_currents(rows.source, lineno, [v for v in iv if not math.isnan(v)])
        cur.append(iv)
        m = rows.text(lineno, row, "marker")
        if markers is not None and m not in markers:
            raise InputError(f"unknown marker {m!r}; the robot has {', '.join(sorted(markers))}",
                             source=source, row=lineno, column="marker")
        marker.append(m)
        pv = [rows.number(lineno, row, c) for c in XYZ_COLS]
        _check_position_units(rows.source, lineno, pv)
        xyz.append(pv)
        line.append(lineno)
        for c in extra_cols:
            v = rows.number(lineno, row, c, required=False)
            if c in UNCERTAINTY_COLUMNS and not (math.isnan(v) or 0 <= v < 0.01):
                raise InputError(f"{c} {v:g} must be >= 0 and below 0.01 m (metres, not millimetres)",
                                 source=source, row=lineno, column=c)
            extra[c].append(v)
    table = StaticTable(source, np.array(pose, dtype=str), np.array(load, dtype=str), np.array(t, dtype=float),
                        np.array(q, dtype=float), np.array(w, dtype=float), np.array(cur, dtype=float),
                        np.array(marker, dtype=str), np.array(xyz, dtype=float), np.array(line, dtype=int),
                        tuple((c, np.array(extra[c], dtype=float)) for c in extra_cols))
    return table


def _static_structure_holds(table: StaticTable) -> bool:
    """Whether :func:`_check_static_structure` finds nothing, in whole-column operations:
    rows grouped by pose, (pose, load) and (pose, marker, load) with ``np.unique``."""
    if len(table) == 0:
        return True
    _, first_of_pose, pose = np.unique(table.pose, return_index=True, return_inverse=True)
    pose = pose.reshape(-1)
    _, load = np.unique(table.load, return_inverse=True)
    _, marker = np.unique(table.marker, return_inverse=True)
    load, marker = load.reshape(-1), marker.reshape(-1)
    n_pose, n_load, n_marker = int(pose.max()) + 1, int(load.max()) + 1, int(marker.max()) + 1
    if not np.all(np.bincount(pose[table.load == "0"], minlength=n_pose) > 0):
        return False                                 # a pose without its unloaded reference
    pose_load = np.unique(pose * n_load + load)
    loads_of_pose = np.bincount(pose_load // n_load, minlength=n_pose)
    if np.any(loads_of_pose < 2) and not table.absolute_only:
        return False                                 # a pose with one load state
    if np.any(np.abs(table.q - table.q[first_of_pose[pose]]) > 1e-6):
        return False                                 # a pose that changes its configuration
    pose_marker = np.unique(pose * n_marker + marker)
    triples = np.unique((pose * n_marker + marker) * n_load + load)
    if len(triples) != int(np.sum(loads_of_pose[pose_marker // n_marker])):
        return False                                 # a marker without a reading under one of its pose's loads
    _, first_of_state, state = np.unique(pose * n_load + load, return_index=True, return_inverse=True)
    w = table.wrench
    with np.errstate(invalid="ignore"):
        return not np.any(np.abs(w - w[first_of_state[state.reshape(-1)]]) > 1e-9)


def _check_static_structure(table: StaticTable) -> None:
    """Every pose has an unloaded reference and at least one load state, for each
    marker; one configuration per pose; the wrench of the reference is zero or empty."""
    if _static_structure_holds(table):
        return
    src = table.source
    for p in dict.fromkeys(table.pose):
        rows = table.pose == p
        loads = set(table.load[rows])
        first = int(table.line[rows][0])
        if "0" not in loads:
            raise InputError(f"pose {p} has no unloaded reference (load 0)", source=src, row=first, column="load")
        if len(loads) < 2 and not table.absolute_only:
            raise InputError(f"pose {p} has only one load state; a deflection needs load 0 and a loaded state "
                             "(or a table without loads: every row load 0, a geometric calibration table)",
                             source=src, row=first, column="load")
        q = table.q[rows]
        bad = np.flatnonzero(np.any(np.abs(q - q[0]) > 1e-6, axis=1))
        if bad.size:
            lineno = int(table.line[rows][bad[0]])
            col = f"q{1 + int(np.argmax(np.abs(q[bad[0]] - q[0]) > 1e-6))}"
            raise InputError(f"pose {p} changes its joint coordinates between rows; one pose, one configuration",
                             source=src, row=lineno, column=col)
        for m in dict.fromkeys(table.marker[rows]):
            mm = rows & (table.marker == m)
            mloads = set(table.load[mm])
            if "0" not in mloads:
                raise InputError(f"marker {m} at pose {p} has no unloaded reference (load 0)",
                                 source=src, row=int(table.line[mm][0]), column="marker")
            for ld in sorted(set(table.load[rows]) - mloads):
                raise InputError(f"marker {m} at pose {p} has no reading under load {ld}",
                                 source=src, row=int(table.line[mm][0]), column="marker")
        for ld in loads:
            rl = rows & (table.load == ld)
            w = table.wrench[rl]
            if np.any(np.isfinite(w)) and np.any(np.abs(w - w[0]) > 1e-9):
                lineno = int(table.line[rl][int(np.argmax(np.any(np.abs(w - w[0]) > 1e-9, axis=1)))])
                raise InputError(f"pose {p} load {ld}: the wrench changes between readings of one load state",
                                 source=src, row=lineno, column="fx")


def read_static_table(path: str | pathlib.Path, robot: Robot | None = None) -> StaticTable:
    """Read and validate a static deflection table."""
    text, source = _read_text(path)
    return parse_static_table(text, robot, source=source)


def _joints_within(q: np.ndarray, robot: Robot | None) -> bool:
    """Whether every angle of ``q`` (n, N) passes :func:`_check_joint_units`."""
    if robot is None:
        return not np.any(np.abs(q) > 2 * math.pi)
    lo = np.array([j.lower for j in robot.joints]) - 1e-3
    hi = np.array([j.upper for j in robot.joints]) + 1e-3
    return bool(np.all((lo <= q) & (q <= hi)))


def _fast_run_table(rows: _Rows, robot: Robot | None) -> RunTable | None:
    """The run table in whole-column operations, or None when any row may fail a check of
    :func:`_parse_run_rows` (which then names the first bad row), as for the static table."""
    cols = rows.columns()
    Q_COLS, DQ_COLS, I_COLS = rows.q_cols, rows.dq_cols, rows.i_cols
    n = len(rows.rows)
    text = {}
    for c in ("run", "direction", "load", "marker"):
        text[c] = np.array(cols[c], dtype=str) if c in cols else np.full(n, "", dtype=str)
    if not all(np.all(text[c] != "") for c in ("run", "direction", "load")):
        return None
    if not np.all(np.isin(text["direction"], np.array(DIRECTIONS, dtype=str))):
        return None
    numbers = {}
    for c in ("t", *Q_COLS, *DQ_COLS, *I_COLS, *W_COLS, *XYZ_COLS):
        if c not in cols:
            numbers[c] = (np.full(n, math.nan), np.ones(n, dtype=bool))
            continue
        got = _numbers(cols[c])
        if got is None:
            return None
        numbers[c] = got
    if any(numbers[c][1].any() for c in ("t", *Q_COLS)):
        return None
    for group in (DQ_COLS, I_COLS, W_COLS, XYZ_COLS):     # all of a vector or none of it, row by row
        empty = np.column_stack([numbers[c][1] for c in group])
        if np.any(empty.any(axis=1) & ~empty.all(axis=1)):
            return None

    def values(group: tuple[str, ...]) -> np.ndarray:
        return np.column_stack([numbers[c][0] for c in group]).reshape(n, len(group))

    t, q, dq, cur, w, xyz = (numbers["t"][0], values(Q_COLS), values(DQ_COLS), values(I_COLS), values(W_COLS),
                             values(XYZ_COLS))
    named = text["marker"] != ""
    with np.errstate(invalid="ignore"):
        if np.any(np.abs(t) > MAX_TIME_S) or not _joints_within(q, robot):
            return None
        if np.any(np.abs(dq) > MAX_SPEED_RAD_S) or np.any(np.abs(cur) > MAX_CURRENT_A):
            return None
        if np.any(np.abs(w) > MAX_WRENCH) or np.any(named[:, None] & (np.abs(xyz) > MAX_POSITION_M)):
            return None
    if np.any(named == np.isnan(xyz[:, 0])):       # a marker without a position, or a position without one
        return None
    if robot is not None and not np.all(np.isin(text["marker"][named], np.array(robot.marker_names, dtype=str))):
        return None
    line = np.fromiter((lineno for lineno, _ in rows.rows), dtype=int, count=n)
    return RunTable(rows.source, text["run"], text["direction"], text["load"], t, q, dq, cur, w, text["marker"],
                    xyz, line)


def parse_run_table(text: str, robot: Robot | None = None, *, source: str = "<runs.csv>") -> RunTable:
    """Read and validate a run table (docs/formats.md §3): in whole-column operations when every
    row passes the checks, else row by row to the first bad one; then the checks per run."""
    rows = _Rows(text, source, required=lambda n: ("run", "direction", "load", "t") + joint_columns("q", n),
                 known=run_columns, robot=robot)
    rows.check_groups([(rows.dq_cols, "the joint speed vector"), (rows.i_cols, "the current vector"),
                       (W_COLS, "the wrench"),
                       (("marker",) + XYZ_COLS, "a followed marker")])
    table = _fast_run_table(rows, robot)
    if table is None:
        table = _parse_run_rows(rows, robot)
    for r in dict.fromkeys(table.run):
        rr = table.run == r
        dirs = set(table.direction[rr])
        if len(dirs) != 1:
            raise InputError(f"run {r} mixes directions {', '.join(sorted(dirs))}; one run, one direction",
                             source=source, row=int(table.line[rr][0]), column="direction")
        tt = table.t[rr]
        back = np.flatnonzero(np.diff(tt) < 0)
        if back.size:
            raise InputError(f"run {r}: time goes backwards", source=source,
                             row=int(table.line[rr][back[0] + 1]), column="t")
    _check_speeds_against_motion(table)
    return table


def _parse_run_rows(rows: _Rows, robot: Robot | None) -> RunTable:
    """The per-row reader of run tables: the first row that fails a check raises, naming its line."""
    source = rows.source
    Q_COLS, DQ_COLS, I_COLS = rows.q_cols, rows.dq_cols, rows.i_cols
    markers = set(robot.marker_names) if robot is not None else None
    run, direction, load, t, q, dq, cur, w, marker, xyz, line = ([] for _ in range(11))
    for lineno, row in rows.rows:
        run.append(rows.text(lineno, row, "run"))
        d = rows.text(lineno, row, "direction")
        if d not in DIRECTIONS:
            raise InputError(f"direction must be one of {', '.join(DIRECTIONS)}, got {d!r}",
                             source=source, row=lineno, column="direction")
        direction.append(d)
        load.append(rows.text(lineno, row, "load"))
        tv = rows.number(lineno, row, "t")
        _check_time(rows.source, lineno, tv)
        t.append(tv)
        qv = [rows.number(lineno, row, c) for c in Q_COLS]
        _check_joint_units(rows.source, lineno, qv, robot)
        q.append(qv)
        dqv = rows.group(lineno, row, DQ_COLS, "the joint speed vector")
        for col, v in zip(DQ_COLS, dqv):
            if abs(v) > MAX_SPEED_RAD_S:
                raise InputError(f"{v} rad/s is too fast for a calibration run; degrees per second? "
                                 "speeds are rad/s", source=source, row=lineno, column=col)
        dq.append(dqv)
        iv = rows.group(lineno, row, I_COLS, "the current vector")
        _check_currents(rows.source, lineno, [v for v in iv if not math.isnan(v)])
        cur.append(iv)
        wv = rows.group(lineno, row, W_COLS, "the wrench")
        _check_wrench(rows.source, lineno, wv)
        w.append(wv)
        m = rows.text(lineno, row, "marker", required=False)
        pv = rows.group(lineno, row, XYZ_COLS, "the marker position")
        if m and markers is not None and m not in markers:
            raise InputError(f"unknown marker {m!r}; the robot has {', '.join(sorted(markers))}",
                             source=source, row=lineno, column="marker")
        if m and math.isnan(pv[0]):
            raise InputError(f"marker {m} has no position", source=source, row=lineno, column="x")
        if not m and not math.isnan(pv[0]):
            raise InputError("a position without a marker name", source=source, row=lineno, column="marker")
        if m:
            _check_position_units(rows.source, lineno, pv)
        marker.append(m)
        xyz.append(pv)
        line.append(lineno)
    table = RunTable(source, np.array(run, dtype=str), np.array(direction, dtype=str), np.array(load, dtype=str),
                     np.array(t, dtype=float), np.array(q, dtype=float), np.array(dq, dtype=float),
                     np.array(cur, dtype=float), np.array(w, dtype=float), np.array(marker, dtype=str),
                     np.array(xyz, dtype=float), np.array(line, dtype=int))
    return table


def _check_speeds_against_motion(table: RunTable) -> None:
    """Refuse joint speeds that disagree with the motion of q over t: dq in
    degrees per second (180/pi times the motion), in rpm, with the opposite sign,
    zero while the joint moves, or t not in seconds.

    A run goes one way (docs/formats.md §3), so for each run and joint whose dq
    column is filled, the travel the speeds give, the integral of dq over t, is
    compared with the travel of q, last minus first sample. Only a joint that
    travels at least :data:`MIN_TRAVEL_RAD` is judged: a joint held still has
    no travel to compare, and sample noise does not add up along a run."""
    for r in dict.fromkeys(table.run):
        idx = np.flatnonzero(table.run == r)
        if len(idx) < 3:
            continue
        tt = table.t[idx]
        for j, col in enumerate(joint_columns("dq", table.n_joints)):
            dq = table.dq[idx, j]
            if not np.all(np.isfinite(dq)):
                continue
            travel = float(table.q[idx[-1], j] - table.q[idx[0], j])
            if abs(travel) < MIN_TRAVEL_RAD:
                continue
            ratio = float(np.sum((dq[1:] + dq[:-1]) * np.diff(tt)) / 2.0) / travel
            if SPEED_RATIO_OK[0] <= ratio <= SPEED_RATIO_OK[1]:
                continue
            what = (f"run {r}: the speeds {col} integrated over t give {ratio:.3g} times the travel of "
                    f"q{j + 1} ({travel:.4g} rad)")
            if DEGREE_RATIO[0] <= ratio <= DEGREE_RATIO[1]:
                reason = f"{what}, near 180/pi = 57.3; degrees per second? speeds are rad/s"
            elif ratio < 0:
                reason = f"{what}: {col} has the opposite sign of the motion"
            else:
                reason = f"{what}; speeds are rad/s and times seconds"
            raise InputError(reason, source=table.source, row=int(table.line[idx[0]]), column=col)


def read_run_table(path: str | pathlib.Path, robot: Robot | None = None) -> RunTable:
    """Read and validate a run table."""
    text, source = _read_text(path)
    return parse_run_table(text, robot, source=source)


# ------------------------------------------------------------------ writing
def _fmt(x: float) -> str:
    return "" if not math.isfinite(x) else repr(float(x))


def format_static_table(table: StaticTable) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(static_columns(table.n_joints) + tuple(k for k, _ in table.extra))
    for n in range(len(table)):
        writer.writerow([table.pose[n], table.load[n], _fmt(table.t[n])]
                        + [_fmt(v) for v in table.q[n]] + [_fmt(v) for v in table.wrench[n]]
                        + [_fmt(v) for v in table.currents[n]] + [table.marker[n]]
                        + [_fmt(v) for v in table.xyz[n]] + [_fmt(v[n]) for _, v in table.extra])
    return out.getvalue()


def write_static_table(path: str | pathlib.Path, table: StaticTable) -> None:
    pathlib.Path(path).write_text(format_static_table(table), encoding="utf-8")


def format_run_table(table: RunTable) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(run_columns(table.n_joints))
    for n in range(len(table)):
        writer.writerow([table.run[n], table.direction[n], table.load[n], _fmt(table.t[n])]
                        + [_fmt(v) for v in table.q[n]] + [_fmt(v) for v in table.dq[n]]
                        + [_fmt(v) for v in table.currents[n]] + [_fmt(v) for v in table.wrench[n]]
                        + [table.marker[n]] + [_fmt(v) for v in table.xyz[n]])
    return out.getvalue()


def write_run_table(path: str | pathlib.Path, table: RunTable) -> None:
    pathlib.Path(path).write_text(format_run_table(table), encoding="utf-8")


def _suspect_rows(table: StaticTable | RunTable, robot: Robot | None) -> np.ndarray:
    """Rows that may fail the per-row checks of the readers (a cheap screen of the whole table)."""
    bad = np.zeros(len(table), dtype=bool)
    q = table.q
    bad |= ~np.all(np.isfinite(q), axis=1)
    if robot is not None:
        bad |= np.any((q < robot.lower - 1e-3) | (q > robot.upper + 1e-3), axis=1)
    else:
        bad |= np.any(np.abs(q) > 2 * math.pi, axis=1)
    with np.errstate(invalid="ignore"):
        bad |= np.abs(table.t) > MAX_TIME_S
        bad |= np.any(np.abs(table.xyz) > MAX_POSITION_M, axis=1)
        bad |= np.any(np.abs(table.wrench) > MAX_WRENCH, axis=1)
        bad |= np.any(np.abs(table.currents) > MAX_CURRENT_A, axis=1)
        if isinstance(table, RunTable):
            bad |= np.any(np.abs(table.dq) > MAX_SPEED_RAD_S, axis=1)
    for arr in (table.t, table.xyz, table.wrench, table.currents) + ((table.dq,) if isinstance(table, RunTable) else ()):
        bad |= np.isinf(arr).reshape(len(table), -1).any(axis=1)
    if robot is not None:
        known = np.array(robot.marker_names, dtype=str)
        named = table.marker != ""
        bad |= named & ~np.isin(table.marker, known)
    if isinstance(table, StaticTable):
        bad |= ~np.all(np.isfinite(table.xyz), axis=1)
    return np.flatnonzero(bad)


def check_table_values(table: StaticTable | RunTable, robot: Robot | None = None) -> None:
    """The readers' value checks (units, limits, markers, finite numbers) on a table made from
    arrays (a log, a simulation), so that data from a log pass the checks a CSV table passes;
    an error names the table's line (the line of the exported CSV) and column."""
    src = table.source
    markers = set(robot.marker_names) if robot is not None else None
    static = isinstance(table, StaticTable)
    Q_COLS, DQ_COLS, I_COLS = (joint_columns(p, table.n_joints) for p in ("q", "dq", "i"))
    for n in _suspect_rows(table, robot):
        lineno = int(table.line[n])
        groups = [(Q_COLS, table.q[n]), (("t",), [table.t[n]]), (W_COLS, table.wrench[n]),
                  (I_COLS, table.currents[n]), (XYZ_COLS, table.xyz[n])]
        if not static:
            groups.append((DQ_COLS, table.dq[n]))
        for cols, values in groups:
            for col, v in zip(cols, values):
                required = col in Q_COLS or (static and col in XYZ_COLS)
                if math.isinf(v) or (required and math.isnan(v)):
                    raise InputError(f"not a finite number: {v!r}", source=src, row=lineno, column=col)
        _check_time(src, lineno, float(table.t[n]))
        _check_joint_units(src, lineno, [float(v) for v in table.q[n]], robot)
        _check_wrench(src, lineno, [float(v) for v in table.wrench[n] if not math.isnan(v)])
        _check_currents(src, lineno, [float(v) for v in table.currents[n] if not math.isnan(v)])
        if not static:
            for col, v in zip(DQ_COLS, table.dq[n]):
                if abs(v) > MAX_SPEED_RAD_S:
                    raise InputError(f"{v} rad/s is too fast for a calibration run; degrees per second? "
                                     "speeds are rad/s", source=src, row=lineno, column=col)
        m = str(table.marker[n])
        if m and markers is not None and m not in markers:
            raise InputError(f"unknown marker {m!r}; the robot has {', '.join(sorted(markers))}",
                             source=src, row=lineno, column="marker")
        if m:
            _check_position_units(src, lineno, [float(v) for v in table.xyz[n]])


def static_table_from_arrays(*, pose, load, q, marker, xyz, t=None, wrench=None, currents=None,
                             source: str = "<memory>", robot: Robot | None = None,
                             extra: dict | None = None) -> StaticTable:
    """Build a validated StaticTable from arrays, e.g. from a simulation or a log: the values
    pass the checks of :func:`parse_static_table` (joint limits of ``robot`` when given)."""
    n = len(pose)
    q = np.asarray(q, dtype=float)
    nj = robot.n_joints if robot is not None else (q.shape[1] if q.ndim == 2 else 6)
    nan6 = np.full((n, nj), np.nan)
    table = StaticTable(source, np.asarray(pose, dtype=str), np.asarray(load, dtype=str),
                        np.full(n, np.nan) if t is None else np.asarray(t, dtype=float),
                        q.reshape(n, nj),
                        np.full((n, 6), np.nan) if wrench is None else np.asarray(wrench, dtype=float).reshape(n, 6),
                        nan6.copy() if currents is None else np.asarray(currents, dtype=float).reshape(n, nj),
                        np.asarray(marker, dtype=str), np.asarray(xyz, dtype=float).reshape(n, 3),
                        np.arange(2, n + 2),
                        tuple((k, np.asarray(extra[k], dtype=float)) for k in STATIC_OPTIONAL_COLUMNS
                              if extra and k in extra))
    check_table_values(table, robot)
    _check_static_structure(table)
    return table


def run_table_from_arrays(*, run, direction, load, t, q, dq=None, currents=None, wrench=None, marker=None,
                          xyz=None, source: str = "<memory>", robot: Robot | None = None) -> RunTable:
    """Build a RunTable from arrays (missing columns become NaN / empty); the values pass the
    checks of :func:`parse_run_table` (joint limits of ``robot`` when given), the speeds
    agree with the motion."""
    n = len(run)
    q = np.asarray(q, dtype=float)
    nj = robot.n_joints if robot is not None else (q.shape[1] if q.ndim == 2 else 6)
    nan6 = np.full((n, nj), np.nan)
    table = RunTable(source, np.asarray(run, dtype=str), np.asarray(direction, dtype=str),
                    np.asarray(load, dtype=str), np.asarray(t, dtype=float), q.reshape(n, nj),
                    nan6 if dq is None else np.asarray(dq, dtype=float).reshape(n, nj),
                    nan6.copy() if currents is None else np.asarray(currents, dtype=float).reshape(n, nj),
                    np.full((n, 6), np.nan) if wrench is None else np.asarray(wrench, dtype=float).reshape(n, 6),
                    np.full(n, "", dtype=str) if marker is None else np.asarray(marker, dtype=str),
                    np.full((n, 3), np.nan) if xyz is None else np.asarray(xyz, dtype=float).reshape(n, 3),
                    np.arange(2, n + 2))
    check_table_values(table, robot)
    _check_speeds_against_motion(table)
    return table


def concat_static_tables(tables: Sequence[StaticTable]) -> StaticTable:
    """Several static tables as one (the logs of two rounds diagnosed together): rows in
    order; a table whose pose ids repeat an earlier table's gets them prefixed with its
    place (``2:P1``), so every pose keeps its own unloaded reference. Optional columns
    are kept when every table has them."""
    if not tables:
        raise ValueError("no table to join")
    if len(tables) == 1:
        return tables[0]
    seen: set[str] = set()
    poses = []
    for k, tb in enumerate(tables, start=1):
        ids = np.asarray(tb.pose, dtype=str)
        if seen & set(ids.tolist()):
            ids = np.char.add(f"{k}:", ids)
        seen |= set(ids.tolist())
        poses.append(ids)
    names = [name for name, _ in tables[0].extra if all(tb.optional(name) is not None for tb in tables)]
    return StaticTable(" + ".join(tb.source for tb in tables), np.concatenate(poses),
                       *(np.concatenate([getattr(tb, f) for tb in tables])
                         for f in ("load", "t", "q", "wrench", "currents", "marker", "xyz", "line")),
                       tuple((name, np.concatenate([tb.optional(name) for tb in tables])) for name in names))
