"""`elastocal diagnose`: where the model fails and which missing effect explains it (docs/cli.md)."""

from __future__ import annotations

import argparse
import json
import shlex

from elastocal.commands._inputs import (
    add_input_arguments,
    add_outlier_argument,
    add_tracker_arguments,
    load_inputs,
    prior_line,
    table_model,
    tracker_prior,
)
from elastocal.model.effects import parse_model
from elastocal.diagnose.pipeline import diagnose_data, diagnosis_json
from elastocal.diagnose.unexplained import unexplained_lines
from elastocal.model.kinds import KinematicForm, TorqueSource


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser, several_logs=True)
    add_outlier_argument(parser)
    add_tracker_arguments(parser)


def diagnose_inputs(inputs, model: tuple[str, ...], torque: TorqueSource, form: KinematicForm, *,
                    exclude_outliers: bool = False, prior=None, progress=None):
    """(static Diagnosis or None, run Diagnosis or None) for the loaded inputs; ``prior``
    (:class:`~elastocal.commands._inputs.TrackerPrior`) on the registration, by default the
    one of the cell.toml a log carries; ``progress`` told of each fit (elastocal/progress.py)."""
    if prior is None and inputs.tracker_position is not None:
        prior = tracker_prior(argparse.Namespace(), inputs)
    return diagnose_data(inputs.robot, inputs.static, inputs.runs, model, torque, form,
                         log=None if inputs.log is None else str(inputs.log), exclude_outliers=exclude_outliers,
                         tracker_prior=None if prior is None else prior.base_p_tracker, progress=progress)


def _um(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e6:.1f} µm"


def _p(p: float | None) -> str:
    if p is None:
        return "-"
    return "p < 1e-300" if p == 0.0 else f"p {p:.1g}"


def identify_command(args: argparse.Namespace, model: tuple[str, ...]) -> str:
    parts = ["elastocal", "identify"]
    logs = getattr(args, "log", None)
    if logs:
        parts += logs if isinstance(logs, list) else [logs]
    for flag in ("robot", "static", "runs", "cell", "tracker_position"):   # the same data and tracker prior
        value = getattr(args, flag, None)
        if value:
            parts += [f"--{flag.replace('_', '-')}", value]
    parts += ["--model", ",".join(model)]
    if getattr(args, "torque", "current") != "current":
        parts += ["--torque", args.torque]
    if getattr(args, "form", "exact") != "exact":
        parts += ["--form", args.form]
    if getattr(args, "exclude_outliers", False):
        parts.append("--exclude-outliers")
    return " ".join(shlex.quote(p) for p in parts)


def plannable(effect: str) -> bool:
    """An effect a discriminating static experiment can be planned for (design/discriminate.py)."""
    from elastocal.model.effects import get_effect

    eff = get_effect(effect)
    return "static" in eff.seen_in and eff.design_size is not None


def plan_command(args: argparse.Namespace, effects) -> str:
    """`elastocal plan --discriminate` for ``effects`` from the same data."""
    from elastocal.commands.plan_discriminate import command_for

    logs = getattr(args, "log", None)
    logs = logs if isinstance(logs, list) else ([logs] if logs else [])
    return command_for(effects, logs, robot=getattr(args, "robot", None), static=getattr(args, "static", None))


def open_effects(diag) -> tuple[str, ...]:
    """The plannable effects the static diagnosis leaves open: not testable, unidentifiable in
    part, or leaning towards the effect without deciding (-10 < delta BIC < 0)."""
    from elastocal.diagnose.absolute_only import AbsoluteOnlyDiagnosis

    if diag.verdict is not None or isinstance(diag, AbsoluteOnlyDiagnosis):    # no loads: nothing to plan for
        return ()
    out = [n.effect for n in diag.not_testable]
    out += [c.effect for c in diag.candidates if c.unidentifiable or (not c.significant and c.delta_bic < 0)]
    return tuple(e for e in dict.fromkeys(out) if plannable(e))


