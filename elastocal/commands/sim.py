"""`elastocal sim static|runs|path|plant|serve`: datasets from the simulated cell, a process path, a plant of
cells (elastocal.commands.sim_plant), or simulated devices."""

from __future__ import annotations

import argparse
import json
import pathlib

from elastocal.commands._flags import DEFAULT_LOADS_PER_POSE, add_aliased, add_json, add_seed
from elastocal.errors import InputError

#: Yang's process wrench (Table 8: 1500 N along z): the default of ``sim path``; the same as
#: elastocal.compensation.validate.YANG_WRENCH, kept here so that --help imports no compensation code
YANG_WRENCH = (0.0, 0.0, 1500.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="sim_command", metavar="{static,runs,path,plant,serve}")
    sub.required = True
    for name, text in (("static", "a static before/after-load experiment: robot.toml, static.csv, truth.json"),
                       ("runs", "friction runs and sweeps of the compensator's joint (joint 2; joint 3 on the track): "
                                "robot.toml, runs.csv, truth.json")):
        p = sub.add_parser(name, help=text, description=text)
        effects = ("link_compliance, thermal_drift, static_friction, backlash, kinematic_errors (the real DH "
                   "table, or a URDF robot's joint origins, off by 0.02-0.05 deg and 0.1-0.5 mm), tracker_frame (the tracker on another stand), "
                   "base_tilt (the base tilting under the overturning moment), nonlinear_stiffness (hardening "
                   "gears); several as A,B"
                   if name == "static" else
                   "coulomb_friction, viscous_friction, load_dependent_friction, or friction for all three; "
                   "compensator (robot.toml without its nominal C, l_c); A,B for two")
        p.add_argument("--hidden", default="none",
                       help=f"effect the simulated cell has and the default model lacks: none (default), {effects}")
        add_seed(p)
        p.add_argument("--out", required=True, help="output directory")
        p.add_argument("--robot", help="robot.toml to simulate, or a bundled robot by name: hh150 (the default), "
                                       "hh150_track (the HH-150 on a floor track, seven joints), hh150_urdf (the "
                                       "HH-150 described by a URDF)")
        p.add_argument("--force", action="store_true", help="overwrite the files of an earlier dataset in --out")
        add_json(p)
        if name == "runs":
            p.add_argument("--compensator-sweep", action="store_true",
                           help="also write sweep.csv: a sweep of the compensator's joint reading markers P1 "
                                "(compensator pivot) and P01, P02 (its cylinder), for `elastocal geometry --runs "
                                "sweep.csv --pivot P1 --cylinder P01,P02` (with --joint 3 on the track); "
                                "truth.json gets the compensator geometry")
        if name == "static":
            p.add_argument("--poses", type=int, default=12, help="number of poses (default 12)")
            add_aliased(p, "--loads-per-pose", "--loads", dest="loads", type=int,
                        default=DEFAULT_LOADS_PER_POSE,
                        help=f"loaded states per pose (default {DEFAULT_LOADS_PER_POSE}, as `plan`)")
            p.add_argument("--repeats", type=int, default=3, help="readings per marker and state (default 3)")
            p.add_argument("--outliers", type=int, default=0,
                           help="bad tracker readings (0.3-0.5 mm off) to put among the repeats (default 0); "
                                "truth.json lists their lines")
            p.add_argument("--shared-currents", action="store_true",
                           help="one drive reading per repeat for all its marker rows (docs/formats.md §2)")
            p.add_argument("--tracker-export", action="store_true",
                           help="also write the readings as a tracker software and the controller record them: "
                                "points.csv (Leica-style, mm, named P{pose}_L{load}_{marker}) and joints.csv, "
                                "for `elastocal import` (docs/import.md)")
    text = ("a process path to compensate: robot.toml and path.csv, Yang's line x 1.2 -> 1.8 m at z 0.116 m, "
            "10 mm/s, under a constant process wrench (default 1500 N up)")
    path = sub.add_parser("path", help=text, description=text)
    path.add_argument("--out", required=True, help="output directory")
    path.add_argument("--wrench", metavar="FX,FY,FZ[,MX,MY,MZ]", default=",".join(str(v) for v in YANG_WRENCH),
                      help="the process wrench on the load point for every sample, base axes [N, N*m] "
                           "(default 0,0,1500: Yang's friction stir welding force)")
    path.add_argument("--step", type=float, default=0.005, metavar="M",
                      help="distance between path points [m] (default 0.005)")
    path.add_argument("--force", action="store_true", help="overwrite the files of an earlier path in --out")
    add_json(path)
    from elastocal.commands import sim_plant

    sim_plant.add_arguments(sub)
    serve = sub.add_parser("serve", help="serve simulated devices on loopback and a CAN bus",
                           description="serve simulated devices on 127.0.0.1 and a CAN bus on the loopback "
                                       "interface (udp_loopback on a port of its own, so other processes on this "
                                       "machine reach it and nothing off it does)")
    _add_serve_arguments(serve)


