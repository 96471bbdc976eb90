"""The absolute part of the HTML report: absolute errors per
pose before and after the absolute steps, and the error vectors on a top view
of the cell, from :class:`elastocal.diagnose.absolute.AbsoluteDiagnosis`."""

from __future__ import annotations

import html

import numpy as np

from elastocal.identify.absolute import AbsoluteFit
from elastocal.model.effects import get_effect
from elastocal.report.html import AFTER_COLOUR, BEFORE_COLOUR, FLOOR_COLOUR, _figure, figure_svg

UM = 1e6


def _base_frame(fit: AbsoluteFit) -> tuple[np.ndarray, np.ndarray]:
    """Predicted positions and residual vectors of the unloaded states, base axes (S0, M, 3)."""
    ds = fit.dataset
    refs = np.flatnonzero(ds.state_ref == np.arange(ds.n_states))
    reg = fit.registration
    pos = (fit.predicted[refs] - reg.translation) @ reg.rotation
    err = fit.residuals[refs] @ reg.rotation
    return pos, err


def _pose_plot(fits: list[tuple[str, AbsoluteFit, str]], ident: str) -> str:
    fig = _figure(7.0, 3.2)
    ax = fig.subplots()
    width = 0.8 / len(fits)
    labels = [p["pose"] for p in fits[0][1].per_pose()]
    x = np.arange(len(labels))
    for k, (title, fit, colour) in enumerate(fits):
        rms = np.array([p["rms"] for p in fit.per_pose()]) * UM
        ax.bar(x + (k - (len(fits) - 1) / 2) * width, rms, width, color=colour, alpha=0.85, label=title)
    floor = fits[-1][1].noise_floor
    if floor:
        ax.axhline(floor * np.sqrt(3) * UM, color=FLOOR_COLOUR, ls="--", label="noise floor (per marker, 3-D)")
    _error_axis(ax, [np.array([p["rms"] for p in f.per_pose()]) * UM for _, f, _ in fits])
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_xlabel("pose (unloaded reference)")
    # each marker's 3-D distance, not a component: √3 times the per-component rms of the headline
    ax.set_ylabel("rms per marker (3-D distance) [µm]")
    ax.legend(fontsize=7)
    return figure_svg(fig, ident)


def _error_axis(ax, values: list[np.ndarray]) -> None:
    """A linear axis from 0, or a log axis with decade ticks (1, 10, 100 µm ...) when the bars
    span more than a decade (a geometry calibration: millimetres before, microns after); never
    a log axis over less than a decade, whose ticks (8, 9, 10 µm) read as a linear scale."""
    from matplotlib.ticker import LogLocator, ScalarFormatter

    v = np.concatenate([np.ravel(a) for a in values])
    v = v[np.isfinite(v) & (v > 0)]
    if v.size and v.max() / v.min() > 10.0:
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(base=10.0, numticks=12))
        ax.yaxis.set_minor_locator(LogLocator(base=10.0, subs=(), numticks=12))   # no unlabelled minor ticks
        fmt = ScalarFormatter()
        fmt.set_scientific(False)
        ax.yaxis.set_major_formatter(fmt)
        lo = 10.0 ** np.floor(np.log10(v.min()))
        hi = 10.0 ** np.ceil(np.log10(v.max()))
        ax.set_ylim(lo, hi)
    else:
        ax.set_ylim(0.0, (v.max() if v.size else 1.0) * 1.15)


def _vector_plot(fits: list[tuple[str, AbsoluteFit, str]], ident: str) -> str:
    fig = _figure(4.2 * len(fits), 4.0)
    axes = fig.subplots(1, len(fits), squeeze=False)[0]
    for ax, (title, fit, colour) in zip(axes, fits):
        pos, err = _base_frame(fit)
        p, e = pos.reshape(-1, 3), err.reshape(-1, 3)
        biggest = float(np.max(np.linalg.norm(e[:, :2], axis=1))) or 1.0
        scale = 0.25 / biggest            # the largest arrow 0.25 m on the plot
        ax.plot(p[:, 0], p[:, 1], ".", ms=3, color="#555555")
        ax.quiver(p[:, 0], p[:, 1], e[:, 0] * scale, e[:, 1] * scale, angles="xy", scale_units="xy", scale=1,
                  color=colour, width=0.004)
        ax.set_aspect("equal")
        ax.set_xlabel("x (base) [m]")
        ax.set_ylabel("y (base) [m]")
        ax.set_title(f"{title}: arrows x{scale:.3g} (largest {biggest * UM:.0f} µm)", fontsize=8)
    return figure_svg(fig, ident)


