"""The drift plot of a cell's history (`elastocal history --plot`, docs/history.md).

Panels, top to bottom: the joint stiffness; the other calibrated parameters (when the
calibrations have any); the friction the checks' UV/VU runs measured, joint by joint (when
a check ran any); the checks' unexplained deflection against the noise floor. Every check
is a thin vertical line on every panel (green holds, red recalibrate), and every value is
drawn inside its panel:

* the vertical scale of a parameter panel follows the values (calibrations and checks),
  not the error bars: a parameter its calibration does not determine (a joint the poses
  hardly load, std of 300 %) would otherwise squash a 10 % drop of another into the zero
  line. Its error bar then leaves the panel, and a value the calibration marks as not
  determined is drawn as an ``x`` on the panel's lower edge, never at a value (its change
  is no finding); the changes are taken from the first calibration that determines it;
* friction from the checks is drawn once per joint in its own panel (the parameters
  ``fcJ, fvJ, flJ`` of a joint share the check's ratio, so as three series they would hide
  each other), with the tolerance band, and the joints that failed a check filled red;
* legends stand beside their panel, outside the axes, so they hide no point.

Pure: :func:`drift_figure` takes a :class:`~elastocal.acquisition.history.Drift` and
returns a matplotlib ``Figure`` (no pyplot, no global state).
"""

from __future__ import annotations

import re

import numpy as np

from elastocal.acquisition.history import FRICTION_PREFIXES, Drift

#: markers of the parameter families in the "other parameters" panel, in order of appearance
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">")
_HOLDS, _RECALIBRATE = "tab:green", "tab:red"
#: legend entries per column beside a panel
_LEGEND_ROWS = 12


def _datetimes(t_ns: np.ndarray) -> np.ndarray:
    return np.asarray(t_ns, dtype=np.int64).astype("datetime64[ns]")


def _styles(names: list[str]) -> list[tuple[str, str]]:
    """(colour, marker) per parameter: the colour of its joint, the marker of its family
    (fc, fv, fl, cl...); parameters without a joint number take the colours after the joints'."""
    import matplotlib

    palette = list(matplotlib.colormaps["tab10"].colors) + list(matplotlib.colormaps["Dark2"].colors)
    families: dict[str, int] = {}
    joint_names = [re.match(r"^([A-Za-z_]+?)([1-9][0-9]?)([a-z]?)$", name) for name in names]
    spare = max([6] + [int(m.group(2)) for m in joint_names if m])       # after the last joint's colour
    used: set[tuple[int, str]] = set()
    out = []
    for name, m in zip(names, joint_names):
        family = m.group(1) if m else name
        marker = _MARKERS[families.setdefault(family, len(families)) % len(_MARKERS)]
        if m:
            colour = int(m.group(2)) - 1
        else:
            colour, spare = spare, spare + 1
        # no two series alike: a (colour, marker) pair taken already moves on to the next free colour
        # (the markers repeat after len(_MARKERS) families, the colours after the palette's)
        tries = 0
        while (colour % len(palette), marker) in used and tries < len(palette) * len(_MARKERS):
            colour, tries = colour + 1, tries + 1
            if tries % len(palette) == 0:
                marker = _MARKERS[(_MARKERS.index(marker) + 1) % len(_MARKERS)]
        used.add((colour % len(palette), marker))
        out.append((palette[colour % len(palette)], marker))
    return out


def _limits(ax, values: list[float], *, include: tuple[float, ...] = (0.0,), min_pad: float = 1.0) -> None:
    """Set the vertical limits from the drawn values (not from error bars), padded."""
    v = np.array([x for x in list(values) + list(include) if np.isfinite(x)])
    if not v.size:
        return
    lo, hi = float(v.min()), float(v.max())
    pad = max(0.08 * (hi - lo), min_pad)
    ax.set_ylim(lo - pad, hi + pad)


def _legend(ax) -> None:
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
                  ncols=1 + (len(handles) - 1) // _LEGEND_ROWS)


