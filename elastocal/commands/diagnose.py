"""`elastocal diagnose`: where the model fails and which missing effect explains it (cli.md)."""

from __future__ import annotations

import argparse
import json
import shlex

from elastocal.commands._inputs import add_input_arguments, add_outlier_argument, load_inputs
from elastocal.errors import InputError
from elastocal.identify.effects import ALL_EFFECTS, get_effect, parse_model


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    add_outlier_argument(parser)


def diagnose_inputs(inputs, model: tuple[str, ...], torque: str, form: str, *, exclude_outliers: bool = False):
    """(static Diagnosis or None, run Diagnosis or None) for the loaded inputs."""
    from elastocal.identify.diagnose import diagnose_static

    static = None
    runs = None
    if inputs.static is not None:
        static_model = model
        if inputs.runs is not None:  # run-data effects of the model are the runs' business
            static_model = tuple(m for m in model if "static" in get_effect(m).seen_in)
        pool = tuple(e for e in ALL_EFFECTS if e not in model)
        static = diagnose_static(inputs.robot, inputs.static, model=static_model, torque=torque, form=form,
                                 effects=pool, exclude_outliers=exclude_outliers)
    if inputs.runs is not None:
        from elastocal.identify.diagnose import diagnose_runs

        stiffness = None
        if static is not None:
            stiffness = [p.value for p in static.fit.parameters if p.name.startswith("k")]
            stiffness = stiffness if len(stiffness) == 6 else None
        runs = diagnose_runs(inputs.robot, inputs.runs, model=model, stiffness=stiffness)
    if static is None and runs is None:
        if inputs.log is not None:
            raise InputError("nothing to diagnose: the log holds neither a static experiment nor runs",
                             source=str(inputs.log))
        raise InputError("nothing to diagnose: give a static table and/or runs", source="--static")
    return static, runs


def _um(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e6:.1f} µm"


def _p(p: float | None) -> str:
    if p is None:
        return "-"
    return "p < 1e-300" if p == 0.0 else f"p {p:.1g}"


def identify_command(args: argparse.Namespace, model: tuple[str, ...]) -> str:
    parts = ["elastocal", "identify"]
    if getattr(args, "log", None):
        parts.append(args.log)
    for flag in ("robot", "static", "runs"):
        value = getattr(args, flag, None)
        if value:
            parts += [f"--{flag}", value]
    parts += ["--model", ",".join(model)]
    if getattr(args, "torque", "current") != "current":
        parts += ["--torque", args.torque]
    if getattr(args, "form", "exact") != "exact":
        parts += ["--form", args.form]
    if getattr(args, "exclude_outliers", False):
        parts.append("--exclude-outliers")
    return " ".join(shlex.quote(p) for p in parts)


def format_static(diag, args: argparse.Namespace, model: tuple[str, ...]) -> str:
    fit = diag.fit
    lines = [f"static: {', '.join(diag.model)} ({diag.torque}-based, {diag.form} form), "
             f"{fit.n} deflection components"]
    floor = diag.noise_floor
    if floor is None:
        lines.append(f"  residual {_um(fit.rms)} rms; no repeated readings, so the noise floor is unknown")
    elif diag.verdict is not None:
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
        lines.append(f"  {k}. {c.effect:<{width}}  {change:<20}  {words}")
        if c.unidentifiable:
            lines.append(f"     {' ' * width}  unidentifiable here: {', '.join(c.unidentifiable)} "
                         f"(rank {c.rank} of {c.n_model_parameters}, condition number {c.condition_number:.3g})")
    if diag.steps:
        lines.append("  stepwise: " + " → ".join(
            [_um(fit.rms)] + [f"+{st.effect} {_um(st.rms_after)}" for st in diag.steps])
            + ("" if floor is None else f" (floor {_um(diag.final.noise_floor)})"))
    if diag.unexplained_detail is not None:
        lines.append(f"  {diag.unexplained_detail.summary()}.")
    for u in diag.unexplained:
        lines.append(f"  unexplained: {u}")
    for o in diag.outliers:
        lines.append(f"  outlier: line {o.line} (pose {o.pose}, load {o.load}, marker {o.marker}) is "
                     f"{_um(o.residual)} off its repeats{'; left out' if o.excluded else ''}")
    if diag.not_testable:
        lines.append("  not testable from these data:")
        for n in diag.not_testable:
            lines.append(f"    {n.effect}: {n.reason}")
    if diag.verdict is not None:
        w = diag.where
        pose = w.group("pose")
        worst = sorted(range(len(pose.labels)), key=lambda i: -pose.rms[i])[:3]
        lines.append("  where it fails: poses " + ", ".join(f"{pose.labels[i]} ({_um(pose.rms[i])})" for i in worst))
        lines.append(f"  add it: {identify_command(args, (*model, diag.verdict))}")
    return "\n".join(lines)


