"""`elastocal history`: every calibration and check of a cell, and the drift (docs/history.md).

    elastocal history --cell cell.toml [--json] [--plot drift.png]
    elastocal history add --cell cell.toml --calibration cal.json [--log LOG.mcap] [--plan plan.toml]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

from elastocal.acquisition.history import clean, drift_summary  # clean: also check's
from elastocal.commands._flags import JSON_HELP
from elastocal.errors import InputError


def _common(parser: argparse.ArgumentParser, default=None) -> None:
    """Flags of both actions; on the subcommands their default is SUPPRESS, so a flag
    given before the action (``history --cell C add``) is kept."""
    parser.add_argument("--cell", default=default, help="cell.toml; its [cell] history names the database")
    parser.add_argument("--db", default=default, help="the history database (instead of --cell's)")
    parser.add_argument("--json", action="store_true", default=default if default is not None else False,
                        help=JSON_HELP)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _common(parser)
    parser.add_argument("--plot", help="show: write the drift plot here, .png or .svg")
    for flag in ("--calibration", "--log", "--plan"):    # add's flags given without `add`: a clear error in run
        parser.add_argument(flag, help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="action", metavar="{show,add}")
    sub.default = "show"
    show = sub.add_parser("show", help="the table of calibrations and checks, and the drift (the default)",
                          description="the table of calibrations and checks of the cell, and the drift")
    _common(show, argparse.SUPPRESS)
    show.add_argument("--plot", default=argparse.SUPPRESS, help="write the drift plot here, .png or .svg")
    add = sub.add_parser("add", help="record a calibration in the history",
                         description="record a calibration (and the log it came from) in the cell's history")
    _common(add, argparse.SUPPRESS)
    add.add_argument("--calibration", help="the calibration JSON to record (required)")
    add.add_argument("--log", help="the MCAP log the calibration came from (its hash and plan are kept)")
    add.add_argument("--plan", help="the plan.toml it was measured with (default: the log's)")


def history_path(cell_path: str | None, db: str | None) -> pathlib.Path | None:
    """The history database: ``db``, else ``[cell] history`` of ``cell_path``; None when neither names one."""
    if db:
        return pathlib.Path(db)
    if cell_path:
        from elastocal.drivers.config import load_cell_config

        return load_cell_config(cell_path).history
    return None


def _add(args: argparse.Namespace, db: pathlib.Path) -> int:
    from elastocal.acquisition.history import History
    from elastocal.formats.calibration import file_sha256, read_calibration

    if not args.calibration:
        raise InputError("history add needs --calibration cal.json", source="--calibration")
    cal = read_calibration(args.calibration)
    if args.cell and cal.robot:
        from elastocal.drivers.config import load_cell_config

        robot = load_cell_config(args.cell).load_robot()
        if cal.robot != robot.name:
            raise InputError(f"the calibration is for {cal.robot!r}, the cell's robot is {robot.name!r}",
                             source=args.calibration)
    log_sha = log_path = plan_text = None
    if args.log:
        from elastocal.acquisition.logreader import read_log
        from elastocal.commands._outputs import log_note, note

        log_path = str(pathlib.Path(args.log).resolve())
        if not pathlib.Path(args.log).is_file():
            raise InputError("cannot read: no such log", source=args.log)
        contents = read_log(args.log)
        log_sha = file_sha256(args.log)
        if not args.plan:
            plan_text = contents.plan.text if contents.plan is not None else None
        text = log_note(args.log, contents)
        if text:
            note(args, text)
    else:
        logs = [d for d in cal.data if d.path.endswith(".mcap")] or list(cal.data)
        if logs:
            log_sha, log_path = logs[0].sha256, logs[0].path
    if args.plan:
        from elastocal.formats.plan import load_plan

        plan_text = load_plan(args.plan).text
    with History(db) as h:
        rid = h.add_calibration(cal, time_ns=time.time_ns(), log_sha256=log_sha, log_path=log_path, plan=plan_text)
    if args.json:
        print(json.dumps({"db": str(db), "calibration": rid}))
    else:
        print(f"recorded calibration {rid} ({cal.robot}, {', '.join(cal.model)}) in {db}; it is the current one")
    return 0


def _k(rec, name: str) -> float | None:
    p = rec.calibration.find(name)
    return p.value if p is not None else None


def _show(args: argparse.Namespace, db: pathlib.Path) -> int:
    from elastocal.acquisition.history import History, plot_drift
    from elastocal.commands._outputs import Outputs

    # the drift plot is redrawn on every call: an existing plot is replaced (it must not be an input)
    outputs = Outputs(force=True, inputs=[(db, "the history database"), (args.cell, "--cell")])
    if args.plot:
        if pathlib.Path(args.plot).suffix.lower() not in (".png", ".svg"):
            raise InputError("the drift plot is written as .png or .svg", source="--plot")
        outputs.add(args.plot, "--plot")
    with History(db, create=False) as h:
        cals = h.calibrations()
        checks = h.checks()
        drift = h.drift()
    summary = drift_summary(drift)
    if args.plot:
        with outputs:
            plot_drift(drift, outputs.temp(args.plot))
    if args.json:
        obj = {"db": str(db),
               "calibrations": [{"id": r.id, "time": r.time, "created": r.created, "robot": r.robot,
                                 "model": list(r.calibration.model), "torque": r.calibration.torque,
                                 "parameters": {p.name: p.to_json() for p in r.calibration.parameters},
                                 "residual": r.calibration.residual.to_json(), "log_sha256": r.log_sha256,
                                 "log_path": r.log_path, "has_plan": r.plan is not None} for r in cals],
               "checks": [{"id": c.id, "time": c.time, "calibration": c.calibration_id, "verdict": c.verdict,
                           "reasons": list(c.reasons), "deflection": c.result.get("deflection"),
                           "friction": c.result.get("friction"), "log_sha256": c.log_sha256,
                           "log_path": c.log_path} for c in checks],
               "drift": summary, "plot": args.plot}
        print(json.dumps(clean(obj)))
        return 0
    lines = [f"history {db}: {len(cals)} calibration(s), {len(checks)} check(s)"]
    if cals:
        n_joints = max([6] + [r.calibration.n_stiffness for r in cals])
        lines.append("calibrations (stiffness in 1e6 N*m/rad, 1e6 N/m for a prismatic joint)")
        lines.append(f"  {'id':>3}  {'recorded (UTC)':<20}  {'robot':<10} "
                     + " ".join(f"{f'k{j}':>7}" for j in range(1, n_joints + 1)) + f"  {'rms':>8}  log")
        for r in cals:
            ks = " ".join(f"{_k(r, f'k{j}') / 1e6:7.4f}" if _k(r, f"k{j}") is not None else f"{'-':>7}"
                          for j in range(1, n_joints + 1))
            rms = r.calibration.residual.rms
            rms_s = f"{rms * 1e6:6.1f}µm" if rms is not None and rms < 1.0 else "-"
            lines.append(f"  {r.id:>3}  {r.time:<20}  {r.robot[:10]:<10} {ks}  {rms_s:>8}  "
                         f"{(r.log_sha256 or '-')[:12]}")
    if checks:
        lines.append("checks")
        lines.append(f"  {'id':>3}  {'checked (UTC)':<20}  {'cal':>3}  {'verdict':<11}  {'unexplained':>11}  "
                     f"{'floor':>8}  reason")
        for c in checks:
            d = c.result.get("deflection") or {}
            un = d.get("rms_unexplained")
            fl = d.get("noise_floor")
            lines.append(f"  {c.id:>3}  {c.time:<20}  {c.calibration_id:>3}  {c.verdict:<11}  "
                         f"{(f'{un * 1e6:.1f} µm' if un is not None else '-'):>11}  "
                         f"{(f'{fl * 1e6:.1f} µm' if fl is not None else '-'):>8}  {c.reasons[0] if c.reasons else ''}")
    params = summary
    if params:
        lines.append("drift (first calibration -> latest calibration or later check)")
        for name, p in params.items():
            if p["change"] is None:
                continue
            change = (f"({p['change'] * 100:+.2f} %)" if p["determined"] else
                      "(n/d: a calibration does not determine it, no finding)")
            lines.append(f"  {name:<5} {p['first']:.6g} -> {p['latest']:.6g} {p['unit']} {change}")
    if args.plot:
        lines.append(f"drift plot: {args.plot}")
    print("\n".join(lines))
    return 0


def run(args: argparse.Namespace) -> int:
    db = history_path(args.cell, args.db)
    if db is None:
        raise InputError("no history database: give --db, or --cell with `history = \"history.sqlite\"` in its "
                         "[cell] table", source=args.cell or "--db")
    for flag in ("calibration", "log", "plan"):
        if args.action != "add" and getattr(args, flag):
            raise InputError(f"--{flag} belongs to `history add`", source=f"--{flag}")
    if args.db:
        return _add(args, db) if args.action == "add" else _show(args, db)
    from elastocal.drivers.config import load_cell_config

    with load_cell_config(args.cell).key_errors("history", db):      # the database [cell] history names
        return _add(args, db) if args.action == "add" else _show(args, db)
