"""Path files in, compensated trajectories out: CSV, KUKA KRL, ABB RAPID.

Path CSV (docs/cli.md ``compensate``): ``t,q1..q6`` and optionally ``fx,fy,fz,mx,my,mz``
per sample (SI units, radians, base-frame wrench on the load point).

Output CSV: the input columns, then the compensated commands ``qc1..qc6`` [rad]
and the predicted load-point deflection before compensation ``dx,dy,dz`` [m].

KRL and RAPID programs are joint moves through the compensated commands, in
degrees as those languages expect, one move per sample.
"""

from __future__ import annotations

import csv
import io
import math
import pathlib
import re

import numpy as np

from elastocal.compensation.ik import PlannedPath
from elastocal.compensation.trajectory import CompensatedPath
from elastocal.errors import InputError
from elastocal.identify.robot import Robot
from elastocal.identify.tables import check_header, csv_records
from elastocal.textfiles import read_text_file

Q_COLS = tuple(f"q{j}" for j in range(1, 7))
W_COLS = ("fx", "fy", "fz", "mx", "my", "mz")
QC_COLS = tuple(f"qc{j}" for j in range(1, 7))
D_COLS = ("dx", "dy", "dz")
PATH_COLUMNS = ("t",) + Q_COLS + W_COLS


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
    missing = [c for c in ("t",) + Q_COLS if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", source=source, row=1)
    unknown = [c for c in header if c not in PATH_COLUMNS]
    if unknown:
        raise InputError(f"unknown column(s) {', '.join(unknown)}; a path has t,q1..q6 and optionally fx..mz",
                         source=source, row=1)
    w_present = [c in header for c in W_COLS]
    if any(w_present) and not all(w_present):
        raise InputError(f"the wrench needs all of {','.join(W_COLS)}", source=source, row=1)
    idx = {c: i for i, c in enumerate(header)}
    t, q, w, lines = [], [], [], []
    for lineno, row in reader:
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", source=source, row=lineno)
        row = [c.strip() for c in row]
        t.append(_number(row[idx["t"]], source, lineno, "t"))
        lines.append(lineno)
        qv = [_number(row[idx[c]], source, lineno, c) for c in Q_COLS]
        for j, v in enumerate(qv):
            if robot is not None and not robot.lower[j] - 1e-9 <= v <= robot.upper[j] + 1e-9:
                hint = "; degrees? angles are radians" if abs(v) > 2 * math.pi else ""
                raise InputError(f"{v} rad is outside the joint limits [{robot.lower[j]:.4g}, "
                                 f"{robot.upper[j]:.4g}]{hint}", source=source, row=lineno, column=Q_COLS[j])
        q.append(qv)
        if all(w_present):
            w.append([_number(row[idx[c]], source, lineno, c) for c in W_COLS])
        if len(t) > 1 and t[-1] < t[-2]:
            raise InputError("time goes backwards", source=source, row=lineno, column="t")
    if not t:
        raise InputError("the path has no rows", source=source)
    return PlannedPath(t=np.array(t), q=np.array(q), wrench=np.array(w) if w else None, line=np.array(lines))


def read_path(path: str | pathlib.Path, robot: Robot | None = None) -> PlannedPath:
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_path(text, robot, source=str(path))


def write_path(path: str | pathlib.Path, planned: PlannedPath) -> None:
    """Write a path CSV (t, q1..q6 and the wrench when the path has one)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    cols = ("t",) + Q_COLS + (W_COLS if planned.wrench is not None else ())
    writer.writerow(cols)
    for i in range(len(planned)):
        row = [repr(float(planned.t[i]))] + [repr(float(v)) for v in planned.q[i]]
        if planned.wrench is not None:
            row += [repr(float(v)) for v in planned.wrench[i]]
        writer.writerow(row)
    pathlib.Path(path).write_text(out.getvalue(), encoding="utf-8")


def write_compensated_csv(path: str | pathlib.Path, t: np.ndarray, result: CompensatedPath) -> None:
    """``t, q1..q6, fx..mz, qc1..qc6, dx, dy, dz``."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(("t",) + Q_COLS + W_COLS + QC_COLS + D_COLS)
    for i in range(len(result)):
        values = [t[i], *result.q_planned[i], *result.wrench[i], *result.q_command[i], *result.tcp_deflection[i]]
        writer.writerow([repr(float(v)) for v in values])
    pathlib.Path(path).write_text(out.getvalue(), encoding="utf-8")


def _program_name(path: str | pathlib.Path, max_len: int) -> str:
    stem = re.sub(r"[^A-Za-z0-9_]", "_", pathlib.Path(path).stem) or "path"
    if not stem[0].isalpha():
        stem = "p_" + stem
    return stem[:max_len]


def _deg(v: float) -> str:
    return f"{round(float(v), 6) + 0.0:.6f}"  # no "-0.000000"


def _header_lines(result: CompensatedPath, comment: str) -> list[str]:
    return [f"{comment} elastocal compensated joint path: {len(result)} points, form {result.form}, "
            f"reference {result.reference}",
            f"{comment} joint angles in degrees; compensation removes up to "
            f"{1e3 * float(np.max(np.linalg.norm(result.tcp_deflection, axis=1))):.3f} mm of tool deflection"]


def format_krl(name: str, t: np.ndarray, result: CompensatedPath) -> str:
    """A KUKA KRL program (.src): PTP joint moves (AXIS aggregates, degrees),
    approximated (C_PTP) except the last one."""
    deg = np.degrees(result.q_command)
    lines = ["&ACCESS RVP", f"DEF {name}( )"] + _header_lines(result, ";")
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    lines += [f"; planned duration {duration:.3f} s: set the axis speed (BAS #VEL_PTP) to match",
              "  BAS(#INITMOV, 0)", "  $APO.CPTP = 1"]
    for i, row in enumerate(deg):
        axes = ", ".join(f"A{j + 1} {_deg(v)}" for j, v in enumerate(row))
        approx = " C_PTP" if i < len(deg) - 1 else ""
        lines.append(f"  PTP {{AXIS: {axes}}}{approx}")
    lines.append("END")
    return "\n".join(lines) + "\n"


def format_rapid(name: str, t: np.ndarray, result: CompensatedPath) -> str:
    """An ABB RAPID module (.mod): MoveAbsJ through jointtargets (degrees), each
    move timed (``\\T``) by the path's sample times; the first move approaches
    at v100, the last one stops (fine)."""
    deg = np.degrees(result.q_command)
    lines = [f"MODULE {name}"] + ["  " + s for s in _header_lines(result, "!")] + ["  PROC main()"]
    ext = "[9E9,9E9,9E9,9E9,9E9,9E9]"
    for i, row in enumerate(deg):
        target = "[[" + ",".join(_deg(v) for v in row) + "]," + ext + "]"
        if i == 0:
            speed = "v100"
        else:
            dt = max(float(t[i] - t[i - 1]), 1e-3)
            speed = f"v1000\\T:={dt:.4f}"
        zone = "fine" if i == len(deg) - 1 else "z1"
        lines.append(f"    MoveAbsJ {target}\\NoEOffs, {speed}, {zone}, tool0;")
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