def absolute_html(absolute) -> str:
    """The report's section on the absolute positions."""
    base = absolute.base
    # the registration is in every absolute fit: the model named is what the fit adds to it
    fits = [(f"model: {', '.join(m for m in base.model if not get_effect(m).registration)}", base, BEFORE_COLOUR)]
    if absolute.steps:
        final = absolute.final
        fits.append((f"+ {', '.join(s.effect for s in absolute.steps)}", final, AFTER_COLOUR))
    out = ["<h2>Absolute positions</h2>",
           f'<p class="note">After the best rigid registration of the tracker (it stands at '
           f"{', '.join(f'{v:.3f}' for v in base.registration.base_p_tracker)} m in base coordinates): "
           f"{base.rms * UM:.1f} µm rms per component (x, y, z; the per-pose plot shows each marker's 3-D "
           f"distance, √3 times larger), max {base.max * UM:.0f} µm, noise floor "
           f"{(base.noise_floor or float('nan')) * UM:.1f} µm"
           + (f"; with {html.escape(', '.join(s.effect for s in absolute.steps))}: {absolute.final.rms * UM:.1f} µm "
              f"rms, max {absolute.final.max * UM:.1f} µm" if absolute.steps else "") + ".</p>"]
    out.append('<div class="plot"><h3>Absolute error per pose</h3>' + _pose_plot(fits, "fig-abs-pose") + "</div>")
    out.append('<div class="plot"><h3>Error vectors (top view, unloaded poses)</h3>'
               + _vector_plot(fits, "fig-abs-vec") + "</div>")
    rows = ["<table><tr><th>pose</th>" + "".join(f"<th>{html.escape(t)} rms [µm]</th><th>max [µm]</th>"
                                                 for t, _, _ in fits) + "</tr>"]
    per = [f.per_pose() for _, f, _ in fits]
    for i, p in enumerate(per[0]):
        rows.append(f"<tr><td>{html.escape(p['pose'])}</td>" + "".join(
            f"<td>{pp[i]['rms'] * UM:.1f}</td><td>{pp[i]['max'] * UM:.1f}</td>" for pp in per) + "</tr>")
    out.append("".join(rows) + "</table>")
    return "\n".join(out)


def absolute_only_page(robot, diag, inputs=()) -> str:
    """The HTML report of a table without loads (diagnose/absolute_only.py): the verdict or what
    stays unexplained, the candidates tested, and the absolute section."""
    from elastocal.report.html import _CSS

    title = f"elastocal report: {robot.name}"
    body = [f"<h1>{html.escape(title)}</h1>"]
    if inputs:
        body.append('<p class="note">inputs: ' + ", ".join(f"<code>{html.escape(i)}</code>" for i in inputs) + "</p>")
    body.append(f'<p class="note">a table without loads; model <code>{html.escape(",".join(diag.model))}</code> '
                "against the absolute positions.</p>")
    verdict = diag.verdict
    body.append(f"<p><b>Verdict:</b> {html.escape(verdict) if verdict else 'none'}</p>")
    for sentence in diag.unexplained():
        body.append(f"<p>{html.escape(sentence)}</p>")
    rows = ["<table><tr><th>candidate</th><th>rms after [µm]</th><th>ΔBIC</th><th>p</th><th>significant</th>"
            "<th>evidence</th></tr>"]
    for c in diag.absolute.candidates:
        rows.append(f"<tr><td>{html.escape(c.effect)}</td><td>{c.rms_after * UM:.1f}</td><td>{c.delta_bic:.1f}</td>"
                    f"<td>{c.p_value:.2g}</td><td>{'yes' if c.significant else 'no'}</td>"
                    f"<td>{html.escape(c.evidence)}</td></tr>")
    body.append("<h2>Candidate effects</h2>" + "".join(rows) + "</table>")
    body += [f'<p class="note">not tested: {html.escape(n.effect)}: {html.escape(n.reason)}</p>'
             for n in diag.not_testable]
    body.append(absolute_html(diag.absolute))
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n" + "\n".join(body)
            + "\n</body></html>\n")
