"""`elastocal plan`: choose the calibration poses and loads (docs/plan.md).

Minimises Klimchik's industry measure at the user's test pose and process load
(design/search.py), writes plan.toml in the procedures' format
(formats/plan.py, docs/plan-format.md) with a short [check], prints the
predicted positioning accuracy, and draws Yang's map of where the first-order
model is good enough.
"""

from __future__ import annotations

from elastocal.commands._flags import DEFAULT_LOADS_PER_POSE, add_aliased, add_seed

import argparse
import json
import math
import pathlib
import time

import numpy as np

from elastocal.errors import InputError
from elastocal.model.kinds import TorqueSource


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("robot and cell")
    src.add_argument("--robot", help="robot.toml (default: the robot of --cell)")
    src.add_argument("--cell", help="cell.toml: its robot and the tracker's markers")
    src.add_argument("--markers", help="comma-separated markers to read (default: the tracker's, else all)")
    src.add_argument("--tracker-position", metavar="X,Y,Z",
                     help="the tracker in base coordinates [m]: keep only poses whose markers it sees")
    use = parser.add_argument_group("where the robot works")
    use.add_argument("--test-pose", metavar="Q1,...,QN",
                     help="the working pose [rad] (negative first value: --test-pose=-0.3,...)")
    add_aliased(use, "--wrench", "--load", dest="load", metavar="FX,FY,FZ[,MX,MY,MZ]",
                     help="the process load on the load point, base axes [N, N*m]")
    exp = parser.add_argument_group("the experiment")
    exp.add_argument("--poses", type=int, help="poses to measure (default 12; 6 with --discriminate)")
    exp.add_argument("--loads-per-pose", type=int, default=None,
                     help=f"loaded states per pose (default {DEFAULT_LOADS_PER_POSE}, as `sim static`; 1 with "
                          "--directions down; 2 with --discriminate)")
    exp.add_argument("--f-max", type=float, help="largest load force [N] (default: the size of the process force)")
    exp.add_argument("--directions", choices=("any", "down"), default="any",
                     help="load directions: any (weights and pulls, default) or down (hung weights only)")
    exp.add_argument("--candidates", type=int,
                     help="candidate poses to choose from (default 2000; 150 with --discriminate)")
    exp.add_argument("--min-height", type=float, default=0.3,
                     help="lowest height of elbow, wrist, markers and load point [m] (default 0.3)")
    exp.add_argument("--max-height", type=float, default=3.0, help="highest load point [m] (default 3.0)")
    exp.add_argument("--min-radius", type=float, default=0.5,
                     help="least distance of the load point from the axis of joint 1 [m] (default 0.5)")
    exp.add_argument("--link-radius", type=float, default=0.15,
                     help="radius of the links for the line of sight [m] (default 0.15)")
    exp.add_argument("--repeats", type=int, default=3, help="readings per marker and load state (default 3)")
    exp.add_argument("--tracker-noise", type=float, default=10e-6, help="tracker noise per reading [m] (default 1e-5)")
    exp.add_argument("--current-noise", type=float, default=0.02, help="current noise per sample [A] (default 0.02)")
    exp.add_argument("--torque", choices=[t.value for t in TorqueSource], default="current",
                     help="how the calibration will get the joint torques (default current)")
    exp.add_argument("--check-poses", type=int, default=3, help="poses of the short [check] (default 3)")
    exp.add_argument("--friction-path", metavar="U;V",
                     help="a UV/VU path for friction and the check: one value per joint, ';', one value per "
                          "joint [rad]")
    exp.add_argument("--friction-speeds", default="0.05,0.15", help="speeds of the friction path [rad/s]")
    exp.add_argument("--name", default="calibration", help="the plan's name")
    add_seed(exp, "seed of the candidate sampling")
    exp.add_argument("--stiffness-only", action="store_true",
                     help="choose the poses for the stiffness alone (K40); by default they are exchanged so that "
                          "the kinematic set and the tracker registration are observable too (docs/absolute.md)")
    prior = parser.add_argument_group("prior stiffness (noise model and map)")
    prior.add_argument("--calibration", help="a calibration JSON whose k1..k6 serve as the prior")
    prior.add_argument("--stiffness", metavar="K1,...,KN",
                       help="prior joint stiffness, one per joint [N*m/rad; N/m for a prismatic joint]")
    out = parser.add_argument_group("output")
    out.add_argument("--out", required=True, help="plan.toml to write")
    out.add_argument("--map", help="write the first-order map (Y Fig. 4-6) here, .png or .svg")
    out.add_argument("--map-grid", type=int, default=25, help="grid points per axis of the map (default 25)")
    add_aliased(out, "--map-wrench", "--map-load", dest="map_load", metavar="FX,FY,FZ[,MX,MY,MZ]",
                     help="load of the map (default: F_max split equally over +x, +y, -z)")
    out.add_argument("--force", action="store_true", help="overwrite --out and --map if they exist")
    out.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    from elastocal.commands.plan_discriminate import add_arguments as add_discriminate

    add_discriminate(parser)


