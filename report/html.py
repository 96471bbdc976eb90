"""``elastocal report``: one self-contained HTML page showing where the model fails.

The page holds the diagnosis (candidates, verdict, what no candidate explains),
the parameters, and plots drawn with matplotlib (Agg-free SVG backend, no
pyplot state) and embedded as inline SVG: measured against predicted deflection
per pose, residual per pose against the noise floor, residual against q2,
time and load, by marker and load state; with run data, the UV/VU current
differences (friction torque) against the model and the joint-2 sweep residual.
Each plot shows the model as given and the model with the added effect side by
side, on the same axes. Nothing on the page refers to another file or URL.

Pure: the diagnosis in, the HTML text out.
"""

from __future__ import annotations

import html
import io
import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.diagnose.static import Diagnosis
from elastocal.diagnose.runs import RunDiagnosis
from elastocal.diagnose.where import Where, where_it_fails
from elastocal.model.robot import Robot
from elastocal.identify.static import StaticFit

BEFORE_COLOUR = "#c0392b"
AFTER_COLOUR = "#1f77b4"
MEASURED_COLOUR = "#333333"
FLOOR_COLOUR = "#7f8c8d"
UM = 1e6


# =================================================================== SVG
def _figure(width_in: float = 6.0, height_in: float = 3.4):
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def figure_svg(fig, ident: str) -> str:
    """The figure as inline SVG: no XML prologue, no metadata, ids made unique
    with ``ident`` so several figures can share one page."""
    import matplotlib

    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": ident, "font.size": 9}):
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None, "Format": None, "Type": None})
    text = buf.getvalue()
    text = re.sub(r"<\?xml[^>]*\?>\s*", "", text)
    text = re.sub(r"<!DOCTYPE[^>]*>\s*", "", text)
    text = re.sub(r"<metadata>.*?</metadata>\s*", "", text, flags=re.S)
    text = re.sub(r'id="([^"]+)"', lambda m: f'id="{ident}-{m.group(1)}"', text)
    text = re.sub(r"url\(#([^)]+)\)", lambda m: f"url(#{ident}-{m.group(1)})", text)
    text = re.sub(r'href="#([^"]+)"', lambda m: f'href="#{ident}-{m.group(1)}"', text)
    return text


# =================================================================== plots
@dataclass(frozen=True, eq=False)
class _Side:
    title: str
    fit: StaticFit
    where: Where
    colour: str


def _shared_ylim(values: Sequence[np.ndarray], floor: float = 0.0) -> tuple[float, float]:
    top = max([float(np.nanmax(v)) for v in values if np.size(v) and np.any(np.isfinite(v))] + [floor, 1e-12])
    return 0.0, top * 1.08


def _deflection_plot(sides: Sequence[_Side], ident: str) -> str:
    fig = _figure(6.0 * len(sides), 3.4)
    axes = fig.subplots(1, len(sides), squeeze=False)[0]
    ymax = max(float(np.max(np.linalg.norm(s.where.measured, axis=1))) for s in sides) * 1e3 * 1.08
    for ax, s in zip(axes, sides):
        w = s.where
        n_pose = len(w.pose_ids)
        x = np.empty(len(w.pose))
        for p in range(n_pose):
            idx = np.flatnonzero(w.pose == p)
            x[idx] = p + np.linspace(-0.3, 0.3, len(idx)) if len(idx) > 1 else p
        ax.plot(x, np.linalg.norm(w.measured, axis=1) * 1e3, "o", ms=3.5, color=MEASURED_COLOUR,
                label="measured |dP|")
        ax.plot(x, np.linalg.norm(w.predicted, axis=1) * 1e3, "x", ms=4.5, color=s.colour, label="predicted |dP|")
        ax.set_xticks(range(n_pose), [str(p) for p in w.pose_ids], fontsize=7)
        ax.set_xlabel("pose (deflections of each pose side by side)")
        ax.set_ylabel("deflection [mm]")
        ax.set_ylim(0, ymax)
        ax.set_title(s.title, fontsize=9)
        ax.legend(fontsize=7, loc="best")
    return figure_svg(fig, ident)