def _parameter_panel(ax, drift: Drift, cols: list[int], tc: np.ndarray, tk: np.ndarray) -> None:
    """Calibrated values (filled, ±1 std) and the checks' estimates (open) relative to the first
    calibration that determines each parameter, in %."""
    drawn: list[float] = []
    for j, (colour, marker) in zip(cols, _styles([drift.names[j] for j in cols])):
        name = drift.names[j]
        values, stds = drift.calibration_value[:, j], drift.calibration_std[:, j]
        determined = drift.calibration_determined[:, j] & np.isfinite(values)
        finite = np.flatnonzero(np.isfinite(values) & (values != 0))
        if not finite.size:
            continue
        known = np.flatnonzero(determined & (values != 0))
        base = values[known[0]] if known.size else values[finite[0]]
        rel = (values / base - 1.0) * 100.0
        err = stds / abs(base) * 100.0
        label = name if determined[np.isfinite(values)].all() else f"{name} (x on the edge: not determined)"
        if determined.any():
            ax.errorbar(tc[determined], rel[determined], yerr=np.nan_to_num(err[determined]), color=colour,
                        marker=marker, ms=4, capsize=2, label=label)
            drawn.extend(rel[determined])
            label = None
        undetermined = np.isfinite(values) & ~determined
        if undetermined.any():    # no value to show: on the lower edge of the panel
            ax.plot(tc[undetermined], np.zeros(int(undetermined.sum())), "x", color=colour, ms=7, mew=1.5,
                    transform=ax.get_xaxis_transform(), clip_on=False, label=label)
        friction = any(name.startswith(p) and name[len(p):].isdigit() for p in FRICTION_PREFIXES)
        checked = np.isfinite(drift.check_value[:, j])
        if len(tk) and checked.any() and not friction:     # friction from checks: its own panel
            crel = (drift.check_value[checked, j] / base - 1.0) * 100.0
            ax.plot(tk[checked], crel, linestyle="none", marker=marker, mfc="none", color=colour, ms=6)
            drawn.extend(crel)
    ax.axhline(0.0, color="grey", lw=0.6)
    _limits(ax, drawn)
    ax.set_ylabel("change from first [%]")


def _friction_panel(ax, drift: Drift, tk: np.ndarray) -> None:
    """Each joint's friction along the checks' runs against the calibration it tested, in %."""
    import matplotlib

    tab10 = matplotlib.colormaps["tab10"].colors
    rel = drift.check_friction_relative * 100.0
    tolerance = drift.check_friction_tolerance
    if np.isfinite(tolerance).any():
        tol = float(np.nanmax(tolerance)) * 100.0
        ax.axhspan(-tol, tol, color="grey", alpha=0.15, lw=0, label=f"tolerance ±{tol:.0f} %")
    drawn: list[float] = []
    for j in range(rel.shape[1]):
        measured = np.isfinite(rel[:, j])
        if not measured.any():
            continue
        ax.plot(tk[measured], rel[measured, j], linestyle="none", marker="o", mfc="none", ms=6,
                color=tab10[j], label=f"joint {j + 1}")
        drawn.extend(rel[measured, j])
    failed = drift.check_friction_failed & np.isfinite(rel)
    if failed.any():
        rows, joints = np.nonzero(failed)
        ax.plot(tk[rows], rel[rows, joints], linestyle="none", marker="o", ms=6, color=_RECALIBRATE,
                label="failed the check")
        for r, j in zip(rows, joints):
            ax.annotate(f"J{j + 1}", (tk[r], rel[r, j]), textcoords="offset points", xytext=(5, 3), fontsize=7,
                        color=_RECALIBRATE)
    ax.axhline(0.0, color="grey", lw=0.6)
    _limits(ax, drawn, include=(0.0,) + ((-tol, tol) if np.isfinite(tolerance).any() else ()))
    ax.set_ylabel("measured / calibrated - 1 [%]")