def numbers(text: str, sizes: tuple[int, ...], flag: str) -> tuple[float, ...]:
    """Comma-separated finite numbers, as many as one of ``sizes``."""
    parts = [p.strip() for p in text.split(",") if p.strip()]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise InputError(f"not numbers: {text!r}", source=flag) from None
    if len(values) not in sizes:
        want = " or ".join(str(s) for s in sizes)
        raise InputError(f"expected {want} comma-separated numbers, got {len(values)}", source=flag)
    if not all(math.isfinite(v) for v in values):
        raise InputError("values must be finite", source=flag)
    return values


def _wrench(text: str, flag: str) -> tuple[float, ...]:
    v = numbers(text, (3, 6), flag)
    return v + (0.0, 0.0, 0.0) if len(v) == 3 else v


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _prior(args: argparse.Namespace, robot=None) -> tuple[tuple[float, ...], str]:
    from elastocal.design.search import DEFAULT_PRIOR_STIFFNESS

    n_joints = 6 if robot is None else robot.n_joints
    if args.calibration and args.stiffness:
        raise InputError("give --calibration or --stiffness, not both", source="--stiffness")
    if args.calibration:
        from elastocal.formats.calibration import read_calibration

        cal = read_calibration(args.calibration)
        k = tuple(cal.stiffness())
        if len(k) != n_joints:
            raise InputError(f"the calibration holds {len(k)} joint stiffnesses; the robot has {n_joints} joints",
                             source=args.calibration)
        where = f"calibration {args.calibration}"
    elif args.stiffness:
        k = numbers(args.stiffness, (n_joints,), "--stiffness")
        where = "--stiffness"
    else:
        if robot is not None and n_joints != 6:
            return tuple(robot.prior_stiffness()), ("robot.toml's stiffness where given, else Yang's analysis "
                                                    "values (give --calibration for a better noise model)")
        return DEFAULT_PRIOR_STIFFNESS, "Yang's analysis values (give --calibration for a better noise model)"
    if not all(v > 0 for v in k):
        raise InputError("stiffness values must be > 0", source="--stiffness" if args.stiffness else args.calibration)
    return k, where


def _friction(args: argparse.Namespace, robot=None):
    from elastocal.formats.plan import FrictionSpec

    if not args.friction_path:
        return ()
    halves = args.friction_path.split(";")
    if len(halves) != 2:
        raise InputError("expected U;V: six joint values, ';', six joint values", source="--friction-path")
    n_joints = 6 if robot is None else robot.n_joints
    u = numbers(halves[0], (n_joints,), "--friction-path")
    v = numbers(halves[1], (n_joints,), "--friction-path")
    if robot is not None:
        for half, values in (("U", u), ("V", v)):
            for j, (x, lo, hi) in enumerate(zip(values, robot.lower, robot.upper), start=1):
                if not lo <= x <= hi:
                    raise InputError(f"{half}: q{j} = {x} rad is outside the joint limits [{lo:.4g}, {hi:.4g}]"
                                     + ("; degrees? angles are radians" if abs(x) > 2 * math.pi else ""),
                                     source="--friction-path")
    if u == v:
        raise InputError("U and V are the same pose; the path must move", source="--friction-path")
    speeds = numbers(args.friction_speeds, tuple(range(1, 9)), "--friction-speeds")
    if not all(s > 0 for s in speeds):
        raise InputError("speeds must be > 0", source="--friction-speeds")
    return (FrictionSpec("F1", start=u, end=v, speeds_rad_s=speeds),)


