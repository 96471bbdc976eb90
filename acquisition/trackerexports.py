"""Reading the point files tracker software writes (docs/import.md).

Three layouts, each read into :class:`ExportPoint` records in metres:

* **Leica-style CSV** (emScon/Tracker Pilot, SpatialAnalyzer and PolyWorks
  exports look like it): a header naming the point, ``X [mm]``, ``Y [mm]``,
  ``Z [mm]`` (the unit in brackets or parentheses), optionally ``U(95) [mm]``,
  a target type, ``Temperature [°C]``, ``Pressure [hPa]``, ``Humidity [%]``
  and a timestamp; ``,`` or ``;`` separated (``;`` files may use decimal
  commas);
* **.xyz**: ``name;x;y;z`` lines (``;``, tab, space or ``,`` between the
  fields; ``#`` and ``//`` lines are comments), in ``--unit`` (default mm);
* **generic CSV** with a column mapping given on the command line
  (``name=Point,x=East,y=North,z=Up,t=Time,u95=Unc``) and ``--unit``.

Units are converted and checked: every coordinate within the tracker range
(160 m) and the points not all within 50 mm of the tracker (a metre file read
as millimetres); both errors say which unit the numbers look like.
"""

from __future__ import annotations

import csv
import datetime
import math
import pathlib
import re
from dataclasses import dataclass

from elastocal.errors import Arg, InputError
from elastocal.formats.tables import check_header
from elastocal.formats.textfiles import read_text_file
from elastocal.model.units import unit_table

#: length unit -> metres and pressure unit -> hPa, from elastocal's one unit table; a
#: tracker's export writes them in any case (MM, mmHg), so they are looked up lower-case
LENGTH_UNITS = {sym.lower(): f for sym, f in unit_table("m").items()}
PRESSURE_UNITS = {sym.lower(): f for sym, f in unit_table("hPa").items()}
#: the farthest a tracker measures [m], and the least spread a real cell's points have [m]
MAX_RANGE_M = 160.0
MIN_SPREAD_M = 0.05
LAYOUTS = ("auto", "leica", "xyz", "csv")
ROLES = ("name", "x", "y", "z", "t", "u95", "target", "temperature", "pressure", "humidity")


@dataclass(frozen=True)
class ExportPoint:
    """One point of a tracker export, SI units."""

    source: str
    line: int                              # 1-based line of the file
    name: str
    xyz_m: tuple[float, float, float]
    t_s: float | None = None               # seconds (UTC epoch for dates, else the file's own clock)
    u95_m: float | None = None             # expanded uncertainty (95 %) of the point [m]
    target: str = ""
    temperature_c: float | None = None
    pressure_hpa: float | None = None
    humidity_pct: float | None = None


# ----------------------------------------------------------------- values
def parse_time(text: str, *, source: str, line: int, column: str) -> float:
    """Seconds: a number as it is, an ISO 8601 or ``dd.mm.yyyy hh:mm:ss`` date as UTC epoch seconds
    (a date without a zone is taken as UTC; --clock-offset shifts it)."""
    s = text.strip()
    try:
        return float(s)
    except ValueError:
        pass
    iso = s.replace(",", ".") if re.search(r"\d:\d\d:\d\d,\d", s) else s
    try:
        dt = datetime.datetime.fromisoformat(iso.replace("Z", "+00:00"))
    except ValueError:
        dt = None
        for fmt in ("%d.%m.%Y %H:%M:%S.%f", "%d.%m.%Y %H:%M:%S", "%m/%d/%Y %H:%M:%S.%f", "%m/%d/%Y %H:%M:%S"):
            try:
                dt = datetime.datetime.strptime(iso, fmt)
                break
            except ValueError:
                continue
        if dt is None:
            raise InputError(f"{text!r} is not a time (seconds, or a date like 2026-11-22T10:00:01.250)",
                             source=source, row=line, column=column) from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=datetime.timezone.utc)
    return dt.timestamp()


