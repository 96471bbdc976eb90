"""`elastocal check`: does the current calibration still hold? (docs/check.md)

    elastocal check --cell cell.toml [--sim --yes]            run the plan's [check] on the cell
    elastocal check --cell cell.toml --log check.mcap          a check already recorded
    elastocal check --cell cell.toml --static check.csv [--runs runs.csv]   data given directly

Exit 0: the calibration holds; 3: recalibrate (the reason on stdout); 2 bad
input; 1 device fault. The verdict is recorded in the cell's history.
"""

from __future__ import annotations

from elastocal.commands._flags import add_aliased

import argparse
import dataclasses
import json
import pathlib
import sys
import time

from elastocal.errors import InputError

#: exit code when the calibration no longer holds
EXIT_RECALIBRATE = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cell", required=True, help="cell.toml: robot, devices and the history database")
    parser.add_argument("--calibration", help="the calibration to check (default: the current one of the history)")
    data = parser.add_argument_group("check data (default: run the plan's [check] procedure on the cell)")
    data.add_argument("--static", help="static table of the check, CSV (docs/formats.md §2)")
    data.add_argument("--runs", help="UV/VU runs of the check, CSV (docs/formats.md §3)")
    data.add_argument("--log", help="an MCAP log of a check already run")
    proc = parser.add_argument_group("running the check procedure")
    proc.add_argument("--plan", help="plan.toml with a [check] section (default: the plan stored with the "
                                     "current calibration, else `plan` in [cell] of cell.toml)")
    proc.add_argument("--out", help="the check's MCAP log (default: checks/check-<time>.mcap beside the history)")
    proc.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    proc.add_argument("--sim", action="store_true", help="serve the cell's simulated devices in this process")
    proc.add_argument("--yes", action="store_true", help="answer every prompt automatically (simulated devices only)")
    proc.add_argument("--unattended", action="store_true",
                      help="no person at the cell (the default without a terminal, as when scheduled): run the "
                           "steps that need nobody, say which were skipped")
    test = parser.add_argument_group("the test")
    test.add_argument("--alpha", type=float, default=1e-3,
                      help="false-alarm probability of the whole check when nothing changed (default 0.001)")
    test.add_argument("--friction-tolerance", type=float, default=0.2,
                      help="relative friction change that counts, when significant (default 0.2)")
    add_aliased(parser, "--db", "--history", dest="history",
                help="the history database (default: [cell] history of cell.toml)")
    parser.add_argument("--no-record", action="store_true", help="do not record the verdict in the history")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _calibration(args: argparse.Namespace, db: pathlib.Path | None):
    """(calibration, its id in the history or None, the plan text stored with it)."""
    from elastocal.acquisition.history import History
    from elastocal.formats.calibration import read_calibration

    if args.calibration:
        cal = read_calibration(args.calibration)
        if db is None or not db.exists():
            return cal, None, None
        with History(db) as h:
            same = [r for r in h.calibrations() if r.calibration.to_json() == cal.to_json()]
        return cal, (same[-1].id if same else None), (same[-1].plan if same else None)
    if db is None:
        raise InputError("no calibration to check: give --calibration, or a history (--history, or `history = ...` "
                         "in [cell] of cell.toml)", source="--calibration")
    with History(db, create=False) as h:
        rec = h.current()
    if rec is None:
        raise InputError("the history holds no calibration; record one with `elastocal history add`", source=str(db))
    return rec.calibration, rec.id, rec.plan


def baseline_log(db: pathlib.Path | None, cal_id: int | None) -> pathlib.Path | None:
    """The log the calibration was identified from, as the history recorded it (``history add
    --log``), when it is still there unchanged: its unloaded readings are what an unattended
    check's are compared with (diagnose/check_positions.py)."""
    from elastocal.acquisition.history import History
    from elastocal.formats.calibration import file_sha256

    if db is None or cal_id is None or not db.exists():
        return None
    with History(db, create=False) as h:
        rec = h.calibration(cal_id)
    if rec is None or not rec.log_path:
        return None
    path = pathlib.Path(rec.log_path)
    if not path.is_file() or (rec.log_sha256 and file_sha256(path) != rec.log_sha256):
        return None
    return path


