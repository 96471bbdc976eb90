"""A plant's histories: recording fleet results, and the drift of every cell.

:func:`record_results` puts each result into the SQLite history of its cell
(docs/history.md; the schema is unchanged), from the calling process only —
the workers never write — and idempotently by log hash: a calibration
identified from a log is recorded once per model and torque source, a check
once per calibration (as ``elastocal check`` does). A record's time is when
its log was measured (the log's first session), so replaying old logs does not
make their calibrations newer than the ones recorded since.

:func:`plant_drift` reads every cell's history under some folders: last
calibration, the parameters' drift, checks failed.
"""

from __future__ import annotations

import math
import os
import pathlib
from dataclasses import dataclass
from typing import Sequence

from elastocal.errors import Arg, InputError
from elastocal.fleet.discover import CELL_FILE
from elastocal.fleet.tasks import LogResult


@dataclass(frozen=True)
class Recorded:
    """What :func:`record_results` did."""

    calibrations: int                           # newly recorded
    checks: int
    already: int                                # results that were in their history already
    not_recorded: tuple[tuple[str, str], ...]   # (path, why) of successful results without a history
    histories: tuple[str, ...]                  # the databases written to


def _history_of(cell_config: str | None, cache: dict) -> tuple[pathlib.Path | None, str]:
    """(history database of the cell config, or None and why not)."""
    if cell_config is None:
        return None, f"no {CELL_FILE} in its folder or above (the cell, and its history, are unknown)"
    if cell_config not in cache:
        from elastocal.drivers.config import load_cell_config

        try:
            db = load_cell_config(cell_config).history
        except InputError as exc:
            cache[cell_config] = (None, str(exc))
        else:
            cache[cell_config] = (db, "") if db is not None else (None, f"{cell_config} names no history "
                                                                        "([cell] history = ...)")
    return cache[cell_config]


def record_results(results: Sequence[LogResult], *, now_ns: int) -> Recorded:
    """Record the successful identify and check results in their cells' histories."""
    from elastocal.acquisition.history import History

    by_db: dict[pathlib.Path, list[LogResult]] = {}
    skipped: list[tuple[str, str]] = []
    cache: dict = {}
    for r in results:
        if not r.ok or r.command not in ("identify", "check"):
            continue
        db, why = _history_of(r.cell_config, cache)
        if db is None:
            skipped.append((r.path, why))
            continue
        by_db.setdefault(db, []).append(r)
    n_cal = n_check = already = 0
    for db, group in by_db.items():
        with History(db) as h:
            known_checks = {c.id for c in h.checks()}
            for r in group:
                time_ns = r.time_ns if r.time_ns is not None else now_ns
                log_path = str(pathlib.Path(r.path).resolve())
                if r.command == "identify":
                    cal = r.calibration
                    same = [c for c in h.calibrations_from_log(r.sha256)
                            if c.calibration.model == cal.model and c.calibration.torque == cal.torque]
                    if same:
                        already += 1
                        continue
                    h.add_calibration(cal, time_ns=time_ns, log_sha256=r.sha256, log_path=log_path, plan=r.plan)
                    n_cal += 1
                else:
                    rid = h.add_check(calibration_id=r.calibration_id, time_ns=time_ns, verdict=r.decision,
                                      reasons=r.check["reasons"], result=r.check, log_sha256=r.sha256,
                                      log_path=log_path)
                    if rid in known_checks:
                        already += 1
                    else:
                        known_checks.add(rid)
                        n_check += 1
    return Recorded(calibrations=n_cal, checks=n_check, already=already, not_recorded=tuple(skipped),
                    histories=tuple(str(db) for db in by_db))