def _add_serve_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags of ``elastocal sim serve``."""
    parser.add_argument("--cell", metavar="CELL.toml",
                        help="cell config to serve (default: the packaged simulated HH-150 cell)")
    parser.add_argument("--can", choices=("loopback", "as-configured"), default="loopback",
                        help="CAN bus of the simulated drives: loopback (python-can interface udp_loopback: "
                             "multicast on 127.0.0.1 only, on a free port; reachable from other processes on "
                             "this machine; default) or as the config says (virtual = this process only)")
    parser.add_argument("--write-cell", metavar="PATH",
                        help="write the cell config with the actual ports and device paths here, "
                             "for `elastocal devices --cell PATH`")
    parser.add_argument("--force", action="store_true", help="overwrite --write-cell if it exists")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S seconds (default: until interrupted)")
    add_json(parser)


def _serve(args: argparse.Namespace) -> int:
    """``elastocal sim serve``: serve the simulated devices until interrupted (or ``--duration``)."""
    import contextlib
    import signal
    import sys
    import threading
    import time

    from elastocal.drivers.config import load_cell_config
    from elastocal.sims.serve import SimulatedCell, example_cell_config, to_loopback_can

    if args.duration is not None and not args.duration > 0:
        raise InputError(f"--duration must be > 0, got {args.duration}")
    outputs = None
    if args.write_cell:      # refused before anything is served, like every other output
        from elastocal.commands._outputs import Outputs

        outputs = Outputs(force=args.force, inputs=[(args.cell, "--cell")])
        outputs.add(args.write_cell, "--write-cell")
    config = load_cell_config(args.cell) if args.cell else example_cell_config()
    if args.can == "loopback":
        config = to_loopback_can(config)
    stop = threading.Event()
    previous = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    if previous is not None:
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        with SimulatedCell(config, load_rig=True) as sim:   # calibrate hangs its loads through the rig
            if outputs is not None:
                with outputs:
                    try:
                        outputs.temp(args.write_cell).write_text(sim.config.to_toml(), encoding="utf-8")
                    except OSError as exc:
                        raise InputError(f"cannot write: {exc.strerror}", source=args.write_cell) from None
            if args.json:
                print(json.dumps({"urls": sim.urls, "cell": args.write_cell}), flush=True)
            else:
                print(f"simulated cell {sim.config.name!r} serving (Ctrl-C stops):")
                for name, url in sim.urls.items():
                    print(f"  {name:12s} {url}")
                if any(d.url.scheme == "canopen" and d.url.can_interface == "virtual" for d in sim.config.drives):
                    print("  note: CAN 'virtual' reaches this process only; use --can loopback for others")
                if args.write_cell:
                    print(f"  cell config with these URLs: {args.write_cell}")
                sys.stdout.flush()
            end = None if args.duration is None else time.monotonic() + args.duration
            with contextlib.suppress(KeyboardInterrupt):   # Ctrl-C is the way to stop serving
                while not stop.is_set():
                    remaining = None if end is None else end - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        break
                    stop.wait(0.5 if remaining is None else min(0.5, remaining))
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0


def _robot(args):
    from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path, load_robot

    import pathlib

    if not args.robot:
        return bundled_robot()
    if not pathlib.Path(args.robot).exists() and bundled_robot_path(args.robot).exists():
        return bundled_robot(args.robot)        # a bundled robot by name: hh150, hh150_track, hh150_urdf
    return load_robot(args.robot)


def _path(args: argparse.Namespace) -> int:
    """``elastocal sim path``: the bundled robot and Yang's process path under a constant wrench."""
    import numpy as np

    from elastocal.commands.plan import numbers
    from elastocal.commands._outputs import Outputs, check_folder
    from elastocal.compensation.files import write_path
    from elastocal.compensation.ik import PlannedPath, yang_path
    from elastocal.formats.robot_toml import bundled_robot

    wrench = np.array(numbers(args.wrench, (3, 6), "--wrench") + (0.0,) * 3)[:6]
    if not (np.isfinite(args.step) and 0.0005 <= args.step <= 0.1):
        raise InputError(f"must be between 0.0005 and 0.1 m, got {args.step}", source="--step")
    out = check_folder(args.out, "--out")
    outputs = Outputs(force=args.force)
    for name in ("robot.toml", "path.csv"):
        outputs.add(out / name, "--out", in_folder=True)
    robot = bundled_robot()
    planned = yang_path(robot, step_m=args.step)
    planned = PlannedPath(t=planned.t, q=planned.q, wrench=np.tile(wrench, (len(planned), 1)))
    outputs.make_folder(out)
    with outputs:
        outputs.temp(out / "robot.toml").write_text(robot.to_toml(), encoding="utf-8")
        write_path(outputs.temp(out / "path.csv"), planned)
    written = {"robot": str(out / "robot.toml"), "path": str(out / "path.csv"), "points": len(planned)}
    if args.json:
        print(json.dumps(written))
    else:
        print(f"wrote robot  {written['robot']}")
        print(f"wrote path   {written['path']} ({len(planned)} points, wrench {', '.join(f'{v:g}' for v in wrench)})")
    return 0