def _checks_panel(ax, drift: Drift, tk: np.ndarray, colours: list[str]) -> None:
    """Each check's unexplained deflection (rms) and its noise floor; runs-only checks on the axis."""
    if not len(tk):
        ax.set_ylabel("deflection [µm]")
        return
    static = np.isfinite(drift.check_unexplained_m)
    ax.scatter(tk[static], drift.check_unexplained_m[static] * 1e6,
               c=[c for c, s_ in zip(colours, static) if s_], zorder=3, label="unexplained (rms)")
    ax.plot(tk, drift.check_noise_floor_m * 1e6, "k--", lw=0.8, label="noise floor")
    if np.any(~static):   # checks without static poses (friction runs only): on the axis
        ax.scatter(tk[~static], np.zeros(int(np.sum(~static))), marker="^",
                   c=[c for c, s_ in zip(colours, static) if not s_], zorder=3, clip_on=False,
                   label="no static poses (runs only)")
    values = list(drift.check_unexplained_m[static] * 1e6) + list(drift.check_noise_floor_m * 1e6)
    _limits(ax, values, min_pad=0.5)
    ax.set_ylabel("deflection [µm]")


def drift_figure(drift: Drift):
    """The drift plot (see the module's text); returns a matplotlib Figure."""
    from matplotlib.figure import Figure

    stiff = [j for j, n in enumerate(drift.names) if n.startswith("k") and n[1:].isdigit()]
    other = [j for j in range(len(drift.names)) if j not in stiff]
    panels = [("joint stiffness: calibrations (filled, ±1 std) and checks (open)", "stiffness", stiff)]
    if other:
        panels.append(("other parameters: calibrations (filled, ±1 std) and checks (open)", "other", other))
    if np.isfinite(drift.check_friction_relative).any():
        panels.append(("friction along the checks' runs against the calibration, per joint", "friction", None))
    panels.append(("checks: green holds, red recalibrate", "checks", None))
    rows = [max(len(cols or ()), 6) for _, _, cols in panels]
    heights = [max(2.8, 0.19 * min(r, _LEGEND_ROWS) + 0.9) for r in rows]
    fig = Figure(figsize=(9.5, sum(heights)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(panels), 1, sharex=True, gridspec_kw={"height_ratios": heights}))
    tc, tk = _datetimes(drift.calibration_time_ns), _datetimes(drift.check_time_ns)
    colours = [_HOLDS if v == "holds" else _RECALIBRATE for v in drift.check_verdict]
    for ax, (title, kind, cols) in zip(axes, panels):
        for t, c in zip(tk, colours):       # every check, on every panel, whatever it could measure
            ax.axvline(t, color=c, lw=0.6, alpha=0.4, zorder=0)
        if kind == "checks":
            _checks_panel(ax, drift, tk, colours)
        elif kind == "friction":
            _friction_panel(ax, drift, tk)
        else:
            _parameter_panel(ax, drift, cols, tc, tk)
        ax.set_title(title, fontsize=10)
        _legend(ax)
    _time_axis(axes[-1], np.concatenate([tc, tk]))
    axes[-1].set_xlabel("time (UTC)")
    fig.autofmt_xdate()
    return fig


#: the least time span shown: one calibration (or a few on one day) gets a week around it,
#: not matplotlib's empty years about a single date
MIN_SPAN = np.timedelta64(7 * 24, "h")


def _time_axis(ax, times: np.ndarray) -> None:
    import matplotlib.dates as mdates

    if not times.size:
        return
    lo, hi = times.min(), times.max()
    if hi - lo < MIN_SPAN:
        middle = lo + (hi - lo) // 2
        lo, hi = middle - MIN_SPAN // 2, middle + MIN_SPAN // 2
    else:
        pad = (hi - lo) // 20
        lo, hi = lo - pad, hi + pad
    ax.set_xlim(lo, hi)
    locator = mdates.AutoDateLocator(minticks=3, maxticks=8)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
