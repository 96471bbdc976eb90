"""``elastocal sim plant``: a simulated plant of cells for ``elastocal fleet`` (docs/fleet.md).

Each cell is a folder as docs/fleet.md lays a plant out: ``cell.toml`` naming
its robot and its history, ``logs/YYYY-MM-DD.mcap`` (one static log a week,
dated in the log as when it was measured) and ``history.sqlite`` holding the
cell's first calibration, identified from its first log and recorded exactly
as ``elastocal fleet identify --record`` records it (so a later ``--record``
finds it already there). The cells are built a little differently (their joint
stiffnesses spread by a few per cent, seeded); one cell's joint softens from a
given log on. ``truth.json`` at the top says what each cell really was.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import pathlib
from dataclasses import dataclass

from elastocal.errors import InputError

#: the first log of every cell (a Monday), at 06:00 UTC plus one hour per cell
FIRST_DAY = _dt.datetime(2026, 11, 2, 6, 0, tzinfo=_dt.timezone.utc)
#: days between two logs of a cell
LOG_INTERVAL_DAYS = 7
#: relative spread (1 sigma) of the cells' joint stiffnesses about the robot's (their builds differ)
STIFFNESS_SPREAD = 0.03


def add_arguments(sub) -> None:
    """``sim plant`` and its flags, on the subparsers of ``elastocal sim``."""
    text = ("a plant of simulated cells for `elastocal fleet`: per cell a cell.toml naming its history, "
            "weekly static logs, and the history holding the first calibration; one cell's joint softens")
    p = sub.add_parser("plant", help=text, description=text)
    from elastocal.commands._flags import add_json, add_seed

    p.add_argument("--out", required=True, help="the plant's folder (cell-01/, cell-02/, ..., truth.json)")
    p.add_argument("--cells", type=int, default=3, help="number of cells (default 3)")
    p.add_argument("--logs", type=int, default=4, help="logs per cell, one a week (default 4)")
    p.add_argument("--drift-cell", type=int, default=None, metavar="N",
                   help="the cell whose joint softens (cell-0N; 0: none; default 2, none when --cells is 1)")
    p.add_argument("--drift-joint", type=int, default=2, metavar="J", help="the joint that softens (default 2)")
    p.add_argument("--drift", type=float, default=0.10,
                   help="how much softer it gets, a fraction of its stiffness (default 0.10)")
    p.add_argument("--drift-from", type=int, default=None, metavar="K",
                   help="the first log (1-based) measured after the change (default: the second half's first)")
    p.add_argument("--poses", type=int, default=12, help="poses per log (default 12)")
    add_seed(p)
    p.add_argument("--force", action="store_true", help="overwrite the files of an earlier plant in --out")
    add_json(p)


@dataclass(frozen=True)
class PlantSpec:
    """What ``sim plant`` builds, checked."""

    cells: int
    logs: int
    drift_cell: int            # 1-based; 0: none
    drift_joint: int           # 1-based
    drift: float
    drift_from: int            # 1-based index of the first log after the change
    poses: int
    seed: int

    def cell_name(self, c: int) -> str:
        return f"cell-{c + 1:02d}"

    def log_time(self, c: int, k: int) -> _dt.datetime:
        return FIRST_DAY + _dt.timedelta(days=LOG_INTERVAL_DAYS * k, hours=c)

    def log_name(self, c: int, k: int) -> str:
        return f"logs/{self.log_time(c, k):%Y-%m-%d}.mcap"


def _spec(args: argparse.Namespace) -> PlantSpec:
    import math

    for flag, low, high in (("cells", 1, 99), ("logs", 2, 200), ("poses", 6, 500)):
        value = getattr(args, flag)
        if not low <= value <= high:
            raise InputError(f"must be between {low} and {high}, got {value}", source=f"--{flag}")
    if args.seed < 0:
        raise InputError(f"must be >= 0, got {args.seed}", source="--seed")
    drift_cell = (2 if args.cells >= 2 else 0) if args.drift_cell is None else args.drift_cell
    if not 0 <= drift_cell <= args.cells:
        raise InputError(f"must be 0 (none) or a cell between 1 and --cells ({args.cells}), got {drift_cell}",
                         source="--drift-cell")
    if not 1 <= args.drift_joint <= 6:
        raise InputError(f"must be a joint between 1 and 6, got {args.drift_joint}", source="--drift-joint")
    if not (math.isfinite(args.drift) and -1.0 < args.drift < 1.0):
        raise InputError(f"must be a fraction between -1 and 1 (0.1: 10 % softer), got {args.drift}",
                         source="--drift")
    drift_from = args.logs // 2 + 1 if args.drift_from is None else args.drift_from
    if not 2 <= drift_from <= args.logs:
        raise InputError(f"must be a log between 2 and --logs ({args.logs}): the first log is the cell's first "
                         f"calibration, got {drift_from}", source="--drift-from")
    return PlantSpec(cells=args.cells, logs=args.logs, drift_cell=drift_cell, drift_joint=args.drift_joint,
                     drift=args.drift, drift_from=drift_from, poses=args.poses, seed=args.seed)


def cell_toml(name: str) -> str:
    import tomli_w

    return tomli_w.dumps({"cell": {"name": name, "robot": "hh150", "history": "history.sqlite"}})


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from elastocal.acquisition.logwriter import write_log_from_tables
    from elastocal.commands._outputs import Outputs, check_folder
    from elastocal.formats.robot_toml import bundled_robot
    from elastocal.sims.cell import CellTruth
    from elastocal.sims.static import StaticPlan, simulate_static

    spec = _spec(args)
    out = check_folder(args.out, "--out")
    outputs = Outputs(force=args.force)
    for c in range(spec.cells):
        cell = out / spec.cell_name(c)
        for name in ("cell.toml", *(spec.log_name(c, k) for k in range(spec.logs))):
            outputs.add(cell / name, "--out", in_folder=True)
        outputs.stale(cell / "history.sqlite", "--out", "a history of an earlier plant is in the way")
    outputs.add(out / "truth.json", "--out", in_folder=True)
    robot = bundled_robot()
    plan = StaticPlan(n_poses=spec.poses)
    truth_doc: dict = {"seed": spec.seed, "robot": robot.name, "unit": "N*m/rad", "cells": []}
    for c in range(spec.cells):
        outputs.make_folder(out / spec.cell_name(c) / "logs")
    from elastocal.progress import Progress

    progress = Progress("sim plant", spec.cells * spec.logs + spec.cells, quiet=args.json)
    with outputs:
        for c in range(spec.cells):
            name, cell = spec.cell_name(c), out / spec.cell_name(c)
            outputs.temp(cell / "cell.toml").write_text(cell_toml(name), encoding="utf-8")
            built = CellTruth()
            spread = np.random.default_rng([spec.seed, c]).standard_normal(6) * STIFFNESS_SPREAD
            built_k = built.stiffness * (1.0 + spread)
            logs = []
            for k in range(spec.logs):
                progress(c * spec.logs + k, f"{name} {spec.log_name(c, k)}")
                stiffness = built_k.copy()
                drifted = c + 1 == spec.drift_cell and k + 1 >= spec.drift_from
                if drifted:
                    stiffness[spec.drift_joint - 1] *= 1.0 - spec.drift
                truth = CellTruth(stiffness=stiffness)
                seed = int(np.random.SeedSequence([spec.seed, c, k]).generate_state(1)[0])
                table = simulate_static(robot, truth, seed=seed, plan=plan, source=str(cell / spec.log_name(c, k)))
                when = spec.log_time(c, k)
                write_log_from_tables(outputs.temp(cell / spec.log_name(c, k)), robot, static=table,
                                      cell_text=cell_toml(name),
                                      started_unix_ns=int(when.timestamp()) * 1_000_000_000)
                logs.append({"log": spec.log_name(c, k), "measured": when.isoformat().replace("+00:00", "Z"),
                             "stiffness": [float(v) for v in stiffness], "drifted": drifted})
            truth_doc["cells"].append({
                "cell": name, "built_stiffness": [float(v) for v in built_k],
                "drift": ({"joint": spec.drift_joint, "fraction": spec.drift,
                           "from_log": spec.log_name(c, spec.drift_from - 1)}
                          if c + 1 == spec.drift_cell else None),
                "first_calibration": spec.log_name(c, 0), "logs": logs})
        outputs.temp(out / "truth.json").write_text(json.dumps(truth_doc, indent=2) + "\n", encoding="utf-8")
    recorded = _record_first_calibrations(out, spec, progress)
    progress.done()
    written = {"plant": str(out), "cells": [spec.cell_name(c) for c in range(spec.cells)],
               "logs": spec.cells * spec.logs, "truth": str(out / "truth.json"),
               "first_calibrations": recorded}
    if args.json:
        print(json.dumps(written))
    else:
        print(f"wrote plant  {out}: {spec.cells} cell(s) x {spec.logs} weekly log(s), "
              f"from {FIRST_DAY:%Y-%m-%d}")
        for c in range(spec.cells):
            cell = out / spec.cell_name(c)
            drift = (f"; joint {spec.drift_joint} {spec.drift * 100:g} % softer from "
                     f"{spec.log_name(c, spec.drift_from - 1)} on" if c + 1 == spec.drift_cell else "")
            print(f"  {spec.cell_name(c)}  {cell / 'cell.toml'}, history {cell / 'history.sqlite'} "
                  f"(first calibration: {spec.log_name(c, 0)}){drift}")
        print(f"wrote truth  {out / 'truth.json'}")
    return 0


def _record_first_calibrations(out: pathlib.Path, spec: PlantSpec, progress=None) -> int:
    """Identify each cell's first log and record it in the cell's history, as
    ``elastocal fleet identify --record`` does (the same task, the same record)."""
    import time

    from elastocal.fleet.plant import record_results
    from elastocal.fleet.tasks import FleetTask, run_task

    results = []
    for c in range(spec.cells):
        cell = out / spec.cell_name(c)
        if progress is not None:
            progress(spec.cells * spec.logs + c, f"{spec.cell_name(c)}: first calibration from "
                                                 f"{spec.log_name(c, 0)}")
        r = run_task(FleetTask(command="identify", path=str(cell / spec.log_name(c, 0)),
                               cell_config=str(cell / "cell.toml"), cell=spec.cell_name(c)))
        if not r.ok:
            raise InputError(f"the simulated first calibration failed: {r.error}", source=r.path)
        results.append(r)
    return record_results(results, now_ns=time.time_ns()).calibrations