def _check_flags(args: argparse.Namespace, static: bool) -> None:
    """The flags of ``sim static``/``sim runs`` checked, before anything is written."""
    from elastocal.sims.cell import HIDDEN_EFFECTS
    from elastocal.sims.runs import RUN_HIDDEN

    hidden = HIDDEN_EFFECTS if static else RUN_HIDDEN
    if not all(name.strip() in hidden for name in args.hidden.split(",")):
        raise InputError(f"the simulator cannot hide {args.hidden!r} in {'static' if static else 'run'} data; "
                         f"one of {', '.join(hidden)}", source="--hidden")
    if args.seed < 0:
        raise InputError(f"must be >= 0, got {args.seed}", source="--seed")
    if static:
        for flag in ("poses", "loads", "repeats"):
            if getattr(args, flag) < 1:
                raise InputError(f"must be at least 1, got {getattr(args, flag)}", source=f"--{flag}")
        if args.outliers < 0:
            raise InputError(f"must be >= 0, got {args.outliers}", source="--outliers")
        if args.outliers and args.repeats < 3:
            raise InputError("outliers need 3 or more repeats to be told from their repeats", source="--outliers")


def _simulate(args: argparse.Namespace, robot, static: bool, out: pathlib.Path, progress=None):
    """(the robot the user's robot.toml describes, the simulated table, the cell's truth, truth.json)."""
    from elastocal.sims.cell import CellTruth

    if static:
        import numpy as np

        from elastocal.sims.static import StaticPlan, add_outliers, simulate_static

        truth = CellTruth.for_robot(robot).with_hidden(args.hidden)
        plan = StaticPlan(n_poses=args.poses, n_loads=args.loads, repeats=args.repeats,
                          shared_currents=args.shared_currents)
        table = simulate_static(robot, truth, seed=args.seed, plan=plan, progress=progress)
        try:
            table, outlier_lines = add_outliers(table, args.outliers, np.random.default_rng([args.seed, 18]))
        except ValueError as exc:
            raise InputError(str(exc), source="--outliers") from None
        params = truth.parameters(robot)
    else:
        from elastocal.sims.runs import described_robot, hide_in_runs, simulate_runs

        truth = hide_in_runs(CellTruth.for_robot(robot), args.hidden)
        table = simulate_runs(robot, truth, seed=args.seed, source=str(out / "runs.csv"), progress=progress)
        params = truth.parameters(robot)
        robot = described_robot(robot, args.hidden)     # what the user's robot.toml says
    truth_doc = {"hidden": args.hidden, "seed": args.seed, "robot": robot.name, "parameters": params,
                 "noise": {"tracker_m": truth.tracker_noise_m, "current_a": truth.current_noise_a}}
    if static:
        truth_doc["outliers"] = [int(x) for x in outlier_lines]
    return robot, table, truth, truth_doc


