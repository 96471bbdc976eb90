"""`elastocal plan --discriminate EFFECT[,EFFECT...]`: the next experiment (docs/plan.md).

The given data (one or more logs, or tables) are diagnosed; their fitted model and
measured noise drive the design (design/discriminate.py); plan.toml holds the
poses, the loads and, in ``[expected]``, the evidence each effect is expected to
give and the procedure's time. No plan is written when the round would not be
worth its time, and the reason is printed.
"""

from __future__ import annotations

import argparse
import json
import shlex
import time

import numpy as np

from elastocal.errors import InputError
from elastocal.model.kinds import TorqueSource


def add_arguments(parser: argparse.ArgumentParser) -> None:
    grp = parser.add_argument_group("the next experiment (docs/plan.md)")
    grp.add_argument("--discriminate", metavar="EFFECT[,EFFECT...]",
                     help="plan the poses and loads that show these effects and tell them from the ones they are "
                          "confused with, from the given data (instead of --test-pose)")
    grp.add_argument("--given", action="append", metavar="LOG",
                     help="a log already measured (repeat for several; or --robot with --static)")
    grp.add_argument("--static", help="a static table already measured (with --robot)")
    grp.add_argument("--model", default="joint_stiffness", help="the model of the given data (default joint_stiffness)")


def command_for(effects, given, *, robot=None, static=None, out="next.toml") -> str:
    """The command that plans the experiment for ``effects`` from these data."""
    parts = ["elastocal", "plan", "--discriminate", ",".join(effects)]
    for g in given or ():
        parts += ["--given", str(g)]
    if not given:
        parts += ["--robot", str(robot), "--static", str(static)]
    parts += ["--out", out]
    return " ".join(shlex.quote(p) for p in parts)


def _given(args: argparse.Namespace):
    """(robot, static table, files) of the given data."""
    from elastocal.formats.robot_toml import load_robot
    from elastocal.formats.tables import concat_static_tables, read_static_table

    if args.given:
        if args.static:
            raise InputError("give --given logs or --robot with --static, not both", source="--static")
        from elastocal.commands._inputs import load_log_noted

        robot, tables = None, []
        for path in args.given:
            r, static, _ = load_log_noted(args, path)
            if static is None:
                raise InputError("the log holds no static experiment to plan from", source=path)
            if robot is not None and (r.marker_names != robot.marker_names or r.n_joints != robot.n_joints):
                raise InputError("the logs are of different robots or markers", source=path)
            robot = robot or r
            tables.append(static)
        if args.robot:
            robot = load_robot(args.robot)
        return robot, concat_static_tables(tables)
    if not (args.robot and args.static):
        raise InputError("--discriminate needs the data measured so far: --given LOG, or --robot R --static S",
                         source="--given")
    robot = load_robot(args.robot)
    return robot, read_static_table(args.static, robot)


def _targets(text: str, model) -> tuple[str, ...]:
    from elastocal.model.effects import get_effect

    names = tuple(dict.fromkeys(t.strip() for t in text.split(",") if t.strip()))
    if not names:
        raise InputError("name at least one effect", source="--discriminate")
    for n in names:
        try:
            eff = get_effect(n)
        except InputError:
            from elastocal.model.effects import ALL_EFFECTS

            raise InputError(f"unknown effect {n!r}; known: {', '.join(ALL_EFFECTS)}", source="--discriminate") from None
        if n in model:
            raise InputError(f"{n} is in the model already", source="--discriminate")
        if "static" not in eff.seen_in or eff.design_size is None:
            raise InputError(f"{n}: no static experiment is planned for it (its size worth finding is unknown or "
                             "static data cannot show it)", source="--discriminate")
    return names