def _number(text: str, *, decimal_comma: bool, source: str, line: int, column: str) -> float:
    s = text.strip()
    if decimal_comma:
        s = s.replace(",", ".")
    try:
        v = float(s)
    except ValueError:
        raise InputError(f"{text!r} is not a number", source=source, row=line, column=column) from None
    if not math.isfinite(v):
        raise InputError(f"{text!r} is not a finite number", source=source, row=line, column=column)
    return v


def length_factor(unit: str, *, source: str | None = None, column: str | None = None,
                  argument: str | None = None) -> float:
    """Metres per ``unit``; an unknown unit names the file (``source``, ``column``) or the
    command-line ``argument`` it came from."""
    key = unit.strip().lower()
    if key not in LENGTH_UNITS:
        raise InputError(f"unknown length unit {unit!r}; one of {', '.join(k for k in LENGTH_UNITS if k != 'µm')}",
                         source=source, column=column, argument=argument)
    return LENGTH_UNITS[key]


# ----------------------------------------------------------- Leica header
_UNIT = r"\s*(?:[\[(](?P<unit>[^\])]*)[\])])?\s*$"
_HEADER_ROLES = {
    "name": re.compile(r"^(point|point ?id|point ?name|name|id|pt|label)" + _UNIT, re.I),
    "x": re.compile(r"^x" + _UNIT, re.I),
    "y": re.compile(r"^y" + _UNIT, re.I),
    "z": re.compile(r"^z" + _UNIT, re.I),
    "u95": re.compile(r"^u ?\(?95\)?" + _UNIT, re.I),
    "target": re.compile(r"^(target|target ?type|reflector|reflector ?type|probe)" + _UNIT, re.I),
    "temperature": re.compile(r"^(temp|temperature|air ?temp(erature)?)" + _UNIT, re.I),
    "pressure": re.compile(r"^(press|pressure|air ?pressure)" + _UNIT, re.I),
    "humidity": re.compile(r"^(hum|humidity|rel\.? ?humidity|rh)" + _UNIT, re.I),
    "t": re.compile(r"^(time ?stamp|time|date ?time|date/time|measured)" + _UNIT, re.I),
}


def _leica_roles(header: list[str], source: str) -> dict[str, tuple[int, str | None]]:
    roles: dict[str, tuple[int, str | None]] = {}
    for i, h in enumerate(header):
        for role, rx in _HEADER_ROLES.items():
            m = rx.match(h.strip())
            if m and role not in roles:
                roles[role] = (i, m.group("unit"))
                break
    missing = [r for r in ("name", "x", "y", "z") if r not in roles]
    if missing:
        raise InputError((f"not a Leica-style point export: no column for {', '.join(missing)} (expected a "
                          "header like Point,X [mm],Y [mm],Z [mm]; for other layouts give ", Arg("columns"), ")"),
                         source=source, row=1)
    return roles


def _split_records(text: str, source: str) -> tuple[list[tuple[int, list[str]]], bool]:
    """CSV records with the separator of the header line (``,``, ``;`` or tab); whether the
    numbers use decimal commas (``;`` files)."""
    first = next((ln for ln in text.split("\n") if ln.strip()), "")
    sep = max((",", ";", "\t"), key=first.count)
    records = []
    lines = iter(text.split("\n"))
    for line, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        try:
            fields = next(csv.reader([raw], delimiter=sep))
        except csv.Error as exc:
            raise InputError(f"not a readable CSV record: {exc}", source=source, row=line) from None
        records.append((line, [f.strip() for f in fields]))
    return records, sep == ";"


