"""Did the data determine the stiffness? Two checks, pure (arrays in, answers out).

1. **The loads changed the joint torques.** A static experiment identifies the
   joint springs from what the loads did: the motor currents of a loaded
   state differ from those of its pose's unloaded reference. If nobody hung
   the loads (a served simulated cell nobody can load, a hook that stayed
   empty), every difference is noise, and a fit of it gives stiffness of any
   sign "at the noise floor". :func:`load_evidence` compares every loaded
   state's current differences with the current repeatability: the loads
   changed the torques when the largest change, in standard deviations of
   the noise, exceeds the two-sided normal quantile at :data:`LOADS_ALPHA`
   shared among the values tested (Bonferroni), so data without any load
   change are refused at least 99 % of the time and real loads — tens of
   standard deviations — always pass. The largest change decides, not a sum
   of squares over every value: repeated readings of one state are closer to
   each other than readings of two states (slow drifts), which a sum over
   many values would take for a change. Without currents (force-based tables) the deflections are
   tested against the tracker's repeatability the same way. Without repeated
   readings there is no noise estimate, and the check says so instead of
   guessing (``decided=False``).
2. **A stiffness is a result only when it is determined.** A joint stiffness
   ``k = 1/c`` is reported only when its compliance is positive and at least
   :data:`DETERMINED_SIGMAS` standard deviations from zero (``std(k)/k <
   1/DETERMINED_SIGMAS``): a negative stiffness, or one the data cannot bound
   from above, is marked ``"determined": false`` with the reason, never
   shown as a finding, and never written as a calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.errors import InputError
from elastocal.formats.calibration import is_stiffness_name

#: false-refusal level of the load check: data with no load change pass it with this probability
LOADS_ALPHA = 0.01
#: a compliance this many standard deviations above zero is determined (k's std below 50 %)
DETERMINED_SIGMAS = 2.0


@dataclass(frozen=True)
class LoadEvidence:
    """What the loaded states changed, against the noise."""

    quantity: str            # "current" or "deflection"
    n: int                   # values tested (loaded states x joints, or x coordinates)
    max_z: float             # largest change in noise standard deviations
    critical: float          # the normal quantile it must exceed (Bonferroni over n at LOADS_ALPHA)
    decided: bool            # False: no repeated readings, no noise to judge by

    @property
    def changed(self) -> bool:
        """The loads changed the measurements beyond noise (True when it cannot be judged)."""
        return not self.decided or self.max_z > self.critical


def _z(diff: np.ndarray, sigma: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """Differences in noise standard deviations; with a zero noise any change is infinitely many."""
    scale = sigma[None, :] * spread[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(scale > 0, diff / np.where(scale > 0, scale, 1.0),
                     np.where(np.abs(diff) > 0, np.inf, 0.0))
    return z


def load_evidence(ds) -> LoadEvidence:
    """The load check of a :class:`~elastocal.identify.static.StaticDataset` (module docstring)."""
    loaded = np.flatnonzero(np.asarray(ds.state_ref) != np.arange(ds.n_states))
    if loaded.size == 0:
        return LoadEvidence("current", 0, 0.0, 0.0, decided=False)
    if ds.has_currents and ds.sigma_current is not None:
        ref = np.asarray(ds.state_ref)[loaded]
        diff = ds.state_currents[loaded] - ds.state_currents[ref]
        n1 = np.asarray(ds.state_n_currents, dtype=float)[loaded]
        n0 = np.asarray(ds.state_n_currents, dtype=float)[ref]
        z = _z(diff, np.asarray(ds.sigma_current, dtype=float), np.sqrt(1.0 / n1 + 1.0 / n0))
        quantity = "current"
    elif ds.sigma_tracker is not None and ds.n_deflections:
        spread = np.sqrt(1.0 / np.asarray(ds.defl_n, float) + 1.0 / np.asarray(ds.defl_n_ref, float))
        z = _z(ds.dP, np.full(3, float(ds.sigma_tracker)), spread)
        quantity = "deflection"
    else:
        return LoadEvidence("current", 0, 0.0, 0.0, decided=False)
    z = np.abs(z[~np.isnan(z)])
    n = int(z.size)
    if n == 0:
        return LoadEvidence(quantity, 0, 0.0, 0.0, decided=False)
    from scipy import stats  # imported where used: scipy.stats costs the commands that never test a quarter second

    return LoadEvidence(quantity, n, float(np.max(z)), float(stats.norm.isf(LOADS_ALPHA / (2 * n))), decided=True)


def check_loads_changed(ds) -> LoadEvidence:
    """:func:`load_evidence`, refusing data whose loads changed nothing beyond noise (InputError)."""
    ev = load_evidence(ds)
    if not ev.changed:
        what = "motor currents" if ev.quantity == "current" else "marker positions"
        raise InputError(f"the loads did not change the joint torques: were they hung? (the {what} of the "
                         f"loaded states differ from the unloaded ones by noise only: the largest of {ev.n} "
                         f"changes is {ev.max_z:.1f} standard deviations of the noise, below {ev.critical:.1f})",
                         source=ds.source)
    return ev


def stiffness_problem(value: float, std: float) -> str | None:
    """Why a joint stiffness ``value`` ± ``std`` [N·m/rad] is not a result, or None when it is one."""
    if not np.isfinite(value) or not np.isfinite(std):
        return "not determined (not a finite number)"
    if value <= 0:
        return "negative: the data do not determine it" if value < 0 else "zero: the data do not determine it"
    if std * DETERMINED_SIGMAS >= value:
        return (f"not determined: its standard deviation is {std / value * 100:.0f} % of the value "
                f"(a result needs below {100 / DETERMINED_SIGMAS:.0f} %)")
    return None


def mark_stiffness(parameters: dict) -> dict:
    """``identify --json`` parameters with every joint stiffness that is not a result marked
    ``"determined": false`` and its ``"note"`` (optional fields; the others unchanged)."""
    out = {}
    for name, p in parameters.items():
        if is_stiffness_name(name):
            why = stiffness_problem(float(p["value"]), float(p.get("std") or 0.0))
            if why is not None:
                p = {**p, "determined": False, "note": why}
        out[name] = p
    return out


def mark_twins(parameters: dict, notes: dict[str, str]) -> dict:
    """``identify --json`` parameters with each stiffness of ``notes`` (name -> why: the data cannot
    tell two link-compliance components apart and it follows the choice, identify/selection.py)
    marked ``"determined": false``, its note beside any it had."""
    out = {}
    for name, p in parameters.items():
        if name in notes:
            note = notes[name] if not p.get("note") else f"{p['note']}; {notes[name]}"
            p = {**p, "determined": False, "note": note}
        out[name] = p
    return out


#: a parameter that moves by more than this many std between the deflection-only and the absolute
#: fit, while the absolute fit leaves an unexplained residual, is marked sensitive
SENSITIVE_SIGMAS = 2.0


@dataclass(frozen=True)
class Sensitivity:
    """A parameter that the absolute fit moves while it leaves a residual it cannot explain."""

    name: str
    deflection_value: float
    deflection_std: float
    absolute_value: float
    absolute_std: float
    z: float                  # (absolute - deflection) / sqrt(std_d² + std_a²)
    sentence: str

    def to_json(self) -> dict:
        return {"parameter": self.name, "deflection": {"value": self.deflection_value, "std": self.deflection_std},
                "absolute": {"value": self.absolute_value, "std": self.absolute_std}, "z": self.z,
                "sensitive": True, "sentence": self.sentence}


def sensitive_parameters(deflection: dict, absolute: dict, ratio: float) -> tuple[Sensitivity, ...]:
    """The parameters (name -> (value, std)) that move by more than SENSITIVE_SIGMAS combined std
    between the deflection-only fit and the absolute fit, which leaves ``ratio`` x its floor."""
    out = []
    for name, (va, sa) in absolute.items():
        if name not in deflection:
            continue
        vd, sd = deflection[name]
        scale = float(np.hypot(sd, sa))
        if not (np.isfinite(scale) and scale > 0):
            continue
        z = (va - vd) / scale
        if abs(z) <= SENSITIVE_SIGMAS:
            continue
        rel = f" ({100 * (va - vd) / vd:+.1f} %)" if vd else ""
        out.append(Sensitivity(name, vd, sd, va, sa, float(z),
                               f"{name} moves by {z:+.1f} std{rel} between the deflection-only fit ({vd:.5g}) and "
                               f"the absolute fit ({va:.5g}), which leaves {ratio:.2f}x its noise floor "
                               "unexplained: the absolute fit's value is not a finding, the deflection-only "
                               "one is the safer"))
    return tuple(out)


def mark_sensitive(parameters: dict, marks: "tuple[Sensitivity, ...]") -> dict:
    """``identify --json`` parameters with each sensitive one marked ``"sensitive": true`` and its
    sentence in ``"note"`` (optional fields)."""
    by = {m.name: m for m in marks}
    out = {}
    for name, p in parameters.items():
        if name in by:
            note = by[name].sentence if not p.get("note") else f"{p['note']}; {by[name].sentence}"
            p = {**p, "sensitive": True, "note": note}
        out[name] = p
    return out