def _check_flags(args: argparse.Namespace) -> None:
    """The numeric flags checked (and --loads-per-pose defaulted) before anything is computed."""
    if args.f_max is not None and not (math.isfinite(args.f_max) and args.f_max > 0):
        raise InputError(f"must be > 0, got {args.f_max}", source="--f-max")
    if args.loads_per_pose is None:       # hung weights offer one direction only
        args.loads_per_pose = 1 if args.directions == "down" else DEFAULT_LOADS_PER_POSE
    for flag in ("poses", "loads_per_pose", "candidates", "repeats", "check_poses", "map_grid"):
        if getattr(args, flag) < 1:
            raise InputError(f"must be at least 1, got {getattr(args, flag)}", source="--" + flag.replace("_", "-"))
    if args.seed < 0:
        raise InputError(f"must be >= 0, got {args.seed}", source="--seed")


def _robot_and_markers(args: argparse.Namespace):
    """(the cell or None, the robot, the markers to read) from --robot, --cell and --markers."""
    from elastocal.formats.robot_toml import load_robot

    cell = None
    if args.cell:
        from elastocal.drivers.config import load_cell_config

        cell = load_cell_config(args.cell)
    if args.robot:
        robot = load_robot(args.robot)
    elif cell is not None:
        robot = cell.load_robot()
    else:
        raise InputError("missing --robot robot.toml (or --cell cell.toml)", source="--robot")
    if args.markers:
        markers = tuple(m.strip() for m in args.markers.split(",") if m.strip())
    elif cell is not None and cell.tracker is not None:
        markers = tuple(m for m in cell.tracker.markers if m in robot.marker_names)
    else:
        markers = robot.marker_names
    for m in markers:
        if m not in robot.marker_names:
            raise InputError(f"unknown marker {m!r}; the robot has {', '.join(robot.marker_names)}", source="--markers")
    if not markers:
        raise InputError("no marker to read", source="--markers")
    return cell, robot, markers


def _test_pose(args: argparse.Namespace, robot):
    """(the working pose and its process load, the largest load force [N])."""
    from elastocal.design import search as dz

    if args.load is None:
        raise InputError("the process load is required: --wrench FX,FY,FZ[,MX,MY,MZ]", source="--wrench")
    test = dz.TestPose(q=numbers(args.test_pose, (robot.n_joints,), "--test-pose"),
                       wrench=_wrench(args.load, "--wrench"))
    for j, (v, lo, hi) in enumerate(zip(test.q, robot.lower, robot.upper), start=1):
        if not lo <= v <= hi:
            raise InputError(f"q{j} = {v} {robot.joints[j - 1].unit} is outside the joint limits [{lo:.4g}, {hi:.4g}]",
                             source="--test-pose")
    f_max = args.f_max if args.f_max is not None else float(np.linalg.norm(test.wrench[:3]))
    if f_max <= 0:
        raise InputError("the process load has no force, so the largest load force is unknown: give --f-max",
                         source="--load")
    return test, f_max


def _plan_json(args: argparse.Namespace, robot, planned, out, markers, f_max: float, tracker, prior,
               prior_source: str, fmap, started: float) -> dict:
    """The --json object of the plan."""
    design, candidates, check, check_spec = planned.design, planned.candidates, planned.check, planned.check_spec
    loads, geometry = planned.loads, planned.geometry
    q = design.quality
    names = [f"k{j}" for j in range(1, robot.n_joints + 1)]
    obj = {
        "plan": str(out),
        "poses": {pid: [float(v) for v in qq] for pid, qq in zip(planned.pose_ids, design.q)},
        "loads": [{"id": s.id, "force": [float(v) for v in f], "mass_kg": s.mass_kg}
                  for s, f in zip(loads, design.forces)],
        "markers": list(markers),
        "f_max": f_max,
        "k40": _finite(q.k40),
        "k40_random_median": _finite(float(np.median(planned.baseline_k40))),
        "accuracy": {"value": _finite(q.accuracy_m), "unit": "m"},
        "accuracy_random": {"value": _finite(planned.random_quality.accuracy_m), "unit": "m"},
        "test_deflection": {"value": q.test_deflection_m, "unit": "m"},
        "stiffness_relative_std": {n: _finite(v) for n, v in zip(names, q.stiffness_rel_std)},
        "check": {"poses": list(check_spec.poses), "load": check_spec.load, "friction": check_spec.friction,
                  "k40": _finite(check.quality.k40), "accuracy": _finite(check.quality.accuracy_m)},
        "candidates": {"kept": len(candidates.q), "sampled": candidates.sampled, "accepted": candidates.accepted,
                       "rejected": dict(candidates.rejected)},
        "visibility_checked": tracker is not None,
        "prior": {"stiffness": list(prior), "source": prior_source},
        "map": None if fmap is None else {"path": args.map, "good_fraction": fmap.good_fraction,
                                          "torque": fmap.torque, "load": list(fmap.wrench)},
        "kinematic": None if geometry is None else geometry.to_json(),
        "planning_s": planned.planning_s,
        "time_s": time.monotonic() - started,
    }
    return obj


