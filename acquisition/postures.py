"""Posture-per-row files (docs/import.md): one row per robot posture, the joint values in
named columns and one or more measured points per row, as motion-capture systems, other
tools' calibrations and FIGAROH's calibration CSV write them.

FIGAROH's layout (``figaroh.calibration.data_loader.load_data``, Apache-2.0): a header
with ``x1, y1, z1`` (and the orientation ``phix1, phiy1, phiz1`` when measured) for the
first point, ``x2, …`` for the next, and one column per active joint named as the URDF
joint, in metres and radians. Any such file reads with the joint columns and the points
named on the command line (``--joints``, ``--points R1=x1,y1,z1;R2=x2,y2,z2``); other
columns (orientations, a session id, a pandas index) are ignored.

The result is an absolute-only static table (docs/formats.md §2): one row per posture and
point, load 0, no wrench, no currents, the poses numbered 1, 2, … across the files in
order. Every refusal is one line naming the file and line, or the argument.
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.acquisition.trackerexports import MAX_RANGE_M, MIN_SPREAD_M, _split_records, length_factor
from elastocal.errors import Arg, InputError
from elastocal.formats.tables import STATIC_OPTIONAL_COLUMNS, StaticTable, check_header, check_table_values
from elastocal.formats.textfiles import read_text_file
from elastocal.model.kinds import JointKind
from elastocal.model.robot import Robot
from elastocal.model.units import conversion

#: the angle units a posture file may give its revolute joints in, and their factors to rad (model.units)
ANGLE_UNITS = {unit: conversion(unit, "rad") for unit in ("rad", "deg")}
#: a revolute joint value beyond this many radians is taken as degrees
MAX_RADIANS = 2.0 * math.pi + 1e-6
#: how far outside a joint's limits a value may be (rounding of the file) [rad or m]
LIMIT_SLACK = 1e-3


@dataclass(frozen=True)
class PointColumns:
    """One measured point of each row: the robot's marker it is and its x, y, z columns."""

    marker: str
    columns: tuple[str, str, str]


def parse_points(text: str, robot: Robot) -> tuple[PointColumns, ...]:
    """``NAME=X,Y,Z[;NAME=X,Y,Z…]`` -> the points, each a marker of ``robot``."""
    out: list[PointColumns] = []
    for item in (s.strip() for s in text.split(";")):
        name, sep, cols = item.partition("=")
        columns = tuple(c.strip() for c in cols.split(","))
        if not sep or not name.strip() or len(columns) != 3 or not all(columns):
            raise InputError(f"expected NAME=X,Y,Z[;NAME=X,Y,Z…] (a marker and its three columns), got {item!r}",
                             argument="points")
        name = name.strip()
        if name not in robot.marker_names:
            raise InputError(f"{name!r} is not a marker of robot {robot.name}; its markers are "
                             f"{', '.join(robot.marker_names)} ([tool.markers] of robot.toml)", argument="points")
        if any(p.marker == name for p in out):
            raise InputError(f"marker {name} is given twice", argument="points")
        out.append(PointColumns(name, columns))    # type: ignore[arg-type]
    return tuple(out)


def parse_joint_columns(text: str | None, robot: Robot) -> tuple[str, ...]:
    """``COL1,COL2,…`` (default: the robot's joint names), one column per joint, base to tip."""
    if text is None:
        return tuple(j.name or f"joint{i}" for i, j in enumerate(robot.joints, start=1))
    cols = tuple(c.strip() for c in text.split(","))
    if not all(cols):
        raise InputError(f"an empty column name in {text!r}", argument="joints")
    if len(cols) != robot.n_joints:
        raise InputError(f"names {len(cols)} column{'s' * (len(cols) != 1)}; robot {robot.name} has "
                         f"{robot.n_joints} joints ({', '.join(j.name or '?' for j in robot.joints)}), one column "
                         "each, base to tip", argument="joints")
    if len(set(cols)) != len(cols):
        raise InputError("a column is named twice", argument="joints")
    return cols


@dataclass(frozen=True)
class _Rows:
    q: list[np.ndarray]
    xyz: list[np.ndarray]        # (P, 3) per row, nan where a point was not seen
    u: list[float]
    line: list[int]


