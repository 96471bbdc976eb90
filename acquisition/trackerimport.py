"""Tracker exports plus the robot's joint log -> the static table (docs/formats.md §2; docs/import.md).

Each point of the export (:mod:`elastocal.acquisition.trackerexports`) is paired
with a pose, a load state and a marker, and with the joint coordinates and
motor currents of that moment:

* **by name**: a pattern such as ``P{pose}_L{load}_{marker}`` (fields
  ``{pose}``, ``{load}``, ``{marker}``, optionally ``{repeat}``; ``*`` matches
  anything) reads pose, load and marker from the point's name;
* **by time**: the point's timestamp (plus ``clock_offset_s``) is matched to
  the joint log.

The joint log is either the MCAP log of ``elastocal calibrate`` (its
``reading`` events: by name, the k-th point of a (pose, load, marker) takes
the k-th reading of it; by time, the reading whose window holds the point,
within ``tolerance_s``; ``q``, the wrench, the currents and ``t`` are then
exactly those ``elastocal export`` writes for that reading) or a joint CSV
(:func:`read_joint_csv`: ``t,q1..q6,i1..i6`` and optional ``pose,load`` and
``fx..mz``; the samples within ``window_s`` around the point are averaged,
and each pose gets the mean ``q`` of all its samples: one pose, one
configuration).

A point that cannot be paired is left out and named (:attr:`ImportResult.unpaired`).
The per-point U95 and the weather go into the optional columns of the table
(docs/formats.md §2, optional columns).
"""

from __future__ import annotations

import math
import pathlib
import re
from dataclasses import dataclass

import numpy as np

from elastocal.acquisition.export import StaticReading, static_readings
from elastocal.acquisition.logreader import LogContents
from elastocal.acquisition.trackerexports import ExportPoint, parse_time
from elastocal.errors import Arg, InputError, Message, say
from elastocal.formats.tables import I_COLS, Q_COLS, W_COLS, StaticTable, check_header, csv_records, \
    static_table_from_arrays
from elastocal.formats.textfiles import read_text_file

PATTERN_FIELDS = ("pose", "load", "marker", "repeat")


# ----------------------------------------------------------------- names
@dataclass(frozen=True)
class NamePattern:
    text: str
    regex: re.Pattern

    @classmethod
    def parse(cls, text: str) -> "NamePattern":
        parts = re.split(r"(\{[^}]*\}|\*)", text)
        out, seen = [], set()
        for part in parts:
            if part == "*":
                out.append(".*?")
            elif part.startswith("{") and part.endswith("}"):
                name = part[1:-1]
                if name not in PATTERN_FIELDS:
                    raise InputError(f"unknown field {part} in the name pattern; use "
                                     f"{', '.join('{' + f + '}' for f in PATTERN_FIELDS)}", argument="names")
                if name in seen:
                    raise InputError(f"{part} appears twice in the name pattern", argument="names")
                seen.add(name)
                out.append(f"(?P<{name}>.+?)")
            elif "{" in part or "}" in part:
                raise InputError(f"unbalanced brace in the name pattern {text!r}", argument="names")
            else:
                out.append(re.escape(part))
        if not {"pose", "load", "marker"} <= seen:
            missing = sorted({"pose", "load", "marker"} - seen)
            raise InputError(f"the name pattern needs {', '.join('{' + m + '}' for m in missing)}",
                             argument="names")
        return cls(text, re.compile("^" + "".join(out) + "$"))

    def match(self, name: str) -> dict[str, str] | None:
        m = self.regex.match(name)
        return None if m is None else m.groupdict()


# ----------------------------------------------------------- joint CSV log
@dataclass(frozen=True)
class JointLog:
    """A joint/current log from the robot controller (CSV), samples in time order."""

    source: str
    t_s: np.ndarray              # (n,)
    q: np.ndarray                # (n, 6) rad
    currents: np.ndarray         # (n, 6) A
    wrench: np.ndarray           # (n, 6), NaN when the log has none
    pose: np.ndarray | None      # (n,) str
    load: np.ndarray | None      # (n,) str
    line: np.ndarray             # (n,)


