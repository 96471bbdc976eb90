"""Plain words for what the demo found: the sentences first, the numbers after (README, glossary)."""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from elastocal.model.effects import get_effect, having


def _um(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e6:.0f} µm"


def _length(x: float) -> str:
    return f"{x * 1e3:.2f} mm" if x >= 1e-3 else f"{x * 1e6:.0f} µm"


def demo_findings(*, hidden: str, verdict: str | None, explanation: str | None, rms_before: float,
                  rms_after: float, floor: float | None, stiffness_error_percent: np.ndarray,
                  validation: Mapping[str, Mapping[str, float]],
                  absolute: tuple[float, float] | None = None,
                  undetermined: Sequence[int] = ()) -> list[str]:
    """What the demo found, as sentences a newcomer reads without the glossary (``undetermined``: the
    0-based joints whose stiffness the fit marks not determined; no error is claimed for them)."""
    n = len(stiffness_error_percent)
    words = dict(enumerate(("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")))
    count = words.get(n, str(n))
    open_ = sorted(set(int(j) for j in undetermined))
    found = [e for j, e in enumerate(stiffness_error_percent) if j not in open_]
    worst = float(np.max(found)) if found else float("nan")
    if not open_:
        got = f"got all {count} within {worst:.1f} % of the values the simulator was built with."
    else:
        names = ", ".join(f"k{j + 1}" for j in open_)
        got = (f"got {words.get(len(found), str(len(found)))} of the {count} within {worst:.1f} % of the values the "
               f"simulator was built with; these data do not determine {names} (printed as NOT DETERMINED, "
               f"never as a result).")
    out = [f"The robot bends under load like {count} springs at its joints. elastocal measured how stiff each "
           f"spring is from the motor currents and the tracker alone, and {got}"]
    geometric = verdict is not None and bool(having("geometry", (verdict,)))
    if geometric:
        # the deflections were explained: what the diagnosis names is the shape of the robot, not a bending
        explanation = explanation or get_effect(verdict).explanation
        out.append(f"The springs explain the deflections down to the measurement noise ({_um(rms_before)} left). "
                   f"What the tracker's absolute positions still miss is the robot's geometry, and elastocal "
                   f"names it: {verdict} ({explanation}).")
    elif floor is not None and verdict is not None:
        out.append(f"The springs alone do not explain everything: they leave {_um(rms_before)} of error where the "
                   f"measurement noise accounts for only {_um(floor)}. Something else bends. elastocal tested "
                   f"the physical effects it knows and found the one that was missing: {verdict} ({explanation}). "
                   f"With it, the error falls to {_um(rms_after)}, the level of the measurement noise: nothing "
                   f"else is missing.")
    elif floor is not None and rms_before > 1.3 * floor:
        out.append(f"The springs leave {_um(rms_before)} of error where the measurement noise accounts for "
                   f"{_um(floor)}, and no effect elastocal knows explains the rest: it says so (\"unexplained\") "
                   f"rather than guess a name.")
    else:
        out.append(f"The springs explain the measurements down to the measurement noise ({_um(rms_before)} "
                   "left): nothing is missing from the model.")
    if hidden != "none" and verdict is not None and verdict != hidden:
        out.append(f"(The simulator hid {hidden}; the diagnosis named {verdict}.)")
    if absolute is not None:
        before, after = absolute
        out.append(f"The robot as built is not quite the robot on its drawing: with the drawing's link lengths "
                   f"and angles, the markers are {_length(before)} (typical) from where the tracker sees them; "
                   f"with the lengths and angles elastocal measured, and the tracker's place found, "
                   f"{_length(after)}.")
    unc, exact = validation["uncompensated"]["max"], validation["exact"]["max"]
    out.append(f"Then it corrected a process path: under a 1500 N process force the tool would miss its path by "
               f"up to {_length(unc)}; with the calibration, by up to {_length(exact)}.")
    return out