def format_static(diag, args: argparse.Namespace, model: tuple[str, ...]) -> str:
    fit = diag.fit
    lines = [f"static: {', '.join(diag.model)} ({diag.torque}-based, {diag.form} form), "
             f"{fit.n} deflection components"]
    planned = set(open_effects(diag))
    floor = diag.noise_floor
    if floor is None:
        lines.append(f"  residual {_um(fit.rms)} rms; no repeated readings, so the noise floor is unknown")
    elif diag.verdict is not None and diag.steps and diag.steps[0].effect == diag.verdict:
        lines.append(f"  residual {_um(fit.rms)} rms, noise floor {_um(floor)}: the model misses something.")
    elif diag.unexplained_detail is not None:
        lines.append(f"  residual {_um(fit.rms)} rms, noise floor {_um(floor)}: above the floor, "
                     "and no candidate effect explains all of it.")
    else:
        lines.append(f"  residual {_um(fit.rms)} rms, noise floor {_um(floor)}: "
                     "residual at the noise floor; no missing effect found.")
    width = max([len(c.effect) for c in diag.candidates] + [10])
    for k, c in enumerate(diag.candidates, start=1):
        change = f"{fit.rms * 1e6:.1f} → {c.rms_after * 1e6:.1f} µm"
        if c.implausible:
            words = f"implausible: {c.implausible}"
        elif c.significant:
            words = f"ΔBIC {c.delta_bic:.0f}   {_p(c.p_value)}   {c.evidence}"
        else:
            words = f"not significant (ΔBIC {c.delta_bic:+.0f}, {_p(c.p_value)})"
            if c.delta_bic < 0 and c.effect in planned:
                words += f"; ambiguous: to decide, {plan_command(args, [c.effect])}"
        lines.append(f"  {k}. {c.effect:<{width}}  {change:<20}  {words}")
        if c.unidentifiable:
            lines.append(f"     {' ' * width}  unidentifiable here: {', '.join(c.unidentifiable)} "
                         f"(rank {c.rank} of {c.n_model_parameters}, condition number {c.condition_number:.3g})"
                         + (f"; to separate them: {plan_command(args, [c.effect])}" if c.effect in planned else ""))
    if diag.steps:
        lines.append("  stepwise: " + " → ".join(
            [_um(fit.rms)] + [f"+{st.effect} {_um(st.rms_after)}" for st in diag.steps])
            + ("" if floor is None else f" (floor {_um(diag.final.noise_floor)})"))
    if diag.unexplained_detail is not None:
        lines.append(f"  {diag.unexplained_detail.summary()}.")
    obj = diag.unexplained_json()          # the text from the JSON's very object
    lines += [f"  {line}" for line in unexplained_lines(obj)]
    said = {s for side in (obj or {}).get("sides", []) for s in side.get("follows", [])}
    for u in diag.unexplained:
        if obj and obj.get("sides") and (u in said or u.startswith("absolute positions stay")):
            continue
        lines.append(f"  unexplained: {u}")
    for o in diag.outliers:
        lines.append(f"  outlier: line {o.line} (pose {o.pose}, load {o.load}, marker {o.marker}) is "
                     f"{_um(o.residual)} off its repeats{'; left out' if o.excluded else ''}")
    if diag.unexplained_detail is not None and any(not o.excluded for o in diag.outliers):
        lines.append("  to leave the outliers out: diagnose again with --exclude-outliers")
    if diag.not_testable:
        lines.append("  not testable from these data:")
        for n in diag.not_testable:
            lines.append(f"    {n.effect}: {n.reason}"
                         + (f"; to test it: {plan_command(args, [n.effect])}" if n.effect in planned else ""))
    if len(planned) > 1:
        lines.append(f"  to settle them all in one round: {plan_command(args, sorted(planned))}")
    lines += format_absolute(diag.absolute)
    if diag.verdict is not None:
        if diag.absolute is not None and diag.verdict in {c.effect for c in diag.absolute.steps}:
            step = next(c for c in diag.absolute.steps if c.effect == diag.verdict)
            lines.append("  where it fails: poses " + ", ".join(
                f"{p['pose']} ({_um(p['rms'])})" for p in sorted(diag.absolute.base.per_pose(),
                                                               key=lambda p: -p["rms"])[:3]))
            added = (diag.verdict, *step.fitted_with)
        else:
            w = diag.where
            pose = w.group("pose")
            worst = sorted(range(len(pose.labels)), key=lambda i: -pose.rms[i])[:3]
            lines.append("  where it fails: poses " + ", ".join(f"{pose.labels[i]} ({_um(pose.rms[i])})"
                                                                for i in worst))
            added = (diag.verdict,)
        lines.append(f"  add it: {identify_command(args, tuple(dict.fromkeys((*model, *added))))}")
    return "\n".join(lines)


