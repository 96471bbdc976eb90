"""`elastocal demo`: the whole chain on the embedded simulated cell.

1. builds the simulated HH-150 cell, with an effect the default model lacks
   hidden in its physics;
2. runs the guided static procedure on it, prompts answered automatically,
   recording every sample to an MCAP log: by default in lockstep on the cell's
   simulated clock (acquisition/lockstep.py: same seed, same numbers); with
   ``--realtime`` the cell is served in-process (CiA 402 drives on a virtual CAN
   bus, the laser tracker over TCP, the Modbus cell controller) and the
   procedure runs through the real drivers on the wall clock;
3. identifies the joint stiffness from the log, from currents and from forces;
4. diagnoses the model, names the missing effect, adds it, and shows the error
   falling to the noise floor; writes the HTML report;
5. compensates a process path (Yang's 1500 N path) with the calibration and
   runs it on the simulated cell;
6. prints the table of errors before and after.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import pathlib
import tempfile
import textwrap
import time

import numpy as np

from elastocal.commands._flags import add_seed
from elastocal.commands._format import format_parameters, verdict_line

DEMO_POSES = 12
DEMO_REPEATS = 3
DEMO_DRIVE_RATE_HZ = 200.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_seed(parser, "random seed of the simulated cell")
    parser.add_argument("--out", help="directory for the files the demo writes (default: a temporary one); "
                                      "a second run into it replaces the files of the first")
    parser.add_argument("--hidden",
                        help="effect the simulated cell hides from the default model: none, link_compliance, "
                             "thermal_drift, backlash (default link_compliance; none on the URDF robot, whose "
                             "bent links are not modelled)")
    parser.add_argument("--poses", type=int, default=DEMO_POSES, help=f"poses of the static procedure "
                                                                      f"(default {DEMO_POSES})")
    parser.add_argument("--realtime", action="store_true",
                        help="serve the simulated devices over CAN, TCP and Modbus and run the procedure through "
                             "the real drivers on this computer's clock, as on a real cell (slower; the numbers "
                             "then vary a little between runs); by default the procedure and the simulated "
                             "devices share the cell's simulated clock and the same seed prints the same numbers")
    parser.add_argument("--robot", default="hh150", choices=DEMO_ROBOTS,
                        help="the simulated cell: hh150 (the six-axis arm, default), hh150_track (the arm on "
                             "a floor track, seven joints) or hh150_urdf (the arm described by a URDF: its "
                             "geometric calibration is of the joint origins)")


#: the bundled robots whose simulated cell ships (sims/data)
DEMO_ROBOTS = ("hh150", "hh150_track", "hh150_urdf")


#: the file that marks a folder as the demo's own (a second run into it replaces the demo's files)
DEMO_MARK = ".elastocal-demo"
MARK_TEXT = "elastocal demo writes here: cell.toml, plan.toml, calibration.mcap, report.html, cal.json, compensated.*\n"


def _demo_folder(path: str) -> pathlib.Path:
    """The demo's folder: a new one, an empty one, or one an earlier demo marked as its own
    (:data:`DEMO_MARK`); a folder with anything else in it is refused, nothing written."""
    from elastocal.commands._outputs import check_folder
    from elastocal.errors import InputError

    out = check_folder(path, "--out")
    if out.is_dir() and any(out.iterdir()) and not (out / DEMO_MARK).is_file():
        raise InputError(f"holds files the demo did not make (no {DEMO_MARK} in it); give a new or empty folder: "
                         "the demo replaces only its own files", source=str(out))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create: {exc.strerror}", source=str(out)) from None
    return out


class _Say:
    """The step headlines, in plain words, on the terminal as the demo goes (the tables of each
    step are kept for after the findings: plain words first, numbers after)."""

    def __init__(self, stream=None) -> None:
        import sys

        self.out = stream if stream is not None else sys.stdout
        self.t0 = time.perf_counter()
        self.step = 0

    def __call__(self, text: str) -> None:
        import sys

        self.step += 1
        print(f"\n[{self.step}] {text}  (t = {time.perf_counter() - self.t0:.0f} s)", file=self.out, flush=True)
        if sys.stdout is not self.out:          # the step's tables kept for later: under its headline
            print(f"\n[{self.step}] {text}")


def candidate_line(k: int, c, rms_before: float) -> str:
    """One candidate of the diagnosis as `diagnose` words it: an implausible fit (a drift of
    metres an hour, a negative lost motion) is no ordinary candidate and says why."""
    if c.implausible:
        words = f"implausible: {c.implausible}"
    elif c.significant:
        words = f"ΔBIC {c.delta_bic:+.0f}   {c.evidence}"
    else:
        words = f"not significant (ΔBIC {c.delta_bic:+.0f})"
    return f"  {k}. {c.effect:<18} {_um(rms_before)} → {_um(c.rms_after)}   {words}"


def _um(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e6:.1f} µm"


def run(args: argparse.Namespace) -> int:
    from elastocal.errors import InputError
    from elastocal.sims.cell import DEMO_HIDDEN, DEMO_HIDDEN_URDF

    from elastocal.formats.robot_toml import bundled_robot

    urdf = bundled_robot(args.robot).urdf is not None
    if args.hidden is None:
        args.hidden = "none" if urdf else "link_compliance"
    if args.hidden not in DEMO_HIDDEN:
        raise InputError(f"choose one of {', '.join(DEMO_HIDDEN)}; got {args.hidden!r}", source="--hidden")
    if urdf and args.hidden not in DEMO_HIDDEN_URDF:
        raise InputError(f"a URDF robot's bent links are not modelled beside its joint origins; choose one of "
                         f"{', '.join(DEMO_HIDDEN_URDF)} for --robot {args.robot}", source="--hidden")
    if args.poses < 4:
        raise InputError("at least 4 poses", source="--poses")
    if args.seed < 0:
        raise InputError(f"must be >= 0, got {args.seed}", source="--seed")
    out = _demo_folder(args.out) if args.out else pathlib.Path(tempfile.mkdtemp(prefix="elastocal-demo-"))
    (out / DEMO_MARK).write_text(MARK_TEXT, encoding="utf-8")
    say = _Say()
    details = io.StringIO()         # each step's tables: printed after the plain-words findings
    with contextlib.redirect_stdout(details):
        found = _run_steps(args, out, say)
    _print_findings(args, out, found, details.getvalue())
    return 0


# long: the demo's story, steps 1-6 one after the other, reads best in one piece
def _run_steps(args: argparse.Namespace, out: pathlib.Path, say: _Say) -> dict:
    """Steps 1-6 (the module's docstring); their tables go to stdout (kept by the caller)."""
    from elastocal.acquisition.export import load_log
    from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
    from elastocal.acquisition.lockstep import run_lockstep_calibration
    from elastocal.acquisition.procedures import run_calibration
    from elastocal.commands._cell import lockstep_world, procedure_cell
    from elastocal.commands._outputs import atomic, write_text_atomic
    from elastocal.compensation.files import write_compensated_csv, write_krl, write_rapid
    from elastocal.compensation.ik import yang_path
    from elastocal.compensation.model import CompensationModel
    from elastocal.compensation.trajectory import compensate_path
    from elastocal.compensation.validate import YANG_WRENCH, validate_on_sim
    from elastocal.diagnose.pipeline import Identification
    from elastocal.formats.calibration import write_calibration
    from elastocal.identify.absolute import identify_absolute
    from elastocal.diagnose.static import diagnose_static
    from elastocal.report.html import render_report
    from elastocal.identify.static import identify_static
    from elastocal.sims.cell import CellTruth, SimCell
    from elastocal.sims.serve import example_cell_config
    from elastocal.model.kinds import KinematicForm, TorqueSource
    from elastocal.sims.static import random_poses
    from elastocal.model.effects import get_effect
    from elastocal.model.effects.base import Compensation

    # 1. the simulated cell: built with its real geometry (kinematic errors), the tracker 3.7 m away and turned
    cell_hidden = "kinematic_errors" if args.hidden == "none" else f"{args.hidden},kinematic_errors"
    config = example_cell_config(can_channel=f"demo-{args.seed}", robot=args.robot, seed=args.seed,
                                 hidden=cell_hidden, move_speed_rad_s=2.0)
    # a static procedure needs no 1 kHz current stream: 200 Hz keeps the demo light on 2 cores
    config = dataclasses.replace(config, drives=tuple(dataclasses.replace(d, rate_hz=DEMO_DRIVE_RATE_HZ)
                                                      for d in config.drives))
    robot = config.load_robot()
    truth = CellTruth.for_robot(robot).with_hidden(cell_hidden)
    write_text_atomic(out / "cell.toml", config.to_toml())
    served = ("served over CANopen (TPDO on SYNC), TCP and Modbus and read through the real drivers on this "
              "computer's clock" if args.realtime else
              "sampled in lockstep with the procedure on the cell's simulated clock (--realtime serves them over "
              "CANopen, TCP and Modbus instead)")
    say(f"Simulated cell '{config.name}': a {robot.name} robot whose {robot.n_joints} servo drives report their motor "
        f"currents {DEMO_DRIVE_RATE_HZ:.0f} times a second, a laser tracker that measures 3 markers on the tool, "
        f"and the cell controller; the devices {served}. Hidden in its physics, for elastocal to find: "
        f"{args.hidden}; and the robot as built differs from its drawing by 0.02-0.05 deg and 0.1-0.5 mm, "
        "with the tracker standing 3.7 m away, turned.")

    # 2. the guided procedure
    poses = random_poses(robot, args.poses, np.random.default_rng(args.seed))
    loads = (LoadSpec("L1", mass_kg=60.0), LoadSpec("L2", mass_kg=110.0),
             LoadSpec("L3", force_n=(650.0, -300.0, -400.0)))
    plan_text = plan_toml(poses=poses, loads=loads, markers=robot.marker_names, repeats=DEMO_REPEATS,
                          reading_s=0.02, settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=10.0))
    write_text_atomic(out / "plan.toml", plan_text)
    plan = parse_plan(plan_text, source=str(out / "plan.toml"))
    log = out / "calibration.mcap"
    say(f"Guided static procedure (answered automatically, --yes): {args.poses} poses, unloaded + 3 loads "
        f"(60 kg, 110 kg, a 850 N cable pull), 3 markers, {DEMO_REPEATS} readings each; every drive and tracker "
        f"sample goes to {log.name} ...")
    if args.realtime:
        with procedure_cell(config, sim=True) as (cell, world):
            outcome = run_calibration(cell, plan, log, yes=True, world=world, overwrite=True)
    else:
        world, clock = lockstep_world(config)
        outcome = run_lockstep_calibration(config, plan, log, world=world, clock=clock, overwrite=True)
    print(f"    {outcome.status}: {outcome.steps_done} steps in {outcome.duration_s:.0f} s; log {log} "
          f"({log.stat().st_size / 1e6:.1f} MB)")

    # 3. identification from the log alone
    robot_log, static, _ = load_log(log)
    truth_params = truth.parameters(robot)
    k_names = [f"k{j}" for j in range(1, robot.n_joints + 1)]
    truth_k = {k: truth_params[k] for k in k_names}
    fits = {}
    for torque in (TorqueSource.CURRENT, TorqueSource.FORCE):
        fits[torque] = identify_static(robot_log, static, torque=torque)
    say("Identified the joint stiffness from the log (exact form), from motor currents and from forces:")
    for torque, fit in fits.items():
        print(f"  {torque}-based:")
        print(format_parameters(fit.to_json()["parameters"], truth_k))
        print("  " + verdict_line(fit.rms, fit.noise_floor))

    # 4. diagnosis: where the model fails, which effect is missing, add it
    diag = diagnose_static(robot_log, static)
    say("Diagnosis of the current-based model:")
    print(f"  residual {_um(diag.fit.rms)} rms, noise floor {_um(diag.noise_floor)}")
    for i, c in enumerate(diag.candidates[:4], start=1):
        print(candidate_line(i, c, diag.fit.rms))
    final = diag.final
    if diag.verdict and diag.verdict_candidate is not None:
        print(f"  verdict: {diag.verdict} — adding it: residual {_um(diag.fit.rms)} → {_um(final.rms)} "
              f"(noise floor {_um(final.noise_floor)})")
        added = {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in diag.verdict_candidate.parameters}
        truth_added = {k: truth_params[k] for k in added if k in truth_params}
        print(format_parameters(added, truth_added or None))
    else:
        print("  residual at the noise floor; no missing effect found")
    # 4b. absolute accuracy: geometry and registration with the elastic model
    absolute = diag.absolute
    full_model = (*final.model, "kinematic_errors", "tracker_frame")
    geo = identify_absolute(robot_log, static, model=full_model)
    say("Absolute accuracy (the tracker's absolute positions, after the best rigid registration):")
    print(f"  nominal geometry:    {_um(absolute.base.rms)} rms, max {absolute.base.max * 1e3:.2f} mm "
          f"(noise floor {_um(absolute.base.noise_floor)})")
    print(f"  + kinematic_errors:  {_um(geo.rms)} rms, max {_um(geo.max)} (noise floor {_um(geo.noise_floor)}); "
          f"{len(geo.kinematic_names) - len([n for n in geo.unidentifiable if n in geo.kinematic_names])} "
          f"identifiable of {len(geo.kinematic_names)} kinematic parameters, absorbed: "
          f"{', '.join(n for n in geo.unidentifiable if n in geo.kinematic_names)}")
    worst = sorted(absolute.base.per_pose(), key=lambda p: -p["max"])[:3]
    print("  worst poses before: " + ", ".join(f"{p['pose']} ({p['max'] * 1e3:.2f} mm)" for p in worst))
    report = out / "report.html"
    write_text_atomic(report, render_report(robot_log, diag, inputs=[str(log)]))
    calibration = Identification(model=geo.model, fit=geo, runs=None).calibration(
        robot.name, [log], robot_description=robot_log.to_toml())
    with atomic(out / "cal.json") as tmp:
        write_calibration(tmp, calibration)
    print(f"  report: {report}; calibration: {out / 'cal.json'}")

    # 5. compensated trajectory on the simulated cell
    comp = robot.compensator.nominal_parameters() if robot.compensator is not None else None
    k_params, k_source = _stiffness(final, geo, k_names)
    k = np.array([p.value for p in k_params])
    model = CompensationModel(robot=robot, stiffness=k, compensator=None if comp is None else tuple(comp))
    path = yang_path(robot)
    wrench = np.tile(np.asarray(YANG_WRENCH, dtype=float), (len(path), 1))
    result = compensate_path(model, path.q, wrench, form=KinematicForm.EXACT)
    for name, writer in (("compensated.csv", write_compensated_csv), ("compensated.src", write_krl),
                         ("compensated.mod", write_rapid)):
        with atomic(out / name) as tmp:
            writer(tmp, path.t, result)
    validation = validate_on_sim(SimCell(robot, truth), model, path, YANG_WRENCH).summary()
    say(f"Compensated Yang's path (x 1.2 → 1.8 m at z 0.116 m, 10 mm/s, 1500 N process load, {len(path)} points) "
        f"with the calibration and ran it on the simulated cell: compensated.csv, .src (KUKA KRL), .mod (ABB RAPID)")

    # 6. the table of errors
    say("Errors before and after")
    rows = [
        ("static deflection residual, joint stiffness only", diag.fit.rms, diag.noise_floor),
        (f"static deflection residual, + {diag.verdict}" if diag.verdict else "static residual, final model",
         final.rms, final.noise_floor),
        ("absolute position error, nominal geometry (rms)", absolute.base.rms, absolute.base.noise_floor),
        ("absolute position error, + kinematic_errors, tracker_frame (rms)", geo.rms, geo.noise_floor),
        ("tool error along the path, uncompensated (max)", validation["uncompensated"]["max"], None),
        ("tool error along the path, first-order compensation (max)", validation["first_order"]["max"], None),
        ("tool error along the path, exact compensation (max)", validation["exact"]["max"], None),
    ]
    print(f"  {'':<66} {'error':>10} {'noise floor':>12}")
    for label, value, floor in rows:
        print(f"  {label:<66} {_um(value):>10} {_um(floor):>12}")
    if diag.verdict and get_effect(diag.verdict).compensation is not Compensation.NO_PATH_DEFLECTION:
        print(f"  (the compensation model holds the joint springs; what {diag.verdict} adds on the path is what "
              "exact compensation leaves)")
    err = np.abs(k / truth.stiffness - 1) * 100
    marked = getattr(geo if k_source.startswith("with the as-built") else final, "undetermined", {})
    determined = [e for p, e in zip(k_params, err) if p.name not in marked]
    worst = f"worst error {max(determined):.2f} %" if determined else "no stiffness determined"
    left = f" ({', '.join(sorted(marked))} not determined: no error claimed)" if marked else ""
    print(f"\n  stiffness from currents, {k_source}: {worst} against the simulator's truth{left}")
    return {"diag": diag, "final": final, "err": err, "validation": validation, "absolute": absolute, "geo": geo,
            "truth_k": truth_k, "log": log, "outcome": outcome, "k": (k_params, k_source)}


