"""Write a log from tables (datasets made without devices, e.g. ``elastocal sim``),
so that the export of the log gives the tables back (docs/log-format.md)."""

from __future__ import annotations

import pathlib

import numpy as np

from elastocal.errors import InputError
from elastocal.model.robot import Robot
from elastocal.formats.tables import RunTable, StaticTable


# ------------------------------------------------------------------ tables -> log
class _SetClock:
    """A clock the writer of a synthetic log sets before each event."""

    def __init__(self, t_ns: int) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


#: log time of the first event of a log written from tables [ns]
SYNTHETIC_ORIGIN_NS = 1_000_000_000_000


#: spacing of rows that have no usable time [ns]
SYNTHETIC_SLOT_NS = 10_000_000


def _row_times(t: np.ndarray, start_ns: int) -> np.ndarray:
    """Log times of table rows: their own ``t`` when finite, >= 0 and strictly
    increasing, else one slot per row."""
    if len(t) and np.all(np.isfinite(t)) and t[0] >= 0 and np.all(np.diff(t) > 0):
        times = start_ns + np.round(t * 1e9).astype(np.int64)
        if len(times) < 2 or np.all(np.diff(times) > 1_000):
            return times
    return start_ns + SYNTHETIC_SLOT_NS * (1 + np.arange(len(t), dtype=np.int64))


def _opt(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def _write_static(rec, clock: _SetClock, static: StaticTable) -> int:
    """One step per pose, one reading window per row; the time after the last [ns]."""
    times = _row_times(static.t, SYNTHETIC_ORIGIN_NS)
    order = {p: i for i, p in enumerate(dict.fromkeys(static.pose))}
    for p in order:
        rows = np.flatnonzero(static.pose == p)
        step_id = f"static/{p}"
        clock.t_ns = int(times[rows[0]]) - 2_000
        rec.event("step_start", procedure="static", step_id=step_id)
        for r in rows:
            t = int(times[r])
            for j in range(static.n_joints):
                rec.drive_sample(j + 1, t, float(static.q[r, j]), 0.0, _opt(static.currents[r, j]))
            rec.tracker_sample(t, str(static.marker[r]), static.xyz[r])
            clock.t_ns = t + 500
            w = static.wrench[r]
            rec.event("reading", step_id=step_id, pose=str(p), load=str(static.load[r]),
                      marker=str(static.marker[r]), q=[float(v) for v in static.q[r]],
                      wrench=None if not np.all(np.isfinite(w)) else [float(v) for v in w],
                      window_ns=[t - 500, t + 500])
        clock.t_ns = int(times[rows[-1]]) + 1_000
        rec.event("step_done", procedure="static", step_id=step_id)
    return int(times.max()) + 1_000_000_000


def _write_runs(rec, clock: _SetClock, runs: RunTable, now: int) -> int:
    """One step per run, from ``now`` on (runs that overlap in time moved after one another);
    the time after the last [ns]."""
    for run_id in dict.fromkeys(runs.run):
        rows = np.flatnonzero(runs.run == run_id)
        for name, col in (("load", runs.load), ("wrench", runs.wrench)):
            vals = col[rows]
            same = np.all(vals == vals[0]) if vals.dtype.kind in "US" else \
                np.allclose(vals, vals[0], equal_nan=True, rtol=0, atol=0)
            if not same:
                raise InputError(f"run {run_id}: the {name} changes within the run; a log run has one",
                                 source=runs.source)
        t = runs.t[rows]
        rel = _row_times(t - t[0], 0) if np.all(np.isfinite(t)) else _row_times(t, 0)
        start = now if not np.isfinite(t[0]) else max(now, SYNTHETIC_ORIGIN_NS + int(round(t[0] * 1e9)) - 2_000)
        times = start + 2_000 + rel - rel[0]
        step_id = f"runs/{run_id}"
        clock.t_ns = start
        rec.event("step_start", procedure="runs", step_id=step_id)
        clock.t_ns = start + 1_000
        w = runs.wrench[rows[0]]
        markers = sorted({m for m in runs.marker[rows] if m})
        if len(markers) > 1:
            raise InputError(f"run {run_id} follows several markers ({', '.join(markers)}); a log run "
                             f"follows one", source=runs.source)
        rec.event("run_start", step_id=step_id, run=str(run_id), direction=str(runs.direction[rows[0]]),
                  load=str(runs.load[rows[0]]), marker=markers[0] if markers else None,
                  wrench=None if not np.all(np.isfinite(w)) else [float(v) for v in w])
        for r, tn in zip(rows, times):
            tn = int(tn)
            for j in range(runs.n_joints):
                rec.drive_sample(j + 1, tn, float(runs.q[r, j]), _opt(runs.dq[r, j]),
                                 _opt(runs.currents[r, j]))
            if runs.marker[r]:
                rec.tracker_sample(tn, str(runs.marker[r]), runs.xyz[r])
        clock.t_ns = int(times[-1]) + 1_000
        rec.event("run_end", step_id=step_id, run=str(run_id), direction=str(runs.direction[rows[0]]))
        rec.event("step_done", procedure="runs", step_id=step_id)
        now = clock.t_ns + 1_000_000_000
    return now


def write_log_from_tables(path: str | pathlib.Path, robot: Robot, *, static: StaticTable | None = None,
                          runs: RunTable | None = None, overwrite: bool = True, cell_text: str | None = None,
                          started_unix_ns: int | None = None) -> None:
    """Write a log whose export gives back ``static`` and ``runs`` (datasets made
    without devices, e.g. ``elastocal sim``): one reading window per static row
    holding exactly that row's tracker sample and currents, one drive sample per
    run row. ``q``, currents, wrenches and positions come back bit for bit; ``t``
    comes back to the nanosecond when the table's times are increasing, else as
    10 ms slots; runs that overlap in time are moved after one another.
    ``cell_text``: a cell.toml recorded with the log, as ``calibrate`` records its cell.
    ``started_unix_ns``: when the log says it was measured (its session's wall-clock
    start, UTC ns; default now), e.g. the dates of a simulated plant's logs.
    """
    import time

    from elastocal.acquisition.recorder import Recorder

    clock = _SetClock(SYNTHETIC_ORIGIN_NS)
    unix_clock = time.time_ns if started_unix_ns is None else (lambda: int(started_unix_ns))
    with Recorder(path, overwrite=overwrite, clock=clock, unix_clock=unix_clock) as rec:
        rec.document("robot", robot.name, robot.to_toml())
        if cell_text is not None:
            rec.document("cell", "cell", cell_text)
        rec.event("procedure_start", procedure="from-tables")
        now = SYNTHETIC_ORIGIN_NS - 1_000_000  # step events may precede the origin
        if static is not None and len(static):
            now = _write_static(rec, clock, static)
        if runs is not None and len(runs):
            now = _write_runs(rec, clock, runs, now)
        clock.t_ns = now
        rec.event("procedure_end", status="completed")