def read_joint_csv(path: str | pathlib.Path) -> JointLog:
    """``t,q1..q6,i1..i6`` (t in seconds or as dates like the export's), optional ``pose,load``, ``fx..mz``."""
    source = str(path)
    records = csv_records(read_text_file(path), source)
    try:
        _, header = next(records)
    except StopIteration:
        raise InputError("the file is empty", source=source) from None
    header = [h.strip() for h in header]
    check_header(header, source)
    need = ("t",) + Q_COLS + I_COLS
    missing = [c for c in need if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)} (a joint log has t,q1..q6,i1..i6)",
                         source=source, row=1)
    known = set(need) | {"pose", "load"} | set(W_COLS)
    unknown = [c for c in header if c not in known]
    if unknown:
        raise InputError(f"unknown column(s) {', '.join(unknown)}", source=source, row=1)
    if ("pose" in header) != ("load" in header):
        raise InputError("give both pose and load columns, or neither", source=source, row=1)
    has_w = [c in header for c in W_COLS]
    if any(has_w) and not all(has_w):
        raise InputError(f"the wrench needs all of {','.join(W_COLS)}", source=source, row=1)
    ix = {c: i for i, c in enumerate(header)}
    t, q, cur, w, pose, load, lines = [], [], [], [], [], [], []
    for line, row in records:
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", source=source, row=line)

        def num(col: str, *, row=row, line=line) -> float:
            try:
                v = float(row[ix[col]])
            except ValueError:
                raise InputError(f"{row[ix[col]]!r} is not a number", source=source, row=line, column=col) from None
            if not math.isfinite(v):
                raise InputError("not a finite number", source=source, row=line, column=col)
            return v

        t.append(parse_time(row[ix["t"]], source=source, line=line, column="t"))
        qv = [num(c) for c in Q_COLS]
        if max(abs(v) for v in qv) > 4 * math.pi:
            raise InputError("joint coordinates beyond 2 turns: q is in radians", source=source, row=line,
                             column="q1")
        q.append(qv)
        cur.append([num(c) for c in I_COLS])
        w.append([num(c) for c in W_COLS] if all(has_w) else [math.nan] * 6)
        if "pose" in ix:
            pose.append(row[ix["pose"]].strip())
            load.append(row[ix["load"]].strip())
        lines.append(line)
    if not t:
        raise InputError("the joint log has no rows", source=source)
    t_arr = np.array(t)
    if np.any(np.diff(t_arr) < 0):
        bad = int(np.flatnonzero(np.diff(t_arr) < 0)[0]) + 1
        raise InputError("time goes backwards; samples in time order", source=source, row=lines[bad], column="t")
    return JointLog(source, t_arr, np.array(q), np.array(cur), np.array(w),
                    np.array(pose, dtype=str) if pose else None, np.array(load, dtype=str) if load else None,
                    np.array(lines))


# ---------------------------------------------------------------- pairing
@dataclass(frozen=True)
class ImportResult:
    table: StaticTable
    paired: tuple[tuple[ExportPoint, int], ...]      # (point, row of the table)
    #: (point, why): the why names the arguments that would pair it as :class:`~elastocal.errors.Arg`
    unpaired: tuple[tuple[ExportPoint, Message], ...]

    def unpaired_line(self, *, command_line: bool = False) -> str:
        """Every unpaired point in one line (its arguments as flags with ``command_line``)."""
        items = [f"{p.source}:{p.line} {p.name} ({say(why, command_line=command_line)})" for p, why in self.unpaired]
        return f"{len(items)} point(s) not paired: " + "; ".join(items)


