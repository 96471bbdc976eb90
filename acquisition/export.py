"""Turn an elastocal MCAP log into the robot, static table and run table (docs/formats.md §2-3).

The log is read by :mod:`elastocal.acquisition.logreader`; :func:`load_log` turns
its samples and events into the tables the identification uses; :func:`export_log`
writes them as files. Tables are built from raw samples by fixed rules
(docs/log-format.md), so identifying from the log and from the exported tables
gives the same result. The reverse, a log written from tables, is
:mod:`elastocal.acquisition.logwriter`.

Only steps whose ``step_done`` event is in the log contribute rows: a pose
interrupted between its unloaded reference and its loads is left out whole.
"""

from __future__ import annotations

import datetime
import pathlib
from dataclasses import dataclass

import numpy as np

from elastocal.formats import logformat as lf
from elastocal.acquisition.logreader import SEGMENT_NS, LogContents, read_log
from elastocal.errors import Arg, InputError
from elastocal.model.robot import Robot
from elastocal.formats.robot_toml import parse_robot
from elastocal.formats.tables import (
    RunTable,
    StaticTable,
    run_table_from_arrays,
    static_table_from_arrays,
    write_run_table,
    write_static_table,
)


def _key(event: dict, t_ns: int) -> int:
    return int(event["segment"]) * SEGMENT_NS + int(t_ns)


def _window(t_ns: np.ndarray, start: int, end: int) -> slice:
    return slice(int(np.searchsorted(t_ns, start, side="left")), int(np.searchsorted(t_ns, end, side="right")))


def _time_origin(contents: LogContents) -> int:
    """Origin of the ``t`` columns: the first ``procedure_start`` of the log (a
    resumed log keeps the one of the log it continues)."""
    for e in contents.events:
        if e["kind"] == "procedure_start":
            return int(e["t_ns"])
    return min(e["t_ns"] for e in contents.events) if contents.events else 0


def _wrench(value) -> list[float]:
    if value is None:
        return [float("nan")] * 6
    return [float(x) for x in value]


@dataclass(frozen=True)
class StaticReading:
    """One ``reading`` event of a completed static step and what the log holds for it."""

    pose: str
    load: str
    marker: str
    window: tuple[int, int]         # sample keys (session * SEGMENT_NS + monotonic ns)
    t_s: float                      # the window's middle, seconds from the log's time origin
    q: tuple[float, ...]            # commanded pose [rad]
    wrench: tuple[float, ...]       # nominal load [N, N·m], NaN when unknown
    currents: tuple[float, ...]     # mean current of each drive over the window [A], NaN without samples
    wall_s: tuple[float, float]     # the window on the UTC clock of its session (epoch seconds)
    no_sample: tuple[int, ...] = ()  # joints whose drive has no sample in the window (a broken log)


def static_readings(contents: LogContents) -> list[StaticReading]:
    """The ``reading`` events of the log's completed static steps, in log order (the rows
    :func:`static_table_from_log` makes, without the tracker's positions)."""
    done = set(contents.completed_steps)
    origin = _time_origin(contents)
    out = []
    for e in contents.events:
        if e["kind"] != "reading" or e.get("step_id") not in done:
            continue
        start, end = (_key(e, v) for v in e["window_ns"])
        cur = []
        no_sample = []
        for j, d in enumerate(contents.drives, start=1):
            dsl = _window(d.t_ns, start, end)
            cur.append(float(_mean(d.current_a[dsl])) if dsl.stop > dsl.start else float("nan"))
            if dsl.stop <= dsl.start:
                no_sample.append(j)
        session = contents.sessions[min(int(e["segment"]), len(contents.sessions) - 1)]
        wall0 = _utc_seconds(session["started_utc"], contents.path) - int(session["monotonic_ns"]) * 1e-9
        out.append(StaticReading(
            pose=str(e["pose"]), load=str(e["load"]), marker=str(e["marker"]), window=(start, end),
            t_s=((start + end) // 2 - e["segment"] * SEGMENT_NS - origin) * 1e-9,
            q=tuple(float(v) for v in e["q"]), wrench=tuple(_wrench(e.get("wrench"))), currents=tuple(cur),
            wall_s=tuple(wall0 + int(v) * 1e-9 for v in e["window_ns"]), no_sample=tuple(no_sample)))
    return out


def _mean(x: np.ndarray) -> np.ndarray:
    """The mean of a window's samples (along the first axis) about its first sample: equal samples
    give that sample exactly, whatever their number (a plain sum of n equal values can end a last bit
    off, so two windows of one reading holding 2 or 3 samples would differ in a last digit)."""
    return x[0] + np.mean(x - x[0], axis=0)


def _utc_seconds(text: str, source: str) -> float:
    try:
        dt = datetime.datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"session start {text!r} is not an ISO 8601 time", source=source) from None
    return (dt if dt.tzinfo else dt.replace(tzinfo=datetime.timezone.utc)).timestamp()


