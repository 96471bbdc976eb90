"""`elastocal fleet`: identify, diagnose or check every log of a plant, on Dask (docs/fleet.md).

    elastocal fleet identify|diagnose|check PATHS... --out results.csv|results.parquet
        [--scheduler tcp://host:8786 | --workers N] [--pool auto|dask|processes] [--record]
    elastocal fleet history PATHS... [--json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

from elastocal.errors import InputError
from elastocal.model.kinds import KinematicForm, TorqueSource

ACTIONS = ("identify", "diagnose", "check", "history")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=ACTIONS,
                        help="identify, diagnose or check every log; history: the plant's drift table")
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="logs (.mcap), table folders, or folders holding them (searched recursively); "
                             "history: folders holding the cells' cell.toml")
    parser.add_argument("--out", help="the results table: .csv, or .parquet (needs pyarrow)")
    parser.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    parser.add_argument("--cell", help="cell.toml of every input (default: the nearest cell.toml in each "
                                       "input's folder or above)")
    parser.add_argument("--model", default="joint_stiffness",
                        help="comma-separated effects to include (default joint_stiffness)")
    parser.add_argument("--torque", choices=[t.value for t in TorqueSource], default="current",
                        help="joint torques from motor currents (default) or from the wrench columns")
    parser.add_argument("--form", choices=[f.value for f in KinematicForm], default="exact",
                        help="exact (secant, default) or first-order kinematics")
    parser.add_argument("--exclude-outliers", action="store_true",
                        help="identify/diagnose: leave out single readings far off their repeats (as identify's flag)")
    parser.add_argument("--alpha", type=float, default=1e-3, help="check: false-alarm probability (default 0.001)")
    parser.add_argument("--friction-tolerance", type=float, default=0.2,
                        help="check: relative friction change that counts, when significant (default 0.2)")
    run = parser.add_argument_group("where the tasks run")
    run.add_argument("--scheduler", metavar="URL", help="a running Dask scheduler, e.g. tcp://host:8786 "
                                                        "(default: a local cluster)")
    run.add_argument("--workers", type=int, help="worker processes of the local cluster (default: the cores)")
    run.add_argument("--pool", choices=("auto", "dask", "processes"), default="auto",
                     help="auto (default): Dask when installed, else a local process pool; dask; processes")
    parser.add_argument("--record", action="store_true",
                        help="identify/check: record the results in each cell's history (once per log)")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _history(args: argparse.Namespace) -> int:
    from elastocal.acquisition.history import DETERMINED_RELATIVE_STD   # the history's rule (is_determined)
    from elastocal.fleet.plant import plant_drift

    for flag in ("out", "record", "scheduler", "workers", "cell"):
        if getattr(args, flag):
            raise InputError(f"--{flag.replace('_', '-')} is not an option of `fleet history`", source=f"--{flag}")
    cells = plant_drift(args.paths)
    if args.json:
        from elastocal.acquisition.history import clean

        print(json.dumps(clean({"cells": [
            {"cell": c.cell, "cell_config": c.cell_config, "history": c.history, "robot": c.robot,
             "calibrations": c.calibrations, "last_calibration": c.last_calibration,
             "drift": {n: {"unit": u, "first": f, "latest": la, "change": ch, "determined": d}
                       for n, u, f, la, ch, d in c.drift},
             "checks": c.checks, "checks_failed": c.checks_failed, "last_check": c.last_check,
             "last_verdict": c.last_verdict, "error": c.error or None} for c in cells]})))
        return 0
    from elastocal.formats.calibration import is_stiffness_name

    n_joints = max([6] + [int(n[1:]) for c in cells for n, *_ in c.drift if is_stiffness_name(n)])
    stiff = [f"k{j}" for j in range(1, n_joints + 1)]
    width = max([len(c.cell) for c in cells] + [4])
    lines = [f"plant: {len(cells)} cell(s); drift = latest (last calibration or later check) against the first "
             f"calibration; n/d: not determined by the calibrations' data (std > "
             f"{DETERMINED_RELATIVE_STD * 100:.0f} % of the value)",
             f"  {'cell':<{width}}  {'robot':<10}  {'cals':>4}  {'last calibration':<20}  "
             + " ".join(f"{k:>7}" for k in stiff) + f"  {'largest other':<18}  {'checks failed':>13}  last check"]
    for c in cells:
        if c.error:
            lines.append(f"  {c.cell or '?':<{width}}  {c.cell_config}: {c.error}")
            continue
        ks = " ".join(_change(*c.change(k)) for k in stiff)
        big = c.largest(exclude=stiff)
        other_s = f"{big[0]} {big[1] * 100:+.1f}%" if big else "-"
        last = f"{c.last_verdict} {c.last_check}" if c.last_check else "-"
        lines.append(f"  {c.cell:<{width}}  {c.robot[:10]:<10}  {c.calibrations:>4}  "
                     f"{c.last_calibration or '-':<20}  {ks}  {other_s:<18}  "
                     f"{f'{c.checks_failed} of {c.checks}':>13}  {last}")
    print("\n".join(lines))
    return 0


def _change(change: float | None, determined: bool) -> str:
    """A drift as ``+1.23%``; ``n/d`` when the data do not determine the parameter."""
    if change is None:
        return f"{'-':>7}"
    return f"{change * 100:+6.2f}%" if determined else f"{'n/d':>7}"


def _tasks(args: argparse.Namespace, inputs, model: tuple[str, ...]):
    """(tasks, results decided before any task: the checks whose cell has no calibration)."""
    from elastocal.drivers.config import load_cell_config
    from elastocal.fleet import FleetTask, LogResult
    from elastocal.fleet.plant import current_calibration
    from elastocal.fleet.tasks import error_text

    names: dict = {}
    calibrations: dict = {}
    tasks, early = [], {}
    for k, item in enumerate(inputs):
        cfg = None if item.cell_config is None else str(item.cell_config)
        if cfg is not None and cfg not in names:
            try:
                names[cfg] = load_cell_config(cfg).name
            except InputError:
                names[cfg] = ""   # the task reports it where it matters (check); identify reads the log
        cell = names.get(cfg, "") if cfg else ""
        cal = cal_id = None
        if args.action == "check":
            if cfg not in calibrations:
                calibrations[cfg] = current_calibration(cfg)
            cal, cal_id, why = calibrations[cfg]
            if cal is None:
                early[k] = LogResult(path=str(item.path), command="check", cell=cell, cell_config=cfg,
                                     error=error_text(why))
                continue
        tasks.append((k, FleetTask(command=args.action, path=str(item.path), tables=item.tables, cell_config=cfg,
                                   cell=cell, model=model, torque=TorqueSource(args.torque),
                                   form=KinematicForm(args.form),
                                   exclude_outliers=args.exclude_outliers, calibration=cal,
                                   calibration_id=cal_id, alpha=args.alpha,
                                   friction_tolerance=args.friction_tolerance)))
    return tasks, early


def run(args: argparse.Namespace) -> int:
    if args.action == "history":
        return _history(args)
    from elastocal.commands._outputs import Outputs, note
    from elastocal.fleet.discover import find_inputs
    from elastocal.fleet.plant import record_results
    from elastocal.fleet.pool import INSTALL_HINT, resolve_pool
    from elastocal.fleet.table import write_table
    from elastocal.model.effects import parse_model

    kind = _refuse_flags(args)
    model = parse_model(args.model)
    pool = resolve_pool(args.pool, args.scheduler)
    if pool == "processes" and args.pool == "auto":
        note(args, f"note: dask.distributed is not installed, so the tasks ran on a local process pool; "
                   f"for Dask (and --scheduler): {INSTALL_HINT}")
    inputs = find_inputs(args.paths, cell_config=args.cell)
    outputs = Outputs(force=args.force, inputs=[(str(i.path), "a fleet input") for i in inputs if not i.tables])
    outputs.add(args.out, "--out")
    tasks, early = _tasks(args, inputs, model)
    start = time.perf_counter()
    ordered = _results(args, tasks, early, len(inputs), pool)
    with outputs:
        write_table(outputs.temp(args.out), ordered, kind)
    seconds = time.perf_counter() - start
    recorded = record_results(ordered, now_ns=time.time_ns()) if args.record else None
    n_workers = None if args.scheduler else (args.workers or _cores())
    if args.json:
        print(json.dumps(_summary_json(args, ordered, pool, n_workers, seconds, recorded)))
    else:
        print("\n".join(_summary_lines(args, ordered, pool, n_workers, seconds, recorded)))
    return 0


def _refuse_flags(args: argparse.Namespace) -> str:
    """The results table's format, after refusing the flags that do not go together with the action
    or with each other, before any work."""
    from elastocal.fleet.table import table_format

    if not args.out:
        raise InputError(f"fleet {args.action} needs --out results.csv or results.parquet", source="--out")
    kind = table_format(args.out)
    if args.exclude_outliers and args.action == "check":
        raise InputError("a check compares every reading with the calibration; --exclude-outliers is for "
                         "identify and diagnose", source="--exclude-outliers")
    if args.record and args.action == "diagnose":
        raise InputError("diagnoses are not kept in the history; --record goes with fleet identify or check",
                         source="--record")
    if not 0.0 < args.alpha < 1.0:
        raise InputError(f"must be between 0 and 1, got {args.alpha}", source="--alpha")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"must be at least 1, got {args.workers}", source="--workers")
    if args.scheduler and args.workers is not None:
        raise InputError("the scheduler's workers do the work; --workers sizes a local cluster", source="--workers")
    return kind


def _results(args: argparse.Namespace, tasks: list, early: dict, n_inputs: int, pool: str) -> list:
    """Every input's result in the inputs' order: the tasks run on the pool, with one progress line
    counting the results decided before any task (checks without a calibration) as done and failed."""
    from elastocal.fleet.pool import run_tasks
    from elastocal.progress import Progress

    done_early = len(early)
    failed_early = len(early)
    progress = Progress(f"fleet {args.action}", len(tasks) + done_early, quiet=args.json)

    def shown(done: int, total: int, failed: int, result) -> None:
        label = "" if result is None else str(getattr(result, "path", "") or "")
        progress(done + done_early, pathlib.Path(label).name if label else "tasks",
                 total=total + done_early, failed=failed + failed_early)

    if not tasks and early:
        progress(len(early), "inputs", failed=len(early))
    ran = run_tasks([t for _, t in tasks], pool=pool, scheduler=args.scheduler, workers=args.workers,
                    progress=shown)
    results = dict(early)
    results.update({k: r for (k, _), r in zip(tasks, ran)})
    return [results[k] for k in range(n_inputs)]


def _summary_json(args: argparse.Namespace, ordered: list, pool: str, n_workers: int | None, seconds: float,
                  recorded) -> dict:
    """The ``--json`` object of a fleet run (docs/cli.md)."""
    failures = [r for r in ordered if not r.ok]
    obj = {"action": args.action, "out": args.out, "pool": pool, "scheduler": args.scheduler,
           "workers": n_workers, "inputs": len(ordered), "ok": len(ordered) - len(failures),
           "failed": len(failures), "seconds": seconds,
           "failures": [{"path": r.path, "error": r.error} for r in failures],
           "recorded": None if recorded is None else {
               "calibrations": recorded.calibrations, "checks": recorded.checks, "already": recorded.already,
               "histories": list(recorded.histories),
               "not_recorded": [{"path": p, "why": w} for p, w in recorded.not_recorded]}}
    if args.action == "check":
        obj["recalibrate"] = [r.path for r in ordered if r.decision == "recalibrate"]
    return obj


def _summary_lines(args: argparse.Namespace, ordered: list, pool: str, n_workers: int | None, seconds: float,
                   recorded) -> list[str]:
    """The text summary of a fleet run: counts, failures, the checks that say recalibrate, the history."""
    failures = [r for r in ordered if not r.ok]
    where = args.scheduler or ("a Dask LocalCluster" if pool == "dask" else "a local process pool")
    workers_s = "" if n_workers is None else f" ({n_workers} worker{'s' if n_workers != 1 else ''})"
    lines = [f"fleet {args.action}: {len(ordered)} input(s), {len(ordered) - len(failures)} ok, "
             f"{len(failures)} failed, in {seconds:.1f} s on {where}{workers_s}"]
    for r in failures:
        lines.append(f"  failed: {r.path}: {r.error}")
    if args.action == "check":
        bad = [r for r in ordered if r.decision == "recalibrate"]
        lines.append(f"  {len(bad)} check(s) say recalibrate" + (":" if bad else ""))
        lines += [f"    {r.cell or '?'}: {r.path}" for r in bad]
    lines.append(f"results written to {args.out}")
    if recorded is not None:
        lines.append(f"recorded {recorded.calibrations} calibration(s) and {recorded.checks} check(s) in "
                     f"{len(recorded.histories)} histor{'y' if len(recorded.histories) == 1 else 'ies'}; "
                     f"{recorded.already} already recorded")
        for path, why in recorded.not_recorded:
            lines.append(f"  not recorded: {path}: {why}")
    return lines


def _cores() -> int:
    from elastocal.fleet.pool import default_workers

    return default_workers()