def _baseline(args: argparse.Namespace, db: pathlib.Path | None, cal_id: int | None, robot):
    """The calibration's own static table, or None (with a note saying why the unloaded positions
    cannot be compared)."""
    from elastocal.commands._inputs import load_log_noted
    from elastocal.commands._outputs import note

    path = baseline_log(db, cal_id)
    if path is None:
        note(args, "note: the history holds no log of this calibration (`elastocal history add --log`), so "
                   "the unloaded positions are not compared with the calibration's")
        return None
    log_robot, static, _ = load_log_noted(args, path)
    if static is None or (log_robot is not None and log_robot.name != robot.name):
        return None
    return static


def unattended(args: argparse.Namespace) -> bool:
    """No person can answer prompts: --unattended, or no terminal on stdin (a scheduled run) without --yes."""
    if args.yes:
        return False
    if args.unattended:
        return True
    try:
        return not sys.stdin.isatty()
    except (AttributeError, ValueError, OSError):      # no stdin at all
        return True


def _run_procedure(args: argparse.Namespace, config, plan_text: str | None, db: pathlib.Path | None,
                   now_ns: int):
    """Run the plan's [check] on the cell; returns the log and the labels of the steps skipped."""
    from elastocal.acquisition.history import iso_utc
    from elastocal.formats.plan import load_plan, parse_plan
    from elastocal.acquisition.procedures import run_calibration
    from elastocal.acquisition.ui import AutoUI, TerminalUI
    from elastocal.commands._cell import check_answers, procedure_cell

    if args.plan:
        plan = load_plan(args.plan)
    elif plan_text is not None:
        plan = parse_plan(plan_text, source="the plan stored with the calibration")
    elif config.plan is not None:
        with config.key_errors("plan", config.plan):
            plan = load_plan(config.plan)
    else:
        raise InputError("no check plan: give --plan plan.toml (with a [check] section), record the calibration "
                         "with its log or plan (`elastocal history add --log ...`), or name the plan in [cell] "
                         "of the cell config", source="--plan")
    if plan.check is None:
        raise InputError("the plan has no [check] section", source=plan.source)
    # the flags are checked before anything is written (the checks/ folder included)
    check_answers(config, sim=args.sim, yes=args.yes, prompts=not unattended(args))
    if args.yes and args.unattended:
        raise InputError("--yes answers prompts, --unattended runs without them: give one", source="--unattended")
    ui = AutoUI(sys.stderr, quiet=args.json, answered_by="--yes") if args.yes else TerminalUI(sys.stderr)
    if args.out:
        out = pathlib.Path(args.out)
    elif db is not None:
        out = db.parent / "checks" / f"check-{iso_utc(now_ns).replace(':', '').replace('-', '')}.mcap"
        out.parent.mkdir(exist_ok=True)
    else:
        raise InputError("give --out for the check's log (no history folder to put it in)", source="--out")
    with procedure_cell(config, sim=args.sim) as (cell, world):
        outcome = run_calibration(cell, plan, out, yes=args.yes, ui=ui, procedures=("check",), world=world,
                                  overwrite=args.force, unattended=unattended(args))
    if outcome.status != "completed":
        raise InputError(f"the check procedure did not complete ({outcome.status}: {outcome.message})",
                         source=str(out))
    return out, outcome.skipped


def _data(args: argparse.Namespace, config, robot, plan_text: str | None, db, now_ns: int):
    """(static, runs, the data file, the log or None, what an unattended check skipped): the
    tables given, the log given, or the log the check procedure records now."""
    from elastocal.formats.tables import read_run_table, read_static_table

    log_path = None
    skipped: tuple[str, ...] = ()
    if args.static or args.runs or args.log:
        if any((args.plan, args.sim, args.yes, args.out, args.unattended)):
            raise InputError("--plan, --sim, --yes, --unattended and --out run the check procedure; not with "
                             "--static, --runs or --log", source="--log" if args.log else "--static")
    if args.static or args.runs:
        static = read_static_table(args.static, robot) if args.static else None
        runs = read_run_table(args.runs, robot) if args.runs else None
        data_path = pathlib.Path(args.static or args.runs)
    else:
        from elastocal.commands._inputs import load_log_noted

        if args.log:
            log_path = pathlib.Path(args.log)
        else:
            log_path, skipped = _run_procedure(args, config, plan_text, db, now_ns)
        _, static, runs = load_log_noted(args, log_path)
        data_path = log_path
        if static is None and runs is None:
            raise InputError("nothing to check: the log holds neither static poses nor runs", source=str(log_path))
    return static, runs, data_path, log_path, skipped