# ------------------------------------------------------------------ read
def read_points(path: str | pathlib.Path, *, layout: str = "auto", unit: str | None = None,
                columns: dict[str, str] | None = None) -> list[ExportPoint]:
    """The points of one tracker export (see the module docstring)."""
    path = pathlib.Path(path)
    source = str(path)
    if layout not in LAYOUTS:
        raise InputError(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}", argument="layout")
    text = read_text_file(path)
    if layout == "auto":
        layout = "csv" if columns else ("xyz" if path.suffix.lower() in (".xyz", ".txt") else "leica")
    if layout == "xyz":
        points = _read_xyz(text, source, unit or "mm")
    else:
        points = _read_table(text, source, unit, columns if layout == "csv" else None)
    if not points:
        raise InputError("the export has no points", source=source)
    check_units(points, source)
    return points


def _read_xyz(text: str, source: str, unit: str) -> list[ExportPoint]:
    f = length_factor(unit, argument="unit")
    out = []
    for line, raw in enumerate(text.split("\n"), start=1):
        s = raw.strip()
        if not s or s.startswith("#") or s.startswith("//"):
            continue
        fields = [x for x in re.split(r"[;\t ]+|,(?=\s*[-+\d.])", s) if x != ""]
        if len(fields) != 4:
            raise InputError(f"expected name;x;y;z, got {len(fields)} field(s)", source=source, row=line)
        xyz = tuple(_number(v, decimal_comma=False, source=source, line=line, column=c) * f
                    for v, c in zip(fields[1:], "xyz"))
        out.append(ExportPoint(source, line, fields[0], xyz))      # type: ignore[arg-type]
    return out


def _table_units(roles: dict, header: list[str], unit: str | None, source: str) -> tuple[float, float, str, str]:
    """(metres per coordinate, metres per U95, temperature unit, pressure unit) from the
    header's brackets, else ``unit``; a header and a ``unit`` that disagree are refused."""
    head_units = {r: u for r, (_, u) in roles.items() if u}
    xyz_units = {head_units.get(c) for c in "xyz"}
    if len(xyz_units) > 1:
        raise InputError(f"X, Y and Z have different units ({', '.join(sorted(u or '?' for u in xyz_units))})",
                         source=source, row=1)
    file_unit = xyz_units.pop()
    if unit is not None and file_unit is not None and length_factor(unit, argument="unit") != \
            length_factor(file_unit, source=source, column=header[roles["x"][0]]):
        raise InputError((Arg("unit", unit), f" contradicts the header's unit [{file_unit}]"), source=source, row=1)
    length = file_unit or unit
    if length is None:
        raise InputError(("the coordinates' unit is not in the header (X [mm]); give ", Arg("unit", "mm"), " or ",
                          Arg("unit", "m")), source=source, row=1)
    f = length_factor(length, source=source) if file_unit else length_factor(length, argument="unit")
    fu = length_factor(head_units["u95"], source=source) if "u95" in head_units else f
    temp_unit = (head_units.get("temperature") or "°C").replace(" ", "").lower()
    if temp_unit not in ("°c", "c", "degc", "°f", "f", "degf"):
        raise InputError(f"unknown temperature unit {temp_unit!r} (°C or °F)", source=source, row=1)
    press_unit = (head_units.get("pressure") or "hPa").replace(" ", "").lower()
    if press_unit not in PRESSURE_UNITS:
        raise InputError(f"unknown pressure unit {press_unit!r}; one of {', '.join(PRESSURE_UNITS)}",
                         source=source, row=1)
    return f, fu, temp_unit, press_unit