def static_table_from_log(contents: LogContents, robot: Robot | None = None) -> StaticTable | None:
    """The static deflection table of the log's completed static steps, or None.

    One row per ``reading`` event: the mean tracker position of its marker and
    the mean current of each drive over the reading's window; ``t`` is the
    window's middle in seconds from the log's first event; ``q`` and the wrench
    are the commanded pose and the nominal load the event names.
    """
    readings = static_readings(contents)
    if not readings:
        return None
    if not contents.markers:
        raise InputError(("the log has readings but no tracker sample (its tracker was read by its own "
                          "software): pair that software's export with the log (docs/import.md: `import` "
                          "with ", Arg("log", "LOG.mcap"), ")"), source=contents.path)
    pose, load, t, q, wrench, currents, marker, xyz = [], [], [], [], [], [], [], []
    for r in readings:
        start, end = r.window
        if r.no_sample:     # a recorded reading always has every drive's samples: the log lost some
            raise InputError(f"drive(s) {', '.join(f'J{j}' for j in r.no_sample)} have no sample in the window "
                             f"of the reading of marker {r.marker} at pose {r.pose} load {r.load}: the log "
                             "lacks that drive's messages, and its current column would be blank",
                             source=contents.path)
        samples = contents.markers.get(r.marker)
        sl = _window(samples.t_ns, start, end) if samples is not None else slice(0, 0)
        if samples is None or sl.stop <= sl.start:
            raise InputError(f"reading of marker {r.marker} at pose {r.pose} load {r.load} has no tracker sample "
                             f"in its window", source=contents.path)
        xyz.append(_mean(samples.xyz[sl]))
        currents.append(list(r.currents))
        pose.append(r.pose)
        load.append(r.load)
        t.append(r.t_s)
        q.append(list(r.q))
        wrench.append(list(r.wrench))
        marker.append(r.marker)
    try:
        return static_table_from_arrays(pose=pose, load=load, t=t, q=q, wrench=wrench, currents=currents,
                                        marker=marker, xyz=xyz, source=contents.path, robot=robot)
    except InputError as exc:
        raise InputError(f"the log's static readings do not make a deflection table: {_exported_at(exc, 'static')}",
                         source=contents.path) from None


def _exported_at(exc: InputError, table: str) -> str:
    """An error of a table built from a log, with where it is in the exported CSV."""
    where = [f"line {exc.row}"] if exc.row is not None else []
    where += [f"column {exc.column}"] if exc.column else []
    return f"{exc.detail} ({', '.join(where)} of the exported {table}.csv)" if where else exc.detail