def _record(args: argparse.Namespace, db, cal_id, result, obj: dict, data_path: pathlib.Path, now_ns: int):
    """The check's id in the history (None with --no-record or without a history)."""
    from elastocal.acquisition.history import History
    from elastocal.formats.calibration import file_sha256

    if args.no_record or db is None:
        return None
    if cal_id is None:
        raise InputError("the calibration is not in the history, so the verdict cannot be recorded: add it with "
                         "`elastocal history add`, or give --no-record", source=args.calibration)
    with History(db) as h:
        return h.add_check(calibration_id=cal_id, time_ns=now_ns, verdict=result.verdict, reasons=result.reasons,
                           result=obj, log_sha256=file_sha256(data_path), log_path=str(data_path.resolve()))


def run(args: argparse.Namespace) -> int:
    from elastocal.commands._cell import check_sim_section
    from elastocal.commands.history import clean
    from elastocal.drivers.config import load_cell_config
    from elastocal.diagnose.check import check_calibration

    now_ns = time.time_ns()
    if args.out:  # the folder and the name; an existing log is refused by the procedure (as calibrate's)
        from elastocal.commands._outputs import Outputs

        Outputs(force=True, inputs=[(args.cell, "--cell"), (args.plan, "--plan"), (args.calibration,
                                    "--calibration")]).add(args.out, "--out")
    config = load_cell_config(args.cell)
    check_sim_section(config)
    robot = config.load_robot()
    db = pathlib.Path(args.history) if args.history else config.history
    with config.key_errors("history", None if args.history else db):
        cal, cal_id, plan_text = _calibration(args, db)
    if cal.robot and cal.robot != robot.name:
        raise InputError(f"the calibration is for {cal.robot!r}, the cell's robot is {robot.name!r}",
                         source=args.calibration or str(db))
    if (args.static or args.runs) and args.log:
        raise InputError("give either a log or --static/--runs tables, not both", source=args.log)
    static, runs, data_path, log_path, skipped = _data(args, config, robot, plan_text, db, now_ns)
    baseline = _baseline(args, db, cal_id, robot) if static is not None and static.absolute_only else None
    result = check_calibration(robot, cal, static=static, runs=runs, alpha=args.alpha,
                               friction_tolerance=args.friction_tolerance, baseline=baseline)
    if skipped:
        tested = (result.deflection is not None or result.positions is not None or result.absolute is not None
                  or (result.friction is not None and result.friction.joints))
        if not tested:
            raise InputError(f"the unattended check tested nothing: it skipped {'; '.join(skipped)} (no person to "
                             "hang the load), and the rest does not test this calibration (no log of it in the "
                             "history to compare the unloaded positions with)", source=str(log_path))
        result = dataclasses.replace(result, reasons=result.reasons + (
            f"not checked, no person at the cell (unattended): {'; '.join(skipped)}",))
    obj = clean(result.to_json())
    obj["skipped"] = list(skipped)
    recorded = _record(args, db, cal_id, result, obj, data_path, now_ns)
    obj.update({"calibration": cal_id, "recorded": recorded, "history": None if db is None else str(db),
                "log": None if log_path is None else str(log_path)})
    code = 0 if result.verdict == "holds" else EXIT_RECALIBRATE
    if args.json:
        print(json.dumps(obj))
        return code
    head = ("HOLDS: the calibration still holds" if result.verdict == "holds"
            else "RECALIBRATE: the calibration no longer holds")
    lines = [head] + [f"  - {r}" for r in result.reasons]
    if recorded is not None:
        lines.append(f"recorded as check {recorded} of calibration {cal_id} in {db}")
    if log_path is not None:
        lines.append(f"log: {log_path}")
    print("\n".join(lines))
    return code
