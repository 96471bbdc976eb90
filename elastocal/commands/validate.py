"""`elastocal validate`: a calibration against data it was not fitted on (docs/cli.md)."""

from __future__ import annotations

import argparse
import json

import numpy as np

from elastocal.commands._inputs import add_tracker_arguments, calibration_robot, prior_line, tracker_prior
from elastocal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robot", help="robot.toml (docs/formats.md §1): the nominal description (default: the "
                                        "description the calibration holds)")
    parser.add_argument("--calibration", required=True, help="calibration JSON (docs/formats.md §4)")
    parser.add_argument("--static", required=True, help="static table (docs/formats.md §2), other poses or another "
                                         "day's data than the fit's (docs/absolute.md)")
    parser.add_argument("--keep-frame", action="store_true",
                        help="keep the calibration's tracker registration (tracker_frame) instead of "
                             "registering the tracker afresh on these data")
    add_tracker_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _row(name: str, stats) -> str:
    def um(x: float) -> str:
        return f"{x * 1e3:.3f} mm" if x >= 1e-3 else f"{x * 1e6:.1f} µm"

    return (f"  {name:<11} rms {um(stats.rms):>10}  mean {um(stats.mean):>10}  p95 {um(stats.p95):>10}  "
            f"max {um(stats.max):>10}  ({stats.n} components)")


def run(args: argparse.Namespace) -> int:
    from elastocal.progress import long_work

    with long_work("validate", 2, quiet=args.json) as progress:
        return _run(args, progress)


def _run(args: argparse.Namespace, progress) -> int:
    from elastocal.identify.accuracy import validate
    from elastocal.formats.calibration import file_sha256, read_calibration
    from elastocal.formats.tables import read_static_table

    progress(0, "reading the calibration and the table")
    calibration = read_calibration(args.calibration)
    robot = calibration_robot(args, calibration)
    table = read_static_table(args.static, robot)
    if not len(table):
        raise InputError("the table holds no readings", source=args.static)
    prior = tracker_prior(args)
    progress(1, "the calibrated robot against the readings")
    result = validate(robot, calibration, table, keep_frame=args.keep_frame, calibration_name=args.calibration)
    progress.done()
    obj = result.to_json()
    # the same bytes as a file the calibration was fitted on: an accuracy of the fit, not a validation
    fit_data = file_sha256(args.static) in {d.sha256 for d in calibration.data if d.sha256}
    obj["fit_data"] = fit_data
    if prior is not None:     # where the registration puts the tracker against where the cell says it stands
        found = np.asarray(obj["registration"]["base_p_tracker"])
        obj["registration"]["prior"] = {"base_p_tracker": list(prior.base_p_tracker), "source": prior.source,
                                        "offset": float(np.linalg.norm(found - np.asarray(prior.base_p_tracker))),
                                        "unit": "m"}
    if result.note() is not None:
        args.notes.append(f"elastocal validate: note: {result.note()}")
    if args.json:
        print(json.dumps(obj))
        return 0
    frame = "kept from the calibration" if args.keep_frame else "registered afresh on these data"
    print(f"{robot.name}: {args.calibration} against {args.static} ({result.poses} poses; tracker {frame})")
    print("absolute positions:")
    print(_row("nominal", result.absolute_nominal))
    print(_row("calibrated", result.absolute_calibrated))
    if result.deflection_nominal is not None:
        print("deflections:")
        print(_row("nominal", result.deflection_nominal))
        print(_row("calibrated", result.deflection_calibrated))
    else:
        print("deflections: none (a table without loads)")
    a_n, a_c = result.absolute_nominal, result.absolute_calibrated
    line = prior_line(prior, obj["registration"])
    if line:
        print(line)
    which = ("of the fit data (the calibration was fitted on this file: its accuracy on the fit, not a "
             "validation)" if fit_data else "not used in the fit")
    print(f"absolute error on {result.poses} poses {which}: nominal {a_n.rms * 1e6:.0f} µm rms "
          f"(max {a_n.max * 1e3:.2f} mm) → calibrated {a_c.rms * 1e6:.1f} µm (max {a_c.max * 1e6:.0f} µm)")
    return 0