# --------------------------------------------------------------- plant drift
@dataclass(frozen=True)
class CellDrift:
    """One cell of the plant: its history summed up (``error`` when it has none or it cannot be read)."""

    cell: str
    cell_config: str
    history: str | None
    robot: str = ""
    calibrations: int = 0
    last_calibration: str | None = None         # UTC, ISO 8601
    #: (name, unit, first, latest, change, determined): change relative to the first calibration; determined is
    #: False when the first or the last calibration leaves the parameter undetermined
    drift: tuple[tuple[str, str, float, float, float | None, bool], ...] = ()
    checks: int = 0
    checks_failed: int = 0
    last_check: str | None = None
    last_verdict: str | None = None
    error: str = ""

    def change(self, name: str) -> tuple[float | None, bool]:
        """(relative change of ``name``, whether it is determined); (None, False) when never calibrated."""
        return next(((c, d) for n, _, _, _, c, d in self.drift if n == name), (None, False))

    def largest(self, exclude: Sequence[str] = ()) -> tuple[str, float] | None:
        """The determined parameter (not in ``exclude``) that moved most, and its relative change."""
        moved = [(n, c) for n, _, _, _, c, d in self.drift
                 if d and n not in exclude and c is not None and math.isfinite(c)]
        return max(moved, key=lambda nc: abs(nc[1])) if moved else None


def find_cell_configs(paths: Sequence[str | pathlib.Path]) -> list[pathlib.Path]:
    """Every ``cell.toml`` in or under ``paths`` (files or folders), in path order."""
    found: dict[pathlib.Path, None] = {}
    for given in paths:
        p = pathlib.Path(given)
        if not p.exists():
            raise InputError("no such file or folder", source=str(given))
        if p.is_file():
            found.setdefault(p, None)
            continue
        for folder, dirs, files in os.walk(p):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            if CELL_FILE in files:
                found.setdefault(pathlib.Path(folder) / CELL_FILE, None)
    if not found:
        raise InputError(f"no {CELL_FILE} found", source=", ".join(str(p) for p in paths))
    return sorted(found, key=str)


def cell_drift(cell_config: pathlib.Path) -> CellDrift:
    """The summary of one cell's history."""
    from elastocal.acquisition.history import History, drift_summary
    from elastocal.drivers.config import load_cell_config

    try:
        config = load_cell_config(cell_config)
    except InputError as exc:
        return CellDrift(cell="", cell_config=str(cell_config), history=None, error=str(exc))
    base = {"cell": config.name, "cell_config": str(cell_config)}
    if config.history is None:
        return CellDrift(**base, history=None, error="names no history ([cell] history = ...)")
    if not config.history.exists():
        return CellDrift(**base, history=str(config.history), error="no history yet")
    try:
        with History(config.history, create=False) as h:
            cals = h.calibrations()
            checks = h.checks()
            drift_data = h.drift()
    except InputError as exc:
        return CellDrift(**base, history=str(config.history), error=str(exc))
    summary = drift_summary(drift_data)
    drift = tuple((name, str(p["unit"]), float(p["first"]), float(p["latest"]), p["change"],
                   p["determined"]) for name, p in summary.items())
    return CellDrift(**base, history=str(config.history), robot=cals[-1].robot if cals else "",
                     calibrations=len(cals), last_calibration=cals[-1].time if cals else None, drift=drift,
                     checks=len(checks), checks_failed=sum(c.verdict == "recalibrate" for c in checks),
                     last_check=checks[-1].time if checks else None,
                     last_verdict=checks[-1].verdict if checks else None)


def plant_drift(paths: Sequence[str | pathlib.Path]) -> list[CellDrift]:
    """:func:`cell_drift` of every cell config under ``paths``."""
    return [cell_drift(p) for p in find_cell_configs(paths)]


def current_calibration(cell_config: str | pathlib.Path | None):
    """(the calibration in force in the cell's history, its id, None) -- or (None, None, an
    :class:`InputError` saying why not: the caller says it, ``fleet.tasks.error_text``)."""
    from elastocal.acquisition.history import History
    from elastocal.drivers.config import load_cell_config

    if cell_config is None:
        return None, None, InputError((f"no {CELL_FILE} in its folder or above: a check needs the cell's history "
                                       "(or give ", Arg("cell"), ")"))
    try:
        config = load_cell_config(cell_config)
        if config.history is None:
            return None, None, InputError("names no history ([cell] history = ...), so no calibration to check",
                                          source=str(cell_config))
        with History(config.history, create=False) as h:
            rec = h.current()
    except InputError as exc:
        return None, None, exc
    if rec is None:
        return None, None, InputError("the history holds no calibration; record one first",
                                      source=str(config.history))
    return rec.calibration, rec.id, None