def run_table_from_log(contents: LogContents, robot: Robot | None = None) -> RunTable | None:
    """The run table of the log's completed runs (friction runs, sweeps), or None.

    One row per sample of drive 1 between ``run_start`` and ``run_end``; the
    other drives contribute their sample nearest in time, the followed marker
    its nearest tracker sample when it lies within half a drive period.
    """
    done = set(contents.completed_steps)
    starts = {}
    runs = []
    for e in contents.events:
        if e["kind"] == "run_start":
            starts[e["run"]] = e
        elif e["kind"] == "run_end" and e["run"] in starts and e.get("step_id") in done:
            runs.append((starts.pop(e["run"]), e))
    if not runs:
        return None
    origin = _time_origin(contents)
    cols: dict[str, list] = {k: [] for k in ("run", "direction", "load", "t", "q", "dq", "i", "w", "marker", "xyz")}
    ref = contents.drives[0]
    for start, end in runs:
        sl = _window(ref.t_ns, _key(start, start["t_ns"]), _key(end, end["t_ns"]))
        t_rows = ref.t_ns[sl]
        n = len(t_rows)
        if n == 0:
            raise InputError(f"run {start['run']} has no drive samples", source=contents.path)
        nj = len(contents.drives)
        q = np.empty((n, nj))
        dq = np.empty((n, nj))
        cur = np.empty((n, nj))
        for j, d in enumerate(contents.drives):
            if len(d.t_ns) == 0:
                raise InputError(f"run {start['run']}: drive {j + 1} has no samples", source=contents.path)
            idx = _nearest(d.t_ns, t_rows)
            q[:, j] = d.position_rad[idx]
            dq[:, j] = d.velocity_rad_s[idx]
            cur[:, j] = d.current_a[idx]
        mname = start.get("marker") or ""
        xyz = np.full((n, 3), np.nan)
        marker = np.full(n, "", dtype=object)
        if mname and mname in contents.markers and n > 1:
            tr = contents.markers[mname]
            period = float(np.median(np.diff(t_rows)))
            idx = _nearest(tr.t_ns, t_rows)
            ok = np.abs(tr.t_ns[idx] - t_rows) <= 0.5 * period
            xyz[ok] = tr.xyz[idx[ok]]
            marker[ok] = mname
        cols["run"] += [str(start["run"])] * n
        cols["direction"] += [str(start["direction"])] * n
        cols["load"] += [str(start.get("load", "0"))] * n
        cols["t"].append((t_rows - start["segment"] * SEGMENT_NS - origin) * 1e-9)
        cols["q"].append(q)
        cols["dq"].append(dq)
        cols["i"].append(cur)
        cols["w"].append(np.tile(_wrench(start.get("wrench")), (n, 1)))
        cols["marker"] += list(marker)
        cols["xyz"].append(xyz)
    try:
        return run_table_from_arrays(run=cols["run"], direction=cols["direction"], load=cols["load"],
                                     t=np.concatenate(cols["t"]), q=np.concatenate(cols["q"]),
                                     dq=np.concatenate(cols["dq"]), currents=np.concatenate(cols["i"]),
                                     wrench=np.concatenate(cols["w"]), marker=cols["marker"],
                                     xyz=np.concatenate(cols["xyz"]), source=contents.path, robot=robot)
    except InputError as exc:
        raise InputError(f"the log's runs do not make a run table: {_exported_at(exc, 'runs')}",
                         source=contents.path) from None


