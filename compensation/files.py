"""Path files in, compensated trajectories out: CSV, KUKA KRL, ABB RAPID.

Path CSV (docs/cli.md ``compensate``): ``t,q1..qN`` (N the robot's joints) and optionally
``fx,fy,fz,mx,my,mz`` per sample (SI units, radians, metres for a prismatic joint, base-frame
wrench on the load point).

Output CSV: the input columns, then the compensated commands ``qc1..qcN`` [rad, m]
and the predicted load-point deflection before compensation ``dx,dy,dz`` [m].

KRL and RAPID programs are joint moves through the compensated commands, in
degrees (millimetres for a prismatic joint) as those languages expect, one move per sample.
A robot of more than six joints is a six-axis arm behind external axes (a track): the last
six joints are the arm's axes (KRL A1..A6, RAPID robax), the joints before them its external
axes (KRL E1.., RAPID extax).
"""

from __future__ import annotations

import math
import pathlib
import re

import numpy as np

from elastocal.compensation.ik import PlannedPath
from elastocal.compensation.trajectory import CompensatedPath
from elastocal.errors import InputError
from elastocal.model.robot import Robot
from elastocal.formats.tables import check_header, csv_records
from elastocal.formats.textfiles import read_text_file

Q_COLS = tuple(f"q{j}" for j in range(1, 7))
W_COLS = ("fx", "fy", "fz", "mx", "my", "mz")
QC_COLS = tuple(f"qc{j}" for j in range(1, 7))
D_COLS = ("dx", "dy", "dz")
PATH_COLUMNS = ("t",) + Q_COLS + W_COLS
#: the arm's axes in a robot program; joints before them are external axes
ARM_AXES = 6
#: external axes a KRL E6AXIS / a RAPID extjoint holds
MAX_EXTERNAL_AXES = 6


def _cols(prefix: str, n: int) -> tuple[str, ...]:
    return tuple(f"{prefix}{j}" for j in range(1, n + 1))