def format_absolute(absolute) -> list[str]:
    """The absolute comparison beside the deflection one (diagnose/absolute.py)."""
    if absolute is None:
        return []
    from elastocal.commands._format import absolute_line

    b = absolute.base
    lines = ["  absolute positions (after the best rigid registration): "
             + absolute_line({"rms": b.rms, "max": b.max}, b.noise_floor)]
    for k, c in enumerate(absolute.candidates, start=1):
        with_ = f" (with {', '.join(c.fitted_with)})" if c.fitted_with else ""
        change = f"{c.rms_before * 1e6:.1f} → {c.rms_after * 1e6:.1f} µm{with_}"
        if c.significant:
            words = f"ΔBIC {c.delta_bic:.0f}   {_p(c.p_value)}   {c.explanation}"
        else:
            words = f"not significant (ΔBIC {c.delta_bic:+.0f}, {_p(c.p_value)})"
        lines.append(f"  {k}. {c.effect}  {change}  {words}")
    if not absolute.steps and absolute.base_at_floor:
        lines.append("  absolute positions at their noise floor: the geometry and the registration hold.")
    return lines


def format_runs(diag, args: argparse.Namespace, model: tuple[str, ...]) -> str:
    lines = [f"runs: {', '.join(diag.model)}, {diag.n} torque samples"]
    floor = diag.noise_floor
    if diag.residual_rms is not None:
        head = f"  torque residual {diag.residual_rms:.3g} N*m rms over the parts tested"
        if floor is None:
            lines.append(head + "; the noise floor is unknown (runs too short)")
        elif diag.verdict is not None:
            lines.append(head + f", noise floor {floor:.3g} N*m: the model misses something.")
        elif diag.unexplained_detail is not None:
            lines.append(head + f", noise floor {floor:.3g} N*m: above the floor, and no candidate effect "
                                "explains all of it.")
        else:
            lines.append(head + f", noise floor {floor:.3g} N*m: at the noise floor; no missing effect found.")
    width = max([len(c.effect) for c in diag.candidates] + [10])
    for k, c in enumerate(diag.candidates, start=1):
        change = f"{c.rms_before:.3g} → {c.rms_after:.3g} N*m"
        if c.implausible:
            words = f"implausible: {c.implausible}"
        elif c.significant:
            words = f"ΔBIC {c.delta_bic:.0f}   {_p(c.p_value)}   {c.evidence}"
        else:
            words = f"not significant (ΔBIC {c.delta_bic:+.0f}, {_p(c.p_value)})"
        lines.append(f"  {k}. {c.effect:<{width}}  {change:<24}  {words}")
    if diag.steps:
        lines.append("  stepwise: " + " → ".join(
            [f"{diag.residual_rms:.3g} N*m"] + [f"+{st.effect} {st.rms_after:.3g} N*m" for st in diag.steps])
            + ("" if diag.final.noise_floor is None else f" (floor {diag.final.noise_floor:.3g} N*m)"))
    if diag.unexplained_detail is not None:
        lines.append(f"  {diag.unexplained_detail.summary(scale=1.0, unit_text='N*m')}.")
        for u in diag.unexplained[1:]:
            lines.append(f"  unexplained: {u}")
    if diag.stiffness is not None:
        lines.append(f"  {diag.stiffness.note}")
    if diag.not_testable:
        lines.append("  not testable from these runs:")
        for n in diag.not_testable:
            lines.append(f"    {n.effect}: {n.reason}")
    if diag.verdict is not None:
        added = tuple(st.effect for st in diag.steps)
        lines.append(f"  add it: {identify_command(args, tuple(dict.fromkeys((*model, *added))))}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from elastocal.progress import long_work

    with long_work("diagnose", 1, quiet=args.json) as progress:     # each effect's fit, on a large table
        return _run(args, progress)


def _run(args: argparse.Namespace, progress) -> int:
    inputs = load_inputs(args)
    model = table_model(args, inputs, parse_model(args.model))
    prior = tracker_prior(args, inputs)
    static, runs = diagnose_inputs(inputs, model, TorqueSource(args.torque), KinematicForm(args.form),
                                   exclude_outliers=getattr(args, "exclude_outliers", False), prior=prior,
                                   progress=progress)
    progress.done()
    if args.json:
        obj = diagnosis_json(static, runs)
        left = open_effects(static) if static is not None else ()
        obj["next_experiment"] = {"effects": list(left), "command": plan_command(args, left)} if left else None
        if prior is not None and "prior" in obj.get("registration", {}):
            obj["registration"]["prior"]["source"] = prior.source
        print(json.dumps(obj))
        return 0
    out = [f"{inputs.robot.name}"]
    from elastocal.diagnose.absolute_only import AbsoluteOnlyDiagnosis

    if isinstance(static, AbsoluteOnlyDiagnosis):
        print("\n".join([*out, static.text()]))
        return 0
    if static is not None:
        out.append(format_static(static, args, model))
        line = None if static.absolute is None else prior_line(
            prior, static.absolute.base.json_fields()["registration"])
        if line:
            out.append(f"  {line}")
    if runs is not None:
        out.append(format_runs(runs, args, model))
    print("\n".join(out))
    return 0