def format_runs(diag, args: argparse.Namespace, model: tuple[str, ...]) -> str:
    lines = [f"runs: {', '.join(diag.model)}, {diag.n} torque samples"]
    if diag.residual_rms is not None:
        lines.append(f"  torque residual {diag.residual_rms:.3g} N*m rms over the parts tested")
    width = max([len(c.effect) for c in diag.candidates] + [10])
    for k, c in enumerate(diag.candidates, start=1):
        change = f"{c.rms_before:.3g} → {c.rms_after:.3g} N*m"
        if c.significant:
            words = f"ΔBIC {c.delta_bic:.0f}   {_p(c.p_value)}   {c.evidence}"
        else:
            words = f"not significant (ΔBIC {c.delta_bic:+.0f}, {_p(c.p_value)})"
        lines.append(f"  {k}. {c.effect:<{width}}  {change:<24}  {words}")
    if diag.verdict is None:
        lines.append("  no missing effect found in the run data.")
    if diag.not_testable:
        lines.append("  not testable from these runs:")
        for n in diag.not_testable:
            lines.append(f"    {n.effect}: {n.reason}")
    if diag.verdict is not None:
        lines.append(f"  add it: {identify_command(args, (*model, diag.verdict))}")
    return "\n".join(lines)


def diagnosis_json(static, runs) -> dict:
    """The ``diagnose --json`` object (cli.md): the static diagnosis when there is
    one, the run diagnosis alone otherwise. With both, the run diagnosis is under
    ``runs`` too, and ``candidates`` and ``verdict`` cover both data: every
    candidate says which data tested it (``data``: static or runs), significant
    ones first by delta_bic, and the verdict is the first when it is its own
    data's verdict — so null still means "no missing effect found" in either."""
    if static is None:
        obj = runs.to_json()
        for c in obj["candidates"]:
            c["data"] = "runs"
        return obj
    obj = static.to_json()
    for c in obj["candidates"]:
        c["data"] = "static"
    if runs is None:
        return obj
    obj["runs"] = runs.to_json()
    tagged = [*obj["candidates"], *({**c, "data": "runs"} for c in obj["runs"]["candidates"])]
    tagged.sort(key=lambda c: (not c["significant"], c["delta_bic"]))
    obj["candidates"] = tagged
    verdicts = {"static": static.verdict, "runs": runs.verdict}
    obj["verdict"] = tagged[0]["effect"] if tagged and verdicts[tagged[0]["data"]] == tagged[0]["effect"] else None
    return obj


def run(args: argparse.Namespace) -> int:
    inputs = load_inputs(args)
    model = parse_model(args.model)
    static, runs = diagnose_inputs(inputs, model, args.torque, args.form,
                                   exclude_outliers=getattr(args, "exclude_outliers", False))
    if args.json:
        print(json.dumps(diagnosis_json(static, runs)))
        return 0
    out = [f"{inputs.robot.name}"]
    if static is not None:
        out.append(format_static(static, args, model))
    if runs is not None:
        out.append(format_runs(runs, args, model))
    print("\n".join(out))
    return 0