def _pose_residual_plot(sides: Sequence[_Side], ident: str) -> str:
    fig = _figure(6.0 * len(sides), 3.0)
    axes = fig.subplots(1, len(sides), squeeze=False)[0]
    ylim = _shared_ylim([s.where.group("pose").rms * UM for s in sides])
    for ax, s in zip(axes, sides):
        g = s.where.group("pose")
        x = np.arange(len(g.labels))
        ax.bar(x, g.rms * UM, color=s.colour, alpha=0.8, label="residual rms")
        if g.floor is not None:
            ax.step(np.append(x, x[-1] + 1) - 0.5, np.append(g.floor, g.floor[-1]) * UM, where="post",
                    color=FLOOR_COLOUR, ls="--", label="noise floor")
        ax.set_xticks(x, list(g.labels), fontsize=7)
        ax.set_xlabel("pose")
        ax.set_ylabel("residual rms [µm]")
        ax.set_ylim(*ylim)
        ax.set_title(s.title, fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    return figure_svg(fig, ident)


def _residual_scatter(sides: Sequence[_Side], ident: str, feature: str) -> str:
    fig = _figure(6.0 * len(sides), 3.0)
    axes = fig.subplots(1, len(sides), squeeze=False)[0]
    mags = [np.linalg.norm(s.where.residual, axis=1) * UM for s in sides]
    ylim = _shared_ylim(mags)
    for ax, s, mag in zip(axes, sides, mags):
        w = s.where
        if feature == "q2":
            x, label = w.q[:, 1], "q2 [rad]"
        elif feature == "time":
            x, label = w.t / 60.0, "time of the loaded reading [min]"
        else:
            x, label = w.load_size, f"load change [{w.load_unit}]"
        ax.plot(x, mag, "o", ms=3.5, color=s.colour, alpha=0.75, label="|residual| per deflection")
        if w.noise_var is not None:
            order = np.argsort(x)
            ax.plot(x[order], np.sqrt(w.noise_var[order]) * UM, "-", color=FLOOR_COLOUR, lw=1,
                    label="noise level there")
        ax.set_xlabel(label)
        ax.set_ylabel("|residual| [µm]")
        ax.set_ylim(*ylim)
        ax.set_title(s.title, fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    return figure_svg(fig, ident)


def _group_bars(sides: Sequence[_Side], ident: str, by: str, xlabel: str) -> str:
    fig = _figure(6.0 * len(sides), 2.6)
    axes = fig.subplots(1, len(sides), squeeze=False)[0]
    ylim = _shared_ylim([s.where.group(by).rms * UM for s in sides])
    for ax, s in zip(axes, sides):
        g = s.where.group(by)
        x = np.arange(len(g.labels))
        ax.bar(x - 0.2, g.rms * UM, 0.4, color=s.colour, label="residual rms")
        if g.floor is not None:
            ax.bar(x + 0.2, g.floor * UM, 0.4, color=FLOOR_COLOUR, alpha=0.6, label="noise floor")
        ax.set_xticks(x, list(g.labels), fontsize=7)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("rms [µm]")
        ax.set_ylim(*ylim)
        ax.set_title(s.title, fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    return figure_svg(fig, ident)


def _friction_plot(runs: RunDiagnosis, ident: str) -> str:
    f = runs.friction
    fig = _figure(12.0, 5.2)
    axes = fig.subplots(2, 3).reshape(-1)
    after_name = runs.verdict if f.after is not None else None
    for j, ax in enumerate(axes):
        moving = np.isfinite(f.measured[:, j])
        if not np.any(moving):
            ax.set_title(f"joint {j + 1}: did not move", fontsize=9)
            ax.set_axis_off()
            continue
        x = np.arange(len(f.measured))
        ax.plot(x[moving], f.measured[moving, j], ".", ms=2, color=MEASURED_COLOUR,
                label="measured xi (i_UV - i_VU)/2")
        ax.plot(x[moving], f.before[moving, j], "-", lw=1.2, color=BEFORE_COLOUR,
                label=f"model: {', '.join(m for m in runs.model if 'friction' in m) or 'no friction'}")
        if f.after is not None:
            ax.plot(x[moving], f.after[moving, j], "-", lw=1.2, color=AFTER_COLOUR, label=f"+ {after_name}")
        for k in range(1, len(f.pairs)):
            start = np.flatnonzero(f.pair == k)
            if start.size:
                ax.axvline(start[0], color="#dddddd", lw=0.8)
        ax.set_title(f"joint {j + 1}", fontsize=9)
        ax.set_xlabel("matched samples, pair after pair")
        ax.set_ylabel("friction torque [N·m]")
        if j == 0:
            ax.legend(fontsize=7, loc="best")
    return figure_svg(fig, ident)


def _sweep_plot(runs: RunDiagnosis, ident: str) -> str:
    s = runs.sweeps
    fig = _figure(6.0, 3.0)
    ax = fig.subplots()
    ax.plot(s.q2, s.residual_before, ".", ms=3, color=BEFORE_COLOUR, label="model")
    if s.residual_after is not None:
        ax.plot(s.q2, s.residual_after, ".", ms=3, color=AFTER_COLOUR, label=f"+ {runs.verdict}")
    ax.axhline(0.0, color=FLOOR_COLOUR, lw=0.8)
    ax.set_xlabel("q2 [rad]")
    ax.set_ylabel("joint-2 torque residual [N·m]")
    ax.legend(fontsize=7)
    return figure_svg(fig, ident)


# =================================================================== HTML
_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:24px auto;max-width:1240px;color:#222}
h1{font-size:22px;margin:0 0 4px} h2{font-size:17px;margin:28px 0 8px;border-bottom:1px solid #ddd}
h3{font-size:14px;margin:18px 0 6px}
.verdict{font-size:17px;padding:10px 14px;border-radius:6px;margin:12px 0}
.found{background:#fdecea;border-left:5px solid #c0392b}.clean{background:#eaf6ec;border-left:5px solid #27ae60}
.open{background:#fff6e0;border-left:5px solid #e6a700}
table{border-collapse:collapse;font-size:13px;margin:6px 0}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:right}td.l,th.l{text-align:left}
tr.sig td{background:#fdf2f0;font-weight:600}
.pair{display:flex;gap:12px;flex-wrap:wrap}.pair>div{flex:1 1 0;min-width:380px;overflow-x:auto}
table.groups{width:100%;table-layout:fixed}table.groups th,table.groups td{overflow-wrap:anywhere;padding:3px 4px}
table.groups th.l,table.groups td.l{width:6.5em}
.plot svg{width:100%;height:auto}.plot.narrow{max-width:620px}.note{color:#555;font-size:13px}
code{background:#f4f4f4;padding:1px 4px;border-radius:3px}
"""


def _e(x) -> str:
    return html.escape(str(x))


def _um(x: float | None) -> str:
    return "–" if x is None else f"{x * UM:.1f} µm"


def _p(p: float | None) -> str:
    if p is None:
        return "–"
    return "&lt; 1e-300" if p == 0.0 else f"{p:.2g}"


def _fmt(x: float) -> str:
    return f"{x:.5g}"


def _verdict_html(diag: Diagnosis) -> str:
    fit = diag.fit
    if diag.verdict is not None and diag.verdict_candidate is None:      # found in the absolute positions
        a = diag.absolute
        step = next(s for s in a.steps if s.effect == diag.verdict)
        return (f'<div class="verdict found" id="verdict">Deflections: residual {_um(fit.rms)} rms, noise floor '
                f'{_um(diag.noise_floor)}. Absolute positions: {_um(a.base.rms)} rms, noise floor '
                f'{_um(a.base.noise_floor)}: the model misses something. Missing effect: <b>{_e(diag.verdict)}</b> '
                f'— {_e(step.evidence)}.</div>')
    if diag.verdict is not None:
        c = diag.verdict_candidate
        return (f'<div class="verdict found" id="verdict">Residual {_um(fit.rms)} rms, noise floor '
                f'{_um(diag.noise_floor)}: the model misses something. Missing effect: '
                f'<b>{_e(diag.verdict)}</b> — {_e(c.evidence)}. Adding it brings the residual to '
                f'{_um(c.rms_after)}.</div>')
    if diag.unexplained:
        return (f'<div class="verdict open" id="verdict">Residual {_um(fit.rms)} rms, noise floor '
                f'{_um(fit.noise_floor)}: above the floor, and no candidate effect explains it.</div>')
    if diag.noise_floor is None:
        return (f'<div class="verdict clean" id="verdict">Residual {_um(fit.rms)} rms; no repeated readings, so '
                "the noise floor is unknown; no missing effect found.</div>")
    return (f'<div class="verdict clean" id="verdict">Residual {_um(fit.rms)} rms, noise floor '
            f'{_um(fit.noise_floor)}: residual at the noise floor; no missing effect found.</div>')


def _candidates_html(diag: Diagnosis) -> str:
    rows = ["<tr><th class=l>#</th><th class=l>effect</th><th>rms before</th><th>rms after</th>"
            "<th>ΔBIC</th><th>p</th><th class=l>significant</th><th class=l>evidence</th></tr>"]
    for k, c in enumerate(diag.candidates, start=1):
        cls = ' class="sig"' if c.significant and not c.implausible else ""
        note = f" (implausible: {_e(c.implausible)}; never a step)" if c.implausible else ""
        if c.unidentifiable:
            note = (f" (unidentifiable here: {_e(', '.join(c.unidentifiable))}; rank {c.rank} of "
                    f"{c.n_model_parameters}, condition number {c.condition_number:.3g})")
        rows.append(f"<tr{cls}><td class=l>{k}</td><td class=l>{_e(c.effect)}</td><td>{_um(diag.fit.rms)}</td>"
                    f"<td>{_um(c.rms_after)}</td><td>{c.delta_bic:.1f}</td><td>{_p(c.p_value)}</td>"
                    f"<td class=l>{'yes' if c.significant else 'no'}</td>"
                    f"<td class=l>{_e(c.evidence if c.significant else c.explanation)}{note}</td></tr>")
    out = [f'<table id="candidates">{"".join(rows)}</table>']
    if diag.steps:
        out.append('<p id="steps"><b>Stepwise:</b> ' + _e(" → ".join(
            [_um(diag.fit.rms)] + [f"+{st.effect} {_um(st.rms_after)}" for st in diag.steps])) + "</p>")
    if diag.unexplained_detail is not None:
        out.append(f'<p id="unexplained-summary">{_e(diag.unexplained_detail.summary())}.</p>')
    if diag.outliers:
        out.append('<p><b>Outliers</b> (readings far off their repeats; left out of the noise floor):</p>'
                   '<ul id="outliers">' + "".join(
                       f"<li>line {o.line}: pose {_e(o.pose)}, load {_e(o.load)}, marker {_e(o.marker)}, "
                       f"{_um(o.residual)} off{' (excluded from the fit)' if o.excluded else ''}</li>"
                       for o in diag.outliers) + "</ul>")
    if diag.unexplained:
        out.append("<p><b>Unexplained:</b></p><ul>" + "".join(f"<li>{_e(u)}</li>" for u in diag.unexplained)
                   + "</ul>")
    if diag.not_testable:
        out.append('<p class="note">Not testable from these data:</p><ul class="note">'
                   + "".join(f"<li><b>{_e(n.effect)}</b>: {_e(n.reason)}</li>" for n in diag.not_testable)
                   + "</ul>")
    return "\n".join(out)


def _params_html(fit: StaticFit, noise_known: bool = True) -> str:
    rows = ["<tr><th class=l>parameter</th><th>value</th><th>std</th><th class=l>unit</th></tr>"]
    for p in fit.parameters:
        rows.append(f"<tr><td class=l>{_e(p.name)}</td><td>{_fmt(p.value)}</td><td>{_fmt(p.std)}</td>"
                    f"<td class=l>{_e(p.unit)}</td></tr>")
    extra = ""
    if fit.unidentifiable:
        extra = (f'<p class="note">Unidentifiable from these data: {_e(", ".join(fit.unidentifiable))} '
                 f"(rank {fit.n_params}, condition number {fit.condition_number:.3g})</p>")
    return (f"<table>{''.join(rows)}</table>"
            f'<p class="note">residual {_um(fit.rms)} rms, max {_um(fit.max)}, noise floor '
            f"{_um(fit.noise_floor if noise_known else None)}, n = {fit.n}</p>{extra}")


def _groups_html(where: Where, title: str) -> str:
    parts = [f"<h3>{_e(title)}</h3>"]
    for g in where.groups:
        if g.by == "pose":
            continue
        cells = "".join(f"<th>{_e(lab)}</th>" for lab in g.labels)
        rms = "".join(f"<td>{x * UM:.1f}</td>" for x in g.rms)
        row = f"<tr><th class=l>{_e(g.by)}</th>{cells}</tr><tr><td class=l>rms [µm]</td>{rms}</tr>"
        if g.floor is not None:
            row += "<tr><td class=l>floor [µm]</td>" + "".join(f"<td>{x * UM:.1f}</td>" for x in g.floor) + "</tr>"
        parts.append(f'<table class="groups">{row}</table>')
    return "\n".join(parts)


def _plot_block(title: str, svg: str, note: str = "", *, narrow: bool = False) -> str:
    note_html = f'<p class="note">{_e(note)}</p>' if note else ""
    cls = "plot narrow" if narrow else "plot"
    return f'<h3>{_e(title)}</h3>{note_html}<div class="{cls}">{svg}</div>'


def _runs_html(runs: RunDiagnosis) -> str:
    out = ["<h2>Run data</h2>"]
    if runs.verdict is not None:
        out.append(f'<div class="verdict found">Missing effect in the runs: <b>{_e(runs.verdict)}</b> — '
                   f"{_e(runs.steps[0].candidate.evidence if runs.steps else runs.candidates[0].evidence)}.</div>")
    elif runs.unexplained_detail is not None:
        out.append('<div class="verdict found">Run data: above the noise floor, and no candidate effect explains '
                   f"all of it: {_e(runs.unexplained_detail.summary(scale=1.0, unit_text='N·m'))}.</div>")
    else:
        out.append('<div class="verdict clean">Run data: no missing effect found.</div>')
    if runs.noise_floor is not None:
        out.append(f'<p class="note">Torque residual {runs.residual_rms:.3g} N·m rms, noise floor '
                   f"{runs.noise_floor:.3g} N·m (current repeatability through the half-differences and "
                   "sweep means).</p>")
    if runs.stiffness is not None:
        out.append(f'<p class="note">{_e(runs.stiffness.note)}.</p>')
    rows = ["<tr><th class=l>effect</th><th class=l>part</th><th>rms before [N·m]</th><th>rms after [N·m]</th>"
            "<th>ΔBIC</th><th>p</th><th class=l>significant</th></tr>"]
    for c in runs.candidates:
        cls = ' class="sig"' if c.significant else ""
        rows.append(f"<tr{cls}><td class=l>{_e(c.effect)}</td><td class=l>{_e(c.part)}</td>"
                    f"<td>{c.rms_before:.3g}</td><td>{c.rms_after:.3g}</td><td>{c.delta_bic:.1f}</td>"
                    f"<td>{_p(c.p_value)}</td><td class=l>{'yes' if c.significant else 'no'}</td></tr>")
    out.append(f'<table id="run-candidates">{"".join(rows)}</table>')
    if runs.not_testable:
        out.append('<ul class="note">' + "".join(f"<li><b>{_e(n.effect)}</b>: {_e(n.reason)}</li>"
                                                 for n in runs.not_testable) + "</ul>")
    for g in runs.groups:
        cells = "".join(f"<th>{_e(lab)}</th>" for lab in g.labels)
        vals = "".join(f"<td>{x:.3g}</td>" for x in g.rms)
        out.append(f"<table><tr><th class=l>{_e(g.by)}</th>{cells}</tr>"
                   f"<tr><td class=l>rms [N·m]</td>{vals}</tr></table>")
    if runs.friction is not None:
        out.append(_plot_block("UV/VU current differences (friction torque) and the model",
                               _friction_plot(runs, "fig-friction"),
                               "Half the difference of the currents of the same path run forward (UV) and "
                               "backward (VU), in joint torque: gravity and load cancel, friction stays."))
    if runs.sweeps is not None:
        out.append(_plot_block("Joint-2 sweep: torque residual against q2", _sweep_plot(runs, "fig-sweep"),
                               narrow=True))
    return "\n".join(out)


def render_report(robot: Robot, static: Diagnosis | None, runs: RunDiagnosis | None = None, *,
                  add: str | None = None, inputs: Sequence[str] = (), command: str | None = None,
                  next_experiment: tuple[Sequence[str], str] | None = None) -> str:
    """The HTML page. ``add``: the effect whose augmented fit is shown beside
    the model (default: the verdict). ``next_experiment``: (the effects these data
    leave open, the command that plans the experiment for them)."""
    title = f"elastocal report: {robot.name}"
    body = [f"<h1>{_e(title)}</h1>"]
    if inputs:
        body.append('<p class="note">inputs: ' + ", ".join(f"<code>{_e(i)}</code>" for i in inputs) + "</p>")
    if static is not None:
        body.append(f'<p class="note">model <code>{_e(",".join(static.model))}</code>, {_e(static.torque)}-based '
                    f"torques, {_e(static.form)} form; {static.fit.n} deflection components.</p>")
        body.append(_verdict_html(static))
        body.append("<h2>Candidate effects</h2>")
        body.append(_candidates_html(static))
        if next_experiment is not None:
            effects, plan = next_experiment
            body.append(f'<p id="next-experiment"><b>Left open</b> ({_e(", ".join(effects))}: not testable, '
                        f"unidentifiable in part, or not decided by these data). The experiment that settles it: "
                        f"<code>{_e(plan)}</code> (docs/plan.md)</p>")
        effect = add if add is not None else static.verdict
        sides = [_Side(f"model: {', '.join(static.model)}", static.fit, static.where, BEFORE_COLOUR)]
        absolute_steps = () if static.absolute is None else tuple(c.effect for c in static.absolute.steps)
        if effect is not None and effect not in {c.effect for c in static.candidates} and effect in absolute_steps:
            effect = None         # an absolute effect: shown in the absolute section
        if effect is not None:
            cand = next((c for c in static.candidates if c.effect == effect), None)
            if cand is None:
                raise ValueError(f"{effect!r} is not among the tested candidates")
            where_after = (static.where_final if cand.fit is static.final
                           else where_it_fails(robot, cand.fit, noise=static.noise_known))
            sides.append(_Side(f"model + {effect}", cand.fit, where_after, AFTER_COLOUR))
        if command:
            body.append(f'<p class="note">add it: <code>{_e(command)}</code></p>')
        body.append("<h2>Parameters</h2><div class=\"pair\">" + "".join(
            f"<div><h3>{_e(s.title)}</h3>{_params_html(s.fit, static.noise_known)}</div>" for s in sides) + "</div>")
        body.append("<h2>Where the model fails" + (" — before and after adding "
                                                    f"{_e(effect)}" if effect else "") + "</h2>")
        single = len(sides) == 1
        plots = [
            ("Measured and predicted deflection per pose", _deflection_plot(sides, "fig-defl"), ""),
            ("Residual per pose against the noise floor", _pose_residual_plot(sides, "fig-pose"), ""),
            ("Residual against q2", _residual_scatter(sides, "fig-q2", "q2"),
             "The compensator and the arm's own weight change most with q2."),
        ]
        if np.all(np.isfinite(static.where.t)):
            plots.append(("Residual against time", _residual_scatter(sides, "fig-time", "time"),
                          "A drift of the tracker or a warming robot grows with time."))
        plots += [
            ("Residual against the load", _residual_scatter(sides, "fig-load", "load"), ""),
            ("Residual by marker", _group_bars(sides, "fig-marker", "marker", "marker"), ""),
            ("Residual by load state", _group_bars(sides, "fig-loadstate", "load", "load state"), ""),
        ]
        for title_, svg, note in plots:
            body.append(_plot_block(title_, svg, note, narrow=single))
        body.append('<div class="pair">' + "".join(f"<div>{_groups_html(s.where, s.title)}</div>" for s in sides)
                    + "</div>")
        if static.absolute is not None:
            from elastocal.report.absolute import absolute_html

            body.append(absolute_html(static.absolute))
    if runs is not None:
        body.append(_runs_html(runs))
    body.append('<p class="note">Generated by elastocal. Tests: Wald test of the added parameters with the '
                "noise measured from repeated readings (p), BIC of the same likelihood (ΔBIC &lt; −10 and "
                "p &lt; 0.01 name the verdict).</p>")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>\n" + "\n".join(body)
            + "\n</body></html>\n")