def _compensator_sweep(args: argparse.Namespace, robot, truth, truth_doc: dict, out: pathlib.Path):
    """The compensator's marker sweep (its geometry added to ``truth_doc``)."""
    import numpy as np

    from elastocal.sims.compensator_markers import compensator_sweep, compensator_truth

    try:
        truth_doc["compensator_geometry"] = {**compensator_truth(robot), "unit": "m"}
    except ValueError as exc:
        raise InputError(str(exc), source="--compensator-sweep") from None
    return compensator_sweep(robot, np.random.default_rng([args.seed, 2]), noise_m=truth.tracker_noise_m,
                             source=str(out / "sweep.csv"))


def run(args: argparse.Namespace) -> int:
    if args.sim_command == "serve":
        return _serve(args)
    if args.sim_command == "path":
        return _path(args)
    if args.sim_command == "plant":
        from elastocal.commands import sim_plant

        return sim_plant.run(args)
    from elastocal.progress import long_work

    with long_work(f"sim {args.sim_command}", 1, quiet=args.json) as progress:   # a pose or a run at a time
        return _tables(args, progress)


def _tables(args: argparse.Namespace, progress) -> int:
    """``sim static`` and ``sim runs``: the simulated table, its log, the robot and the truth."""
    from elastocal.commands._outputs import Outputs, check_folder

    # everything is checked before anything is written
    static = args.sim_command == "static"
    _check_flags(args, static)
    out = check_folder(args.out, "--out")
    outputs = Outputs(force=args.force, inputs=[(args.robot, "--robot")])
    table_name = "static.csv" if static else "runs.csv"
    sweep = not static and args.compensator_sweep
    export = static and args.tracker_export
    for name in (("robot.toml", table_name, "log.mcap", "truth.json") + (("sweep.csv",) if sweep else ())
                 + (("points.csv", "joints.csv") if export else ())):
        outputs.add(out / name, "--out", in_folder=True)
    robot = _robot(args)

    from elastocal.acquisition.logwriter import write_log_from_tables

    written = {"robot": str(out / "robot.toml")}
    if static:
        from elastocal.formats.tables import write_static_table
    else:
        from elastocal.formats.tables import read_run_table
        from elastocal.sims.runs import write_runs_csv
    robot, table, truth, truth_doc = _simulate(args, robot, static, out, progress)
    sweep_table = _compensator_sweep(args, robot, truth, truth_doc, out) if sweep else None
    progress(progress.total, "writing the table and its log", total=progress.total + 1)
    outputs.make_folder(out)
    with outputs:
        outputs.temp(out / "robot.toml").write_text(robot.to_toml(), encoding="utf-8")
        if static:
            write_static_table(outputs.temp(out / "static.csv"), table)
            written["static"] = str(out / "static.csv")
            write_log_from_tables(outputs.temp(out / "log.mcap"), robot, static=table)
            if export:
                from elastocal.sims.tracker_export import joints_csv, points_csv

                outputs.temp(out / "points.csv").write_text(points_csv(table), encoding="utf-8")
                outputs.temp(out / "joints.csv").write_text(joints_csv(table), encoding="utf-8")
                written["points"], written["joints"] = str(out / "points.csv"), str(out / "joints.csv")
        else:
            write_runs_csv(outputs.temp(out / "runs.csv"), table)
            written["runs"] = str(out / "runs.csv")
            # the log holds what the CSV holds (read back: the same numbers as a user's table)
            back = read_run_table(outputs.temp(out / "runs.csv"), robot)
            write_log_from_tables(outputs.temp(out / "log.mcap"), robot, runs=back)
            if sweep_table is not None:
                write_runs_csv(outputs.temp(out / "sweep.csv"), sweep_table)
                written["sweep"] = str(out / "sweep.csv")
        written["log"] = str(out / "log.mcap")
        outputs.temp(out / "truth.json").write_text(json.dumps(truth_doc, indent=2) + "\n", encoding="utf-8")
        written["truth"] = str(out / "truth.json")
    progress.done()
    if args.json:
        print(json.dumps(written))
    else:
        for kind, path in written.items():
            print(f"wrote {kind:<6} {path}")
    return 0