def run(args: argparse.Namespace) -> int:
    from elastocal.commands._outputs import Outputs
    from elastocal.commands.plan import numbers
    from elastocal.design.candidates import Workspace
    from elastocal.design.discriminate import given_from_diagnosis, plan_discrimination
    from elastocal.design.planning import load_specs
    from elastocal.diagnose.static import diagnose_static
    from elastocal.formats.plan import parse_plan, plan_toml
    from elastocal.model.effects import parse_model

    started = time.monotonic()
    outputs = Outputs(force=args.force, inputs=[(args.robot, "--robot"), (args.static, "--static"),
                                                *((g, "--given") for g in args.given or ())])
    out = outputs.add(args.out, "--out")
    model = parse_model(args.model)
    targets = _targets(args.discriminate, model)
    if args.poses < 1 or args.loads_per_pose < 1 or args.candidates < 1 or args.repeats < 1:
        raise InputError("--poses, --loads-per-pose, --candidates and --repeats must be at least 1", source="--poses")
    robot, table = _given(args)
    diag = diagnose_static(robot, table, model=model, torque=TorqueSource(args.torque))
    given = given_from_diagnosis(diag, sigma_tracker=args.tracker_noise,
                                 sigma_current=np.full(robot.n_joints, args.current_noise))
    wrench = given.dataset.state_wrench[:, :3]
    largest = float(np.max(np.linalg.norm(np.nan_to_num(wrench), axis=1))) if wrench.size else 0.0
    f_max = args.f_max if args.f_max is not None else largest
    if not f_max > 0:
        raise InputError("the given data hold no load force, so the rig's largest force is unknown: give --f-max",
                         source="--f-max")
    tracker = numbers(args.tracker_position, (3,), "--tracker-position") if args.tracker_position else None
    workspace = Workspace(f_max_n=f_max, directions=args.directions, min_height_m=args.min_height,
                          max_height_m=args.max_height, min_radius_m=args.min_radius, base_p_tracker=tracker,
                          link_radius_m=args.link_radius)
    markers = given.dataset.markers
    design = plan_discrimination(robot, given, targets, workspace, markers=markers, n_poses=args.poses,
                                 loads_per_pose=args.loads_per_pose, n_candidates=args.candidates,
                                 repeats=args.repeats, seed=args.seed)
    shown = {st.effect for st in diag.steps}
    evidence = {e.effect: e.to_json() for e in design.evidence}
    for name in targets:
        evidence[name]["named_by_given"] = name in shown
    worth = design.worth and not all(name in shown for name in targets)
    reason = design.reason if not all(name in shown for name in targets) else \
        "the given data already name every effect asked for (diagnose them)"
    pose_ids = tuple(f"P{k}" for k in range(1, len(design.q) + 1))
    loads = load_specs(design.forces, np.array(robot.gravity))
    expected = {"criterion": "expected delta BIC of diagnose's test at the size worth finding, against the model "
                             "and the hardest rival (design/discriminate.py)",
                "time_s": design.time_s, "worth": worth, "reason": reason, "given": table.source,
                **{name: {k: v for k, v in evidence[name].items() if not isinstance(v, dict)} for name in targets}}
    text = plan_toml(poses=dict(zip(pose_ids, (tuple(float(v) for v in q) for q in design.q))), loads=loads,
                     markers=markers, name=f"discriminate {', '.join(targets)}", repeats=args.repeats,
                     procedures=("static",), expected=expected,
                     pose_loads={pid: [loads[f].id for f in fl] for pid, fl in zip(pose_ids, design.pose_loads)})
    parse_plan(text, source=str(out)).validate_for(robot)
    if worth:
        with outputs:
            outputs.temp(out).write_text(text, encoding="utf-8")
    obj = {"plan": str(out) if worth else None, "worth": worth, "reason": reason, "time_s": design.time_s,
           "poses": {pid: [float(v) for v in q] for pid, q in zip(pose_ids, design.q)},
           "loads": [{"id": s.id, "force": [float(v) for v in f]} for s, f in zip(loads, design.forces)],
           "pose_loads": {pid: [loads[f].id for f in fl] for pid, fl in zip(pose_ids, design.pose_loads)},
           "evidence": evidence, "rivals": list(design.rivals), "markers": list(markers), "f_max": f_max,
           "noise": {"tracker_m": given.sigma_tracker, "source": given.noise_source},
           "elapsed_s": time.monotonic() - started}
    if args.json:
        print(json.dumps(obj))
        return 0
    print("\n".join(_lines(design, targets, evidence, worth, reason, out, given, f_max, obj)))
    return 0


def _lines(design, targets, evidence, worth, reason, out, given, f_max, obj) -> list[str]:
    lines = [f"given data: noise {given.sigma_tracker * 1e6:.1f} µm per reading ({given.noise_source}); "
             f"rivals: {', '.join(design.rivals) or 'none'}; loads up to {f_max:.0f} N"]
    for name in targets:
        e = evidence[name]
        rand = "" if e["delta_bic_random"] is None else f", random rounds of the same size {e['delta_bic_random']:+.0f}"
        lines.append(f"  {name}: expected ΔBIC at the size worth finding {e['delta_bic_rival_given']:+.0f} on the "
                     f"given data → {e['delta_bic_rival']:+.0f} after the round (against "
                     f"{e['rival'] or 'the model'}; -10 decides{rand})"
                     + ("; the given data already name it" if e["named_by_given"] else ""))
    if worth:
        lines.append(f"plan: {len(design.q)} poses, {design.n_states} loaded states, about "
                     f"{design.time_s / 60:.0f} min -> {out}")
        for pid, fl in obj["pose_loads"].items():
            lines.append(f"  {pid}: q = [{', '.join(f'{v:.3f}' for v in obj['poses'][pid])}], loads {', '.join(fl)}")
        lines.append(f"worth its time: {reason}")
        lines.append(f"then: elastocal calibrate --cell CELL --plan {shlex.quote(str(out))} --out next.mcap, and "
                     "diagnose both logs together: elastocal diagnose FIRST.mcap next.mcap")
    else:
        lines.append(f"no round planned: {reason}")
    return lines