def _column_index(header: list[str], name: str, *, source: str, argument: str) -> int:
    if name not in header:
        shown = ", ".join(header[:12]) + (", …" if len(header) > 12 else "")
        raise InputError((f"no column {name!r} (named by ", Arg(argument), f"); its columns are {shown}"),
                         source=source, row=1)
    return header.index(name)


def _number(cell: str, *, decimal_comma: bool, source: str, line: int, column: str) -> float:
    text = cell.replace(",", ".") if decimal_comma else cell
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"{cell!r} is not a number", source=source, row=line, column=column) from None
    if not math.isfinite(v):
        raise InputError(f"{cell!r} is not a finite number", source=source, row=line, column=column)
    return v


def _read_file(path: str, robot: Robot, joints: Sequence[str], points: Sequence[PointColumns], *,
               length_m: float, angle_rad: float, uncertainty: str | None, uncertainty_arg: str) -> _Rows:
    records, decimal_comma = _split_records(read_text_file(path), path)
    if not records:
        raise InputError("the file is empty; expected a header and one row per posture", source=path)
    (_, header), body = records[0], records[1:]
    check_header(header, path)
    jcols = [_column_index(header, c, source=path, argument="joints") for c in joints]
    pcols = [[_column_index(header, c, source=path, argument="points") for c in p.columns] for p in points]
    ucol = None if uncertainty is None else _column_index(header, uncertainty, source=path, argument=uncertainty_arg)
    if not body:
        raise InputError("no postures: the file has a header and no rows", source=path)
    scale = np.array([angle_rad if j.kind is JointKind.REVOLUTE else length_m for j in robot.joints])
    rows = _Rows([], [], [], [])
    for line, cells in body:
        if len(cells) < len(header):
            raise InputError(f"{len(cells)} fields; the header has {len(header)}", source=path, row=line)
        q = np.array([_number(cells[k], decimal_comma=decimal_comma, source=path, line=line, column=header[k])
                      for k in jcols]) * scale
        xyz = np.full((len(points), 3), np.nan)
        for p, (point, cols) in enumerate(zip(points, pcols)):
            given = [cells[k] != "" for k in cols]
            if not any(given):               # not seen in this posture (an occluded marker)
                continue
            if not all(given):
                missing = header[cols[given.index(False)]]
                raise InputError(f"point {point.marker} has an empty {missing}: give all three coordinates of a "
                                 "point or none (not seen)", source=path, row=line, column=missing)
            xyz[p] = [_number(cells[k], decimal_comma=decimal_comma, source=path, line=line, column=header[k])
                      * length_m for k in cols]
        if np.all(np.isnan(xyz)):
            raise InputError("no point measured in this posture (every point's columns empty); leave the row out",
                             source=path, row=line)
        u = math.nan
        if ucol is not None and cells[ucol] != "":
            u = _number(cells[ucol], decimal_comma=decimal_comma, source=path, line=line,
                        column=header[ucol]) * length_m
            if not 0.0 <= u < 0.01:
                raise InputError((f"an uncertainty of {u * 1e3:g} mm; below 10 mm expected (the wrong ",
                                  Arg("unit"), "?)"), source=path, row=line, column=header[ucol])
        _check_joints(q, robot, joints, source=path, line=line, angles_given=angle_rad)
        rows.q.append(q)
        rows.xyz.append(xyz)
        rows.u.append(u)
        rows.line.append(line)
    _check_lengths(np.array(rows.xyz), rows.line, source=path)
    return rows


def _check_joints(q: np.ndarray, robot: Robot, joints: Sequence[str], *, source: str, line: int,
                  angles_given: float) -> None:
    for i, (value, j, col) in enumerate(zip(q, robot.joints, joints)):
        if j.lower - LIMIT_SLACK <= value <= j.upper + LIMIT_SLACK:
            continue
        unit = j.unit
        hint: tuple = ()
        if j.kind is JointKind.REVOLUTE and angles_given == 1.0 and abs(value) > MAX_RADIANS:
            hint = ("; the numbers look like degrees: give ", Arg("angles", "deg"))
        elif j.kind is JointKind.PRISMATIC and abs(value) > 10.0:
            hint = ("; the numbers look like millimetres: give ", Arg("unit", "mm"))
        raise InputError((f"joint {i + 1} ({j.name or col}) at {value:.6g} {unit} is outside its limits "
                          f"{j.lower:g}..{j.upper:g} {unit}", *hint), source=source, row=line, column=col)