@dataclass
class _Row:
    point: ExportPoint
    pose: str
    load: str
    marker: str
    t: float
    q: np.ndarray
    wrench: np.ndarray
    currents: np.ndarray


def _identify_point(point: ExportPoint, names: NamePattern | None,
                    markers: tuple[str, ...] | None) -> tuple[dict | None, str, str]:
    """(the pattern's fields or None, the marker, why the point cannot be paired or "")."""
    fields = names.match(point.name) if names is not None else None
    if names is not None and fields is None:
        return None, "", f"name does not match {names.text}"
    marker = fields["marker"] if fields else point.name
    if markers is not None and marker not in markers:
        return fields, marker, f"marker {marker!r} is not one of the robot's ({', '.join(markers)})"
    return fields, marker, ""


def pair_with_log(points: list[ExportPoint], contents: LogContents, *, names: NamePattern | None,
                  by: str, tolerance_s: float = 0.5, clock_offset_s: float = 0.0,
                  markers: tuple[str, ...] | None = None) -> tuple[list[_Row], list[tuple[ExportPoint, str]]]:
    readings = static_readings(contents)
    if not readings:
        raise InputError("the log holds no completed static reading", source=contents.path)
    rows, unpaired = [], []
    queues: dict[tuple[str, str, str], list[StaticReading]] = {}
    for r in readings:
        queues.setdefault((r.pose, r.load, r.marker), []).append(r)
    counts = {k: len(v) for k, v in queues.items()}
    wall = np.array([r.wall_s for r in readings])
    for p in points:
        fields, marker, why = _identify_point(p, names, markers)
        if why:
            unpaired.append((p, why))
            continue
        if by == "name":
            key = (fields["pose"], fields["load"], marker)
            queue = queues.get(key)
            if not queue:
                why = (f"more points than the {counts[key]} reading(s) of pose {key[0]} load {key[1]} marker "
                       f"{marker}" if key in counts else f"no reading of pose {key[0]} load {key[1]} marker "
                       f"{marker} in the log")
                unpaired.append((p, why))
                continue
            r = queue.pop(0)
        else:
            if p.t_s is None:
                unpaired.append((p, "no timestamp"))
                continue
            t = p.t_s + clock_offset_s
            inside = np.flatnonzero((wall[:, 0] <= t) & (t <= wall[:, 1]))      # a window that holds it
            if inside.size == 0:                                                # else one within tolerance
                inside = np.flatnonzero((wall[:, 0] - tolerance_s <= t) & (t <= wall[:, 1] + tolerance_s))
            if inside.size == 0:
                unpaired.append((p, f"no reading within {tolerance_s:g} s of its time"))
                continue
            r = readings[int(inside[np.argmin(np.abs(wall[inside].mean(axis=1) - t))])]
            if r.marker != marker or (fields and (fields["pose"], fields["load"]) != (r.pose, r.load)):
                unpaired.append((p, f"at its time the log read pose {r.pose} load {r.load} marker {r.marker}"))
                continue
        rows.append(_Row(p, r.pose, r.load, r.marker, r.t_s, np.array(r.q), np.array(r.wrench),
                         np.array(r.currents)))
    return rows, unpaired