def _read_table(text: str, source: str, unit: str | None, columns: dict[str, str] | None) -> list[ExportPoint]:
    records, decimal_comma = _split_records(text, source)
    if not records:
        raise InputError("the file is empty", source=source)
    _, header = records[0]
    check_header(header, source)
    if columns is None:
        roles = _leica_roles(header, source)
    else:
        roles = {}
        for role, col in columns.items():
            if col not in header:
                raise InputError((Arg("columns"), f" maps {role} to {col!r}, which is not in the header "
                                  f"({', '.join(header)})"), source=source, row=1)
            roles[role] = (header.index(col), None)
    f, fu, temp_unit, press_unit = _table_units(roles, header, unit, source)
    out = []
    for line, row in records[1:]:
        if not any(row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", source=source, row=line)

        def num(role: str, *, line=line, row=row) -> float | None:
            if role not in roles or row[roles[role][0]] == "":
                return None
            return _number(row[roles[role][0]], decimal_comma=decimal_comma, source=source, line=line,
                           column=header[roles[role][0]])

        name = row[roles["name"][0]]
        if not name:
            raise InputError("the point has no name", source=source, row=line, column=header[roles["name"][0]])
        xyz = []
        for c in "xyz":
            v = num(c)
            if v is None:
                raise InputError("missing coordinate", source=source, row=line, column=header[roles[c][0]])
            xyz.append(v * f)
        t = None
        if "t" in roles and row[roles["t"][0]]:
            t = parse_time(row[roles["t"][0]], source=source, line=line, column=header[roles["t"][0]])
        u95 = num("u95")
        if u95 is not None and u95 < 0:
            raise InputError("U95 must be >= 0", source=source, row=line, column=header[roles["u95"][0]])
        temp = num("temperature")
        if temp is not None and temp_unit in ("°f", "f", "degf"):
            temp = (temp - 32.0) / 1.8
        press = num("pressure")
        hum = num("humidity")
        for value, lo, hi, role in ((temp, -40.0, 60.0, "temperature"), (None if press is None else
                                    press * PRESSURE_UNITS[press_unit], 500.0, 1200.0, "pressure"),
                                    (hum, 0.0, 100.0, "humidity")):
            if value is not None and not lo <= value <= hi:
                raise InputError(f"{role} {value:g} is outside {lo:g}..{hi:g} (°C, hPa, %); check the unit",
                                 source=source, row=line, column=header[roles[role][0]])
        out.append(ExportPoint(source, line, name, tuple(xyz), t,           # type: ignore[arg-type]
                               None if u95 is None else u95 * fu,
                               row[roles["target"][0]] if "target" in roles else "", temp,
                               None if press is None else press * PRESSURE_UNITS[press_unit], hum))
    return out


def check_units(points: list[ExportPoint], source: str) -> None:
    """Coordinates within the tracker's range and not all within 50 mm of it (see the module docstring)."""
    far = max(points, key=lambda p: max(abs(v) for v in p.xyz_m))
    if max(abs(v) for v in far.xyz_m) > MAX_RANGE_M:
        raise InputError((f"point {far.name} is {max(abs(v) for v in far.xyz_m):.4g} m away, beyond a tracker's "
                          f"{MAX_RANGE_M:g} m: the numbers look like millimetres; give ", Arg("unit", "mm")),
                         source=source, row=far.line)
    reach = max(math.sqrt(sum(v * v for v in p.xyz_m)) for p in points)
    if reach < MIN_SPREAD_M:
        raise InputError((f"every point is within {reach * 1e3:.3g} mm of the tracker: the numbers look like "
                          "metres read as millimetres; give ", Arg("unit", "m")), source=source)


def parse_columns(text: str | None) -> dict[str, str] | None:
    """``--columns name=Point,x=X,...`` -> {role: column}."""
    if text is None:
        return None
    out: dict[str, str] = {}
    for item in text.split(","):
        if "=" not in item:
            raise InputError(f"expected role=column, got {item!r}", argument="columns")
        role, col = (s.strip() for s in item.split("=", 1))
        if role not in ROLES:
            raise InputError(f"unknown role {role!r}; one of {', '.join(ROLES)}", argument="columns")
        if role in out:
            raise InputError(f"{role} is mapped twice", argument="columns")
        out[role] = col
    missing = [r for r in ("name", "x", "y", "z") if r not in out]
    if missing:
        raise InputError(f"must map {', '.join(missing)} (e.g. name=Point,x=X,y=Y,z=Z)", argument="columns")
    return out