def _number(value: str, source: str, row: int, col: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise InputError(f"not a number: {value!r}", source=source, row=row, column=col) from None
    if not math.isfinite(x):
        raise InputError(f"not a finite number: {value!r}", source=source, row=row, column=col)
    return x


def parse_path(text: str, robot: Robot | None = None, *, source: str = "<path.csv>") -> PlannedPath:
    """Read a path CSV; errors name file, line and column."""
    reader = csv_records(text, source)
    try:
        header = [h.strip() for h in next(reader)[1]]
    except StopIteration:
        raise InputError("the file is empty", source=source) from None
    check_header(header, source)
    from elastocal.formats.tables import table_joints

    n_joints = table_joints(header, robot, source)
    q_cols = _cols("q", n_joints)
    missing = [c for c in ("t",) + q_cols if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", source=source, row=1)
    unknown = [c for c in header if c not in ("t",) + q_cols + W_COLS]
    if unknown:
        raise InputError(f"unknown column(s) {', '.join(unknown)}; a path has t,q1..q{n_joints} and optionally "
                         "fx..mz", source=source, row=1)
    w_present = [c in header for c in W_COLS]
    if any(w_present) and not all(w_present):
        raise InputError(f"the wrench needs all of {','.join(W_COLS)}", source=source, row=1)
    idx = {c: i for i, c in enumerate(header)}
    records = list(reader)
    fast = _parse_plain(records, header, idx, robot, all(w_present), q_cols)
    if fast is not None:
        return fast
    t, q, w, lines = [], [], [], []
    for lineno, row in records:
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", source=source, row=lineno)
        row = [c.strip() for c in row]
        t.append(_number(row[idx["t"]], source, lineno, "t"))
        lines.append(lineno)
        qv = [_number(row[idx[c]], source, lineno, c) for c in q_cols]
        for j, v in enumerate(qv):
            if robot is not None and not robot.lower[j] - 1e-9 <= v <= robot.upper[j] + 1e-9:
                unit = robot.joints[j].unit
                hint = "; millimetres? a prismatic joint's q is in metres" if unit == "m" else \
                    ("; degrees? angles are radians" if abs(v) > 2 * math.pi else "")
                raise InputError(f"{v} {unit} is outside the joint limits [{robot.lower[j]:.4g}, "
                                 f"{robot.upper[j]:.4g}]{hint}", source=source, row=lineno, column=q_cols[j])
        q.append(qv)
        if all(w_present):
            w.append([_number(row[idx[c]], source, lineno, c) for c in W_COLS])
        if len(t) > 1 and t[-1] < t[-2]:
            raise InputError("time goes backwards", source=source, row=lineno, column="t")
    if not t:
        raise InputError("the path has no rows", source=source)
    return PlannedPath(t=np.array(t), q=np.array(q), wrench=np.array(w) if w else None, line=np.array(lines))


def _parse_plain(records: list[tuple[int, list[str]]], header: list[str], idx: dict[str, int], robot: Robot | None,
                 with_wrench: bool, q_cols: tuple[str, ...] = Q_COLS) -> PlannedPath | None:
    """The path of a file without blank lines whose fields are all finite numbers within the
    joint limits, in time order, converted in one numpy pass (numpy parses a field as
    ``float()`` does); None for any other file, which the row-by-row reader reads or
    refuses with the line and column of the first problem."""
    if not records or any(len(row) != len(header) for _, row in records):
        return None
    try:
        values = np.array([row for _, row in records], dtype=float)
    except ValueError:
        return None
    if not np.all(np.isfinite(values)):
        return None
    t = values[:, idx["t"]]
    q = values[:, [idx[c] for c in q_cols]]
    if robot is not None and np.any((q < robot.lower - 1e-9) | (q > robot.upper + 1e-9)):
        return None
    if np.any(t[1:] < t[:-1]):
        return None
    wrench = values[:, [idx[c] for c in W_COLS]] if with_wrench else None
    return PlannedPath(t=t.copy(), q=q, wrench=wrench, line=np.array([lineno for lineno, _ in records]))


def _csv_lines(header: tuple[str, ...], values: np.ndarray) -> str:
    """CSV text: the header, then one line per row of ``values`` with each number as
    ``repr(float)`` (the shortest text that reads back to the same number)."""
    lines = [",".join(header)]
    lines += [repr(row)[1:-1].replace(", ", ",") for row in values.tolist()]
    return "\n".join(lines) + "\n"


def read_path(path: str | pathlib.Path, robot: Robot | None = None) -> PlannedPath:
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_path(text, robot, source=str(path))


def write_path(path: str | pathlib.Path, planned: PlannedPath) -> None:
    """Write a path CSV (t, q1..qN and the wrench when the path has one)."""
    cols = ("t",) + _cols("q", np.asarray(planned.q).shape[1]) + (W_COLS if planned.wrench is not None else ())
    parts = [planned.t, planned.q] + ([planned.wrench] if planned.wrench is not None else [])
    values = np.column_stack([np.asarray(p, dtype=float).reshape(len(planned), -1) for p in parts])
    pathlib.Path(path).write_text(_csv_lines(cols, values), encoding="utf-8")


def write_compensated_csv(path: str | pathlib.Path, t: np.ndarray, result: CompensatedPath) -> None:
    """``t, q1..qN, fx..mz, qc1..qcN, dx, dy, dz``."""
    values = np.column_stack([np.asarray(t, dtype=float).reshape(-1, 1), result.q_planned, result.wrench,
                              result.q_command, result.tcp_deflection]).astype(float)
    n = result.q_planned.shape[1]
    pathlib.Path(path).write_text(_csv_lines(("t",) + _cols("q", n) + W_COLS + _cols("qc", n) + D_COLS, values),
                                  encoding="utf-8")


def _program_name(path: str | pathlib.Path, max_len: int) -> str:
    stem = re.sub(r"[^A-Za-z0-9_]", "_", pathlib.Path(path).stem) or "path"
    if not stem[0].isalpha():
        stem = "p_" + stem
    return stem[:max_len]


def _deg_lines(template: str, rows: np.ndarray) -> list[str]:
    """``template % row`` for each row of numbers, whose ``%.6f`` fields print an angle in
    degrees to 6 decimals: rounded to nearest (ties to even, as ``round``), and never as
    "-0.000000" (a tiny negative angle prints as 0)."""
    return [(template % tuple(row)).replace("-0.000000", "0.000000") for row in rows.tolist()]


def _program_axes(result: CompensatedPath) -> tuple[np.ndarray, np.ndarray]:
    """The commands in a robot program's units (degrees; millimetres for a prismatic joint), split
    into the arm's axes (the last six joints) and the external axes before them."""
    q = result.q_command
    prismatic = np.array(result.prismatic or (False,) * q.shape[1], dtype=bool)
    values = np.where(prismatic, q * 1e3, np.degrees(q))
    n_ext = max(q.shape[1] - ARM_AXES, 0)
    if n_ext > MAX_EXTERNAL_AXES:
        raise InputError(f"{q.shape[1]} joints: a robot program holds six arm axes and at most "
                         f"{MAX_EXTERNAL_AXES} external axes", argument="krl")
    return values[:, n_ext:], values[:, :n_ext]


def _header_lines(result: CompensatedPath, comment: str) -> list[str]:
    units = "joint angles in degrees" + (", prismatic joints in mm" if any(result.prismatic) else "")
    return [f"{comment} elastocal compensated joint path: {len(result)} points, form {result.form}, "
            f"reference {result.reference}",
            f"{comment} {units}; compensation removes up to "
            f"{1e3 * float(np.max(np.linalg.norm(result.tcp_deflection, axis=1))):.3f} mm of tool deflection"]


def format_krl(name: str, t: np.ndarray, result: CompensatedPath) -> str:
    """A KUKA KRL program (.src): PTP joint moves (AXIS aggregates, degrees),
    approximated (C_PTP) except the last one."""
    arm, ext = _program_axes(result)
    lines = ["&ACCESS RVP", f"DEF {name}( )"] + _header_lines(result, ";")
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    lines += [f"; planned duration {duration:.3f} s: set the axis speed (BAS #VEL_PTP) to match",
              "  BAS(#INITMOV, 0)", "  $APO.CPTP = 1"]
    axes = ", ".join([f"A{j + 1} %.6f" for j in range(arm.shape[1])] + [f"E{j + 1} %.6f" for j in range(ext.shape[1])])
    kind = "E6AXIS" if ext.shape[1] else "AXIS"
    moves = _deg_lines(f"  PTP {{{kind}: {axes}}} C_PTP", np.hstack([arm, ext]))
    if moves:
        moves[-1] = moves[-1][:-len(" C_PTP")]              # the last move stops
    lines += moves
    lines.append("END")
    return "\n".join(lines) + "\n"


def format_rapid(name: str, t: np.ndarray, result: CompensatedPath) -> str:
    """An ABB RAPID module (.mod): MoveAbsJ through jointtargets (degrees), each
    move timed (``\\T``) by the path's sample times; the first move approaches
    at v100, the last one stops (fine)."""
    arm, ext = _program_axes(result)
    lines = [f"MODULE {name}"] + ["  " + s for s in _header_lines(result, "!")] + ["  PROC main()"]
    extax = "[" + ",".join(["%.6f"] * ext.shape[1] + ["9E9"] * (MAX_EXTERNAL_AXES - ext.shape[1])) + "]"
    target = "[[" + ",".join(["%.6f"] * arm.shape[1]) + "]," + extax + "]"
    moves = _deg_lines(f"    MoveAbsJ {target}\\NoEOffs, ", np.hstack([arm, ext]))
    # the first move approaches at v100, the others take their sample interval (1 ms at least)
    dt = np.maximum(np.diff(np.asarray(t, dtype=float)), 1e-3)
    speeds = ["v100"] + [f"v1000\\T:={d:.4f}" for d in dt.tolist()]
    zones = ["z1"] * (len(moves) - 1) + ["fine"]
    lines += [f"{move}{speed}, {zone}, tool0;" for move, speed, zone in zip(moves, speeds, zones)]
    lines += ["  ENDPROC", "ENDMODULE"]
    return "\n".join(lines) + "\n"


def write_krl(path: str | pathlib.Path, t: np.ndarray, result: CompensatedPath, *,
              name_from: str | pathlib.Path | None = None) -> None:
    """The KRL program at ``path``, named after ``name_from`` (default: ``path``)."""
    name = _program_name(path if name_from is None else name_from, 24)
    pathlib.Path(path).write_text(format_krl(name, t, result), encoding="utf-8")


def write_rapid(path: str | pathlib.Path, t: np.ndarray, result: CompensatedPath, *,
                name_from: str | pathlib.Path | None = None) -> None:
    """The RAPID module at ``path``, named after ``name_from`` (default: ``path``)."""
    name = _program_name(path if name_from is None else name_from, 32)
    pathlib.Path(path).write_text(format_rapid(name, t, result), encoding="utf-8")