def _print_text(args: argparse.Namespace, obj: dict, planned, markers, out, tracker, prior_source: str,
                fmap) -> None:
    """The text the command prints without --json."""
    design, candidates, check, check_spec = planned.design, planned.candidates, planned.check, planned.check_spec
    loads, geometry, q = planned.loads, planned.geometry, planned.design.quality
    names = [f"k{j}" for j in range(1, len(q.stiffness_rel_std) + 1)]
    lines = [f"plan: {len(design.q)} poses x {len(loads)} loads (+ the unloaded reference), markers "
             f"{', '.join(markers)}, {args.repeats} readings each -> {out}"]
    for s in loads:
        lines.append(f"  load {s.id}: {s.description}")
    lines.append(f"industry measure K40 = {q.k40:.4g} ({args.poses} random candidate poses, same loads: median "
                 f"{np.median(planned.baseline_k40):.4g})")
    if geometry is not None:
        g = obj["kinematic"]
        lines.append(f"kinematic set ({len(g['identifiable']) - 6} parameters and the registration): observability "
                     f"index O1 = {g['o1']:.4g} (stiffness-only plan {g['o1_stiffness_only']:.4g}, random median "
                     f"{g['o1_random_median']:.4g}); largest predicted std {g['max_std']['value'] * 1e6:.1f} µm; "
                     f"K40 {g['k40_stiffness_only']:.4g} for the stiffness alone")
    rel = 100.0 * q.accuracy_m / q.test_deflection_m if q.test_deflection_m > 0 else math.nan
    lines.append(f"predicted accuracy at the test pose: {q.accuracy_m * 1e6:.2f} µm rms after compensation "
                 f"(deflection there {q.test_deflection_m * 1e3:.3f} mm under the process load, {rel:.3f} %; "
                 f"random poses: {planned.random_quality.accuracy_m * 1e6:.2f} µm)")
    lines.append("predicted stiffness std: " + ", ".join(
        f"{n} {v * 100:.2f} %" if math.isfinite(v) else f"{n} unidentifiable" for n, v in zip(names, q.stiffness_rel_std)))
    lines.append(f"check: poses {', '.join(check_spec.poses)} under {check_spec.load}"
                 + (f", friction path {check_spec.friction}" if check_spec.friction else "")
                 + f" (a calibration from the check's data alone would reach {check.quality.accuracy_m * 1e6:.1f} µm "
                   "at the test pose)")
    rejected = ", ".join(f"{n} {r}" for r, n in candidates.rejected if n)
    lines.append(f"candidates: {len(candidates.q)} poses; {candidates.accepted} of {candidates.sampled} drawn "
                 "respected the workspace" + (f" (rejected: {rejected})" if rejected else ""))
    if tracker is None:
        lines.append("marker visibility not checked: give --tracker-position")
    lines.append(f"prior stiffness: {prior_source}")
    if fmap is not None:
        lines.append(f"first-order map: {args.map} (good enough on {fmap.good_fraction * 100:.0f} % of (q2, q3))")
    lines.append(f"planning {planned.planning_s:.2f} s, total {obj['time_s']:.2f} s")
    print("\n".join(lines))


def run(args: argparse.Namespace) -> int:
    from elastocal.progress import long_work

    with long_work("plan", 1, quiet=args.json) as progress:      # the planning's stages, thousands of poses
        return _run(args, progress)