def _stiffness(final, geo, k_names: list[str]) -> tuple[list, str]:
    """The joint stiffness the calibration holds, and where it comes from: the joint fit's with the
    as-built geometry when it reached its floor. The deflection fit takes the drawing's geometry, whose
    errors (0.02-0.05 deg on the arm) move the weakest spring, the seven-joint cell's carriage, by 2 std
    on average; the joint fit corrects the geometry with the springs."""
    at_floor = geo.noise_floor is not None and geo.rms <= 1.3 * geo.noise_floor
    fitted = {p.name: p for p in geo.parameters} if at_floor else {}
    source = "with the as-built geometry" if at_floor else "final model"
    return [fitted.get(n) or final.parameter(n) for n in k_names], source


def _print_findings(args: argparse.Namespace, out: pathlib.Path, found: dict, details: str) -> None:
    """What it found in plain words, the stiffness against the truth, then every step's tables."""
    from elastocal.commands._outputs import write_text_atomic
    from elastocal.commands._plain import demo_findings

    diag, final, err, validation = found["diag"], found["final"], found["err"], found["validation"]
    absolute, geo, truth_k, log, outcome = (found[k] for k in ("absolute", "geo", "truth_k", "log", "outcome"))
    cand = diag.verdict_candidate
    k_params, k_source = found["k"]
    fit_k = geo if k_source.startswith("with the as-built") else final
    undetermined = getattr(fit_k, "undetermined", {})
    open_joints = [j for j, p in enumerate(k_params) if p.name in undetermined]
    print("\nWhat the demo found")
    for sentence in demo_findings(hidden=args.hidden, verdict=diag.verdict,
                                  explanation=None if cand is None else cand.explanation,
                                  rms_before=diag.fit.rms, rms_after=final.rms, floor=diag.noise_floor,
                                  stiffness_error_percent=err, validation=validation,
                                  absolute=(absolute.base.rms, geo.rms), undetermined=open_joints):
        print("  " + textwrap.fill(sentence, 96, subsequent_indent="  "))
    print(f"\n  The numbers: joint stiffness identified ({k_source}, from motor currents) against the truth")
    final_k = {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in k_params}
    # a stiffness that follows the link-compliance selection's choice between twins is no finding
    from elastocal.identify.evidence import mark_twins

    print(format_parameters(mark_twins(final_k, undetermined), truth_k))
    print("\nThe details, step by step" + details)
    print(f"\n  files in {out}")
    print(f"  Words like noise floor, ΔBIC, exact form, TPDO/SYNC and the effect names: README.md, Glossary. "
          f"Look at it in 3-D: elastocal view {log}")
    write_text_atomic(out / "demo.json", json.dumps({
        "hidden": args.hidden, "verdict": diag.verdict, "rms_before": diag.fit.rms, "rms_after": final.rms,
        "absolute": {"rms_before": absolute.base.rms, "max_before": absolute.base.max, "rms_after": geo.rms,
                     "max_after": geo.max, "noise_floor": geo.noise_floor},
        "noise_floor": final.noise_floor, "stiffness_error_percent": err.tolist(),
        # the stiffnesses the fit marks not determined (their error above is against the truth, no finding)
        "stiffness_not_determined": [k_params[j].name for j in open_joints], "compensation": validation,
        "procedure": {"status": outcome.status, "steps": outcome.steps_done, "elapsed_s": outcome.duration_s},
    }, indent=2))