def pair_with_joints(points: list[ExportPoint], log: JointLog, *, names: NamePattern | None, by: str,
                     window_s: float = 0.5, clock_offset_s: float = 0.0,
                     markers: tuple[str, ...] | None = None) -> tuple[list[_Row], list[tuple[ExportPoint, str]]]:
    rows, unpaired = [], []
    t0 = min((p.t_s for p in points if p.t_s is not None), default=None)
    for p in points:
        fields, marker, why = _identify_point(p, names, markers)
        if why:
            unpaired.append((p, why))
            continue
        if by == "time" or (p.t_s is not None and fields is None):
            if p.t_s is None:
                unpaired.append((p, "no timestamp"))
                continue
            t = p.t_s + clock_offset_s
            sel = np.flatnonzero(np.abs(log.t_s - t) <= window_s / 2)
            if sel.size == 0:
                unpaired.append((p, f"no joint sample within ±{window_s / 2:g} s of its time"))
                continue
            if fields is not None:
                pose, load = fields["pose"], fields["load"]
            elif log.pose is not None:
                states = set(zip(log.pose[sel], log.load[sel]))
                if len(states) != 1:
                    unpaired.append((p, f"the joint log changes pose or load within ±{window_s / 2:g} s"))
                    continue
                pose, load = states.pop()
            else:
                unpaired.append((p, ("neither its name (", Arg("names"), ") nor the joint log (pose, load columns) "
                                     "says its pose and load")))
                continue
        else:   # by name: the samples of its pose and load, around its time when it has one (docs/import.md)
            pose, load = fields["pose"], fields["load"]
            if log.pose is not None:
                sel = np.flatnonzero((log.pose == pose) & (log.load == load))
                if sel.size == 0:
                    unpaired.append((p, f"the joint log has no sample of pose {pose} load {load}"))
                    continue
            elif p.t_s is None:
                unpaired.append((p, "no timestamp, and the joint log has no pose and load columns"))
                continue
            else:
                sel = np.arange(len(log.t_s))
            if p.t_s is not None:
                sel = sel[np.abs(log.t_s[sel] - (p.t_s + clock_offset_s)) <= window_s / 2]
                if sel.size == 0:
                    of = f" of pose {pose} load {load}" if log.pose is not None else ""
                    unpaired.append((p, (f"no joint sample{of} within ±{window_s / 2:g} s of its time "
                                         "(the two clocks apart? ", Arg("clock_offset"), ")")))
                    continue
        t_rel = math.nan if p.t_s is None or t0 is None else p.t_s - t0
        rows.append(_Row(p, pose, load, marker, t_rel, log.q[sel].mean(axis=0), log.wrench[sel].mean(axis=0),
                         log.currents[sel].mean(axis=0)))
    # one pose, one configuration: the mean q of every sample its rows used
    for pose in {r.pose for r in rows}:
        mine = [r for r in rows if r.pose == pose]
        q = np.mean([r.q for r in mine], axis=0)
        for r in mine:
            r.q = q
    return rows, unpaired


def build_table(rows: list[_Row], unpaired: list, *, source: str, robot=None) -> ImportResult:
    if not rows:
        parts: list = ["no point of the export could be paired ("]
        for k, (p, why) in enumerate(unpaired[:3]):
            parts += ["; " if k else "", f"{p.name}: ", *((why,) if isinstance(why, str) else why)]
        parts.append(f"{' …' if len(unpaired) > 3 else ''})")
        raise InputError(parts, source=source)
    extra = {}
    for col, attr in (("u95", "u95_m"), ("temperature_c", "temperature_c"), ("pressure_hpa", "pressure_hpa"),
                      ("humidity_pct", "humidity_pct")):
        values = [getattr(r.point, attr) for r in rows]
        if any(v is not None for v in values):
            extra[col] = np.array([math.nan if v is None else v for v in values], dtype=float)
    try:
        table = static_table_from_arrays(
            pose=[r.pose for r in rows], load=[r.load for r in rows], t=[r.t for r in rows],
            q=[r.q for r in rows], wrench=[r.wrench for r in rows], currents=[r.currents for r in rows],
            marker=[r.marker for r in rows], xyz=[r.point.xyz_m for r in rows], source=source, robot=robot,
            extra=extra)
    except InputError as exc:
        point = rows[exc.row - 2].point if exc.row is not None and 2 <= exc.row < len(rows) + 2 else None
        where = f" (point {point.name}, {point.source} line {point.line})" if point is not None else ""
        raise InputError(f"the paired points do not make a deflection table: {exc.detail}{where}",
                         source=source) from None
    return ImportResult(table, tuple((r.point, i) for i, r in enumerate(rows)), tuple(unpaired))