def _check_lengths(xyz: np.ndarray, lines: list[int], *, source: str) -> None:
    """Points within a tracker's or a camera system's range, and not all within 50 mm of its origin."""
    with np.errstate(invalid="ignore"):
        far = np.nanmax(np.abs(xyz), axis=(1, 2))
    k = int(np.nanargmax(far))
    if far[k] > MAX_RANGE_M:
        raise InputError((f"a point {far[k]:.4g} m away, beyond any tracker's {MAX_RANGE_M:g} m: the numbers look "
                          "like millimetres; give ", Arg("unit", "mm")), source=source, row=lines[k])
    reach = float(np.nanmax(np.linalg.norm(xyz, axis=2)))
    if reach < MIN_SPREAD_M:
        raise InputError((f"every point is within {reach * 1e3:.3g} mm of the measuring system's origin: the numbers "
                          "look like metres read as millimetres; give ", Arg("unit", "m")), source=source)


def read_postures(paths: Sequence[str | pathlib.Path], robot: Robot, *, joints: str | None, points: str,
                  unit: str = "m", angles: str = "rad", u95: str | None = None,
                  std: str | None = None) -> StaticTable:
    """The posture files as one absolute-only static table (module docstring). ``unit`` is the
    length unit of the points, the uncertainty and prismatic joints; ``angles`` that of the
    revolute joints; ``u95`` a column of expanded (k = 2) uncertainties, ``std`` one of
    standard uncertainties per axis, of every point of the row."""
    if angles not in ANGLE_UNITS:
        raise InputError(f"unknown angle unit {angles!r}; rad or deg", argument="angles")
    if u95 is not None and std is not None:
        raise InputError("give the uncertainty as u95 or as std, not both", argument="std")
    length_m = length_factor(unit, argument="unit")
    jcols = parse_joint_columns(joints, robot)
    pcols = parse_points(points, robot)
    if std is not None and not all(c in STATIC_OPTIONAL_COLUMNS for c in ("sx", "sy", "sz")):
        raise InputError("this version's static table has no sx,sy,sz columns; give the uncertainty as u95",
                         argument="std")
    pose, q, marker, xyz, u, line = [], [], [], [], [], []
    postures = 0
    for path in map(str, paths):
        rows = _read_file(path, robot, jcols, pcols, length_m=length_m, angle_rad=ANGLE_UNITS[angles],
                          uncertainty=u95 if u95 is not None else std, uncertainty_arg="u95" if u95 else "std")
        for qr, xr, ur, lr in zip(rows.q, rows.xyz, rows.u, rows.line):
            postures += 1
            number = str(postures)
            for p, point in enumerate(pcols):
                if np.isnan(xr[p, 0]):
                    continue
                pose.append(number)
                q.append(qr)
                marker.append(point.marker)
                xyz.append(xr[p])
                u.append(ur)
                line.append(lr)
    n = len(pose)
    extra: dict[str, np.ndarray] | None = None
    if u95 is not None:
        extra = {"u95": np.array(u)}
    elif std is not None:
        extra = {c: np.array(u) for c in ("sx", "sy", "sz")}
    # built here, not by static_table_from_arrays: an absolute-only table has no deflection to check the
    # structure of; every value passes the table readers' checks
    table = StaticTable(source=", ".join(map(str, paths)), pose=np.array(pose, dtype=str),
                        load=np.full(n, "0", dtype=str), t=np.full(n, np.nan), q=np.array(q).reshape(n, robot.n_joints),
                        wrench=np.full((n, 6), np.nan), currents=np.full((n, robot.n_joints), np.nan),
                        marker=np.array(marker, dtype=str), xyz=np.array(xyz).reshape(n, 3), line=np.array(line),
                        extra=tuple((k, v) for k, v in (extra or {}).items()))
    check_table_values(table, robot)
    return table