def _nearest(t_sorted: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Index of the sample of ``t_sorted`` nearest to each query time."""
    right = np.searchsorted(t_sorted, t_query, side="left").clip(0, len(t_sorted) - 1)
    left = (right - 1).clip(0, len(t_sorted) - 1)
    pick_left = np.abs(t_query - t_sorted[left]) <= np.abs(t_sorted[right] - t_query)
    return np.where(pick_left, left, right)


def robot_from_log(contents: LogContents) -> Robot:
    if contents.robot is None:
        raise InputError("the log holds no robot description", source=contents.path)
    return parse_robot(contents.robot.text, source=f"{contents.path} ({lf.TOPIC_ROBOT})")


def load_log(path: str | pathlib.Path) -> tuple[Robot, StaticTable | None, RunTable | None]:
    """Robot, static table and run table of a log (each table None when the log has none)."""
    return tables_from_log(read_log(path))


def tables_from_log(contents: LogContents) -> tuple[Robot, StaticTable | None, RunTable | None]:
    """Robot, static table and run table of a log already read."""
    robot = robot_from_log(contents)
    return robot, static_table_from_log(contents, robot), run_table_from_log(contents, robot)


@dataclass(frozen=True)
class ExportResult:
    files: tuple[str, ...]
    static_rows: int
    run_rows: int
    complete: bool
    truncated: bool
    incomplete_steps: tuple[str, ...]


def tracker_position_from_log(contents: LogContents) -> tuple[float, float, float] | None:
    """Where the cell.toml the log carries says the tracker stands (``[tracker]
    base_p_tracker``, base coordinates [m]), or None when it does not say (no cell
    document, an empty one, no such key, or text that is no TOML: a procedure run
    without a cell file records an empty one). Only this key is read: the rest of
    the cell file was the recording's business. A key that is there but not three
    finite numbers is an error naming the log."""
    import math

    tracker = _cell_tracker_table(contents)
    if tracker is None or "base_p_tracker" not in tracker:
        return None
    v = tracker["base_p_tracker"]
    if not (isinstance(v, list) and len(v) == 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise InputError(f"expected 3 finite numbers [m], got {v!r}", source=f"{contents.path} ({lf.TOPIC_CELL})",
                         column="tracker.base_p_tracker")
    return tuple(float(x) for x in v)


def tracker_noise_from_log(contents: LogContents):
    """The tracker noise law the cell.toml the log carries states (``[tracker] noise``,
    model/tracker_noise.py), or None when it does not say (as :func:`tracker_position_from_log`);
    a table that is there but malformed is an error naming the log."""
    from elastocal.model.tracker_noise import parse_tracker_noise

    tracker = _cell_tracker_table(contents)
    if tracker is None or "noise" not in tracker:
        return None
    return parse_tracker_noise(tracker["noise"], source=f"{contents.path} ({lf.TOPIC_CELL})")


def export_files(contents: LogContents) -> dict[str, str | StaticTable | RunTable | None]:
    """What an export of a log writes: file name -> its text or table (None:
    the log has none, e.g. no static experiment)."""
    robot, static, runs = tables_from_log(contents)
    return {"robot.toml": contents.robot.text,
            "cell.toml": None if contents.cell is None else contents.cell.text,
            "plan.toml": None if contents.plan is None else contents.plan.text,
            "static.csv": static, "runs.csv": runs}


def write_export_file(path: str | pathlib.Path, what: str | StaticTable | RunTable) -> None:
    """One file of :func:`export_files` at ``path``."""
    if isinstance(what, StaticTable):
        write_static_table(path, what)
    elif isinstance(what, RunTable):
        write_run_table(path, what)
    else:
        pathlib.Path(path).write_text(what, encoding="utf-8")


def export_log(path: str | pathlib.Path, out_dir: str | pathlib.Path) -> ExportResult:
    """Write ``robot.toml``, ``static.csv`` and/or ``runs.csv`` (and the recorded
    ``cell.toml`` and ``plan.toml``) of a log into ``out_dir``."""
    contents = read_log(path)
    writes = export_files(contents)
    out = pathlib.Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create: {exc.strerror}", source=str(out)) from None
    files = []
    for name, what in writes.items():
        if what is not None:
            write_export_file(out / name, what)
            files.append(str(out / name))
    return ExportResult(files=tuple(files), static_rows=_rows(writes["static.csv"]),
                        run_rows=_rows(writes["runs.csv"]), complete=contents.complete,
                        truncated=contents.truncated, incomplete_steps=contents.incomplete_steps)


def _rows(table) -> int:
    return 0 if table is None else len(table)


def _cell_tracker_table(contents: LogContents) -> dict | None:
    """The ``[tracker]`` table of the cell.toml a log carries, or None when the log carries no
    cell document, an empty one, text that is no TOML, or no such table."""
    if contents.cell is None or not contents.cell.text.strip():
        return None
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    try:
        doc = tomllib.loads(contents.cell.text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError:
        return None
    tracker = doc.get("tracker")
    return tracker if isinstance(tracker, dict) else None
