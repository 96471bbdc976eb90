"""A laser tracker's noise: a constant plus a part growing with range, along and across the beam.

Tracker makers state the accuracy of a point as ``U = a + b·R`` (e.g. 15 µm +
6 µm/m, ISO 10360-10 MPE), R the distance from the tracker head. Along the beam
the distance meter sets it; across the beam the angle encoders, whose error
grows with R and is the larger part at range (docs/physics.md, "Tracker noise
grows with range"). The noise of one reading at ``p`` (tracker frame, the head
at ``tracker_p_head``) is Gaussian with the covariance

    Σ(p) = σ_along(R)² u uᵀ + σ_across(R)² (I − u uᵀ),   u = (p − head) / R,
    σ_along(R) = along_m + along_per_m · R,   σ_across likewise,

σ being standard uncertainties (one sigma) per direction. :meth:`from_stated`
turns a maker's expanded statement (coverage factor k) into it.

This module is the law; estimating it from repeated readings is
identify/trackernoise.py, reading it from cell.toml ``[tracker] noise`` is
drivers/config.py (``parse_tracker_noise`` here, shared).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from elastocal.errors import InputError

#: coverage factor of a maker's stated U when the file does not say (U = 2 sigma)
DEFAULT_COVERAGE = 2.0


@dataclass(frozen=True)
class TrackerNoise:
    """Standard uncertainty of one tracker reading, along and across the beam [m, m/m]."""

    along_m: float
    along_per_m: float
    across_m: float
    across_per_m: float
    #: where the law comes from ("cell.toml [tracker] noise", "estimated from N repeat groups")
    source: str = ""

    def __post_init__(self) -> None:
        for name in ("along_m", "along_per_m", "across_m", "across_per_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise InputError(f"must be a finite number >= 0, got {v!r}", argument=f"tracker noise {name}")
        if self.along_m + self.along_per_m <= 0 or self.across_m + self.across_per_m <= 0:
            raise InputError("along and across must each have a part > 0", argument="tracker noise")

    @classmethod
    def from_stated(cls, along: tuple[float, float], across: tuple[float, float], *,
                    coverage: float = DEFAULT_COVERAGE, source: str = "") -> "TrackerNoise":
        """The law from a maker's statement ``U = a + b·R`` along and across the beam
        ([m], [m/m]) at coverage factor ``coverage`` (U = coverage · sigma)."""
        if not (math.isfinite(coverage) and coverage > 0):
            raise InputError(f"coverage factor must be > 0, got {coverage!r}", argument="tracker noise k")
        return cls(along[0] / coverage, along[1] / coverage, across[0] / coverage, across[1] / coverage,
                   source=source)

    def scaled(self, factor: float, *, source: str) -> "TrackerNoise":
        """The same law (its shape along and across the beam, over range) times ``factor``."""
        return TrackerNoise(self.along_m * factor, self.along_per_m * factor, self.across_m * factor,
                            self.across_per_m * factor, source=source)

    def sigma_along(self, range_m: np.ndarray | float) -> np.ndarray:
        """Standard uncertainty along the beam at range ``range_m`` [m]."""
        return self.along_m + self.along_per_m * np.asarray(range_m, dtype=float)

    def sigma_across(self, range_m: np.ndarray | float) -> np.ndarray:
        """Standard uncertainty per direction across the beam at range ``range_m`` [m]."""
        return self.across_m + self.across_per_m * np.asarray(range_m, dtype=float)

    def covariance(self, tracker_p: np.ndarray, tracker_p_head: np.ndarray | None = None) -> np.ndarray:
        """(..., 3, 3) covariance of one reading at each point ``tracker_p`` (..., 3) [m²].

        ``tracker_p_head``: where the head is in the points' frame (default the
        origin: the tracker's own measurement frame, docs/formats.md §2)."""
        p = np.asarray(tracker_p, dtype=float)
        if tracker_p_head is not None:
            p = p - np.asarray(tracker_p_head, dtype=float)
        r = np.linalg.norm(p, axis=-1)
        u = p / np.where(r > 0, r, 1.0)[..., None]
        beam = u[..., :, None] * u[..., None, :]
        s_al, s_ac = self.sigma_along(r), self.sigma_across(r)
        return (s_al ** 2)[..., None, None] * beam + (s_ac ** 2)[..., None, None] * (np.eye(3) - beam)

    def rms_sigma(self, tracker_p: np.ndarray) -> float:
        """Standard uncertainty per coordinate over the points ``tracker_p`` (N, 3): the
        square root of the mean of trace(Σ)/3 (one number where one is needed)."""
        cov = self.covariance(np.asarray(tracker_p, dtype=float).reshape(-1, 3))
        return float(np.sqrt(np.mean(np.trace(cov, axis1=-2, axis2=-1)) / 3.0))

    def to_json(self) -> dict:
        return {"along": [self.along_m, self.along_per_m], "across": [self.across_m, self.across_per_m],
                "k": 1.0, "unit": ["m", "m/m"], "source": self.source}

    def describe(self) -> str:
        """One line: the law in µm and µm/m (one sigma)."""
        return (f"tracker noise (1 sigma) along the beam {self.along_m * 1e6:.1f} µm + "
                f"{self.along_per_m * 1e6:.2f} µm/m, across {self.across_m * 1e6:.1f} µm + "
                f"{self.across_per_m * 1e6:.2f} µm/m" + (f" ({self.source})" if self.source else ""))


def _pair(doc: Mapping, key: str, *, source: str, where: str) -> tuple[float, float]:
    v = doc.get(key)
    ok = (isinstance(v, list) and len(v) == 2
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x >= 0
                  for x in v))
    if not ok:
        raise InputError(f"expected [a, b]: U = a + b·R with a [m] and b [m/m] >= 0, got {v!r}", source=source,
                         column=f"{where}.{key}")
    return float(v[0]), float(v[1])


def parse_tracker_noise(doc: object, *, source: str, where: str = "tracker.noise") -> TrackerNoise:
    """A ``noise`` table of cell.toml's ``[tracker]`` (docs/cell-config.md)::

        noise = { along = [15e-6, 6e-6], across = [30e-6, 12e-6], k = 2 }

    ``along`` and ``across``: the maker's ``U = a + b·R`` ([m], [m/m]) along and across the
    beam; ``k`` its coverage factor (default 2). One-line errors naming the key."""
    if not isinstance(doc, Mapping):
        raise InputError("expected a table {along = [a, b], across = [a, b], k = 2}", source=source, column=where)
    unknown = sorted(set(doc) - {"along", "across", "k"})
    if unknown:
        raise InputError(f"unknown key {unknown[0]!r}; expected along, across, k", source=source, column=where)
    along = _pair(doc, "along", source=source, where=where)
    across = _pair(doc, "across", source=source, where=where)
    k = doc.get("k", DEFAULT_COVERAGE)
    if not (isinstance(k, (int, float)) and not isinstance(k, bool) and math.isfinite(k) and k > 0):
        raise InputError(f"coverage factor must be a number > 0, got {k!r}", source=source, column=f"{where}.k")
    if sum(along) <= 0 or sum(across) <= 0:
        raise InputError("along and across must each have a part > 0", source=source, column=where)
    return TrackerNoise.from_stated(along, across, coverage=float(k), source=f"{source} [{where}]")


def tracker_noise_doc(noise: TrackerNoise) -> dict:
    """The cell.toml ``noise`` table of a law (k = 1: the values are one sigma)."""
    return {"along": [noise.along_m, noise.along_per_m], "across": [noise.across_m, noise.across_per_m], "k": 1.0}