def _run(args: argparse.Namespace, progress) -> int:
    if args.discriminate is not None:
        from elastocal.commands import plan_discriminate

        args.poses = 6 if args.poses is None else args.poses
        args.candidates = 150 if args.candidates is None else args.candidates
        args.loads_per_pose = 2 if args.loads_per_pose is None else args.loads_per_pose
        return plan_discriminate.run(args)
    for flag in ("given", "static"):
        if getattr(args, flag):
            raise InputError("only with --discriminate", source="--" + flag)
    if args.test_pose is None:
        raise InputError("the working pose is required: --test-pose Q1,...,Q6 (or --discriminate EFFECT)",
                         source="--test-pose")
    args.poses = 12 if args.poses is None else args.poses
    args.candidates = 2000 if args.candidates is None else args.candidates
    from elastocal.design.planning import PLAN_STAGES, plan_calibration
    from elastocal.design import search as dz
    from elastocal.sims import first_order_map as fom

    from elastocal.commands._outputs import Outputs

    started = time.monotonic()
    outputs = Outputs(force=args.force, inputs=[(args.robot, "--robot"), (args.cell, "--cell"),
                                                (args.calibration, "--calibration")])
    out = outputs.add(args.out, "--out")
    if args.map:
        if pathlib.Path(args.map).suffix.lower() not in (".png", ".svg"):
            raise InputError("the map is written as .png or .svg", source="--map")
        outputs.add(args.map, "--map")
    _check_flags(args)
    cell, robot, markers = _robot_and_markers(args)
    test, f_max = _test_pose(args, robot)
    tracker = numbers(args.tracker_position, (3,), "--tracker-position") if args.tracker_position else None
    if tracker is None and cell is not None and cell.tracker is not None and cell.tracker.base_p_tracker is not None:
        tracker = np.array(cell.tracker.base_p_tracker)
    workspace = dz.Workspace(f_max_n=f_max, directions=args.directions, min_height_m=args.min_height,
                             max_height_m=args.max_height, min_radius_m=args.min_radius, base_p_tracker=tracker,
                             link_radius_m=args.link_radius)
    current_a = args.current_noise if TorqueSource(args.torque) == TorqueSource.CURRENT else 0.0
    noise = dz.NoiseModel(tracker_m=args.tracker_noise, current_a=current_a, repeats=args.repeats)
    prior, prior_source = _prior(args, robot)
    friction = _friction(args, robot)
    try:
        planned = plan_calibration(robot, test, workspace, noise, markers=markers, n_poses=args.poses,
                                   loads_per_pose=args.loads_per_pose, n_candidates=args.candidates,
                                   n_check=args.check_poses, prior_stiffness=prior, friction=friction,
                                   name=args.name, repeats=args.repeats, seed=args.seed, source=str(out),
                                   geometry=not args.stiffness_only, progress=progress)
    except InputError as exc:
        # the plan text is made from the flags: name the flag the bad value came from
        if exc.column and exc.column.startswith("friction"):
            raise InputError(exc.detail, source="--friction-path") from None
        raise
    fmap = None
    if args.map:
        progress(PLAN_STAGES, "the first-order map", total=PLAN_STAGES + 1)
        map_load = (_wrench(args.map_load, "--map-wrench") if args.map_load
                    else tuple(f_max / math.sqrt(3.0) * np.array([1.0, 1.0, -1.0])) + (0.0, 0.0, 0.0))
        fmap = fom.first_order_map(robot, q_base=test.q, wrench=map_load, stiffness=prior, markers=markers,
                                  torque=TorqueSource(args.torque), n_grid=args.map_grid)
    progress.done()
    with outputs:
        if fmap is not None:
            fom.plot_first_order_map(fmap, outputs.temp(args.map), test_q=test.q, poses=planned.design.q)
        outputs.temp(out).write_text(planned.text, encoding="utf-8")
    obj = _plan_json(args, robot, planned, out, markers, f_max, tracker, prior, prior_source, fmap, started)
    if args.json:
        print(json.dumps(obj))
        return 0
    _print_text(args, obj, planned, markers, out, tracker, prior_source, fmap)
    return 0
