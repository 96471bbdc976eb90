"""One ``unexplained`` object for the deflections and the absolute positions (docs/cli.md).

When the final model leaves more than the noise on either side, ``diagnose
--json`` holds one object: the first side that stays above its floor
(deflections before absolute positions) at its top level, every such side in
``sides``, each with how far above the floor (``ratio``), what it follows, where
it sits (``where``: the strongest place, diagnose/locate.py) and what the steps
explained. The text output is made from this very object
(:func:`unexplained_lines`), so a script and a reader see the same finding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from elastocal.diagnose.locate import Place

SIDES = ("deflections", "absolute")


@dataclass(frozen=True)
class SideUnexplained:
    """What one side (deflections or absolute positions) leaves above its floor."""

    side: str
    rms: float
    noise_floor: float
    unit: str
    follows: tuple[str, ...]
    #: (effect, share of the excess it removed, named) for each step of that side
    steps: tuple[tuple[str, float, bool], ...] = ()
    where: Place | None = None

    @property
    def ratio(self) -> float:
        return self.rms / self.noise_floor if self.noise_floor > 0 else math.inf

    def to_json(self) -> dict:
        return {"side": self.side, "rms": self.rms, "noise_floor": self.noise_floor, "ratio": self.ratio,
                "unit": self.unit, "follows": list(self.follows),
                "where": None if self.where is None else self.where.to_json(),
                "steps": [{"effect": e, "share_explained": s, "named": named} for e, s, named in self.steps]}


def unexplained_json(sides: Sequence[SideUnexplained], sentences: Sequence[str]) -> dict | None:
    """The ``unexplained`` object: the first side's fields at the top, every side in ``sides``."""
    if not sides:
        return None
    first = sides[0].to_json()
    return {**first, "sides": [s.to_json() for s in sides], "sentences": list(sentences)}


def side_sentence(side: dict) -> str:
    """One sentence for one side of the object."""
    what = "deflections" if side["side"] == "deflections" else "absolute positions"
    scale = 1e6 if side["unit"] == "m" else 1.0
    unit = "µm" if side["unit"] == "m" else side["unit"]
    text = (f"{what} stay {side['ratio']:.2f}x their noise floor ({side['rms'] * scale:.3g} {unit} rms, floor "
            f"{side['noise_floor'] * scale:.3g} {unit}) and no effect in the model explains the rest")
    if side.get("where"):
        w = side["where"]
        text += f"; it sits in {w['words']} ({100 * w['share']:.0f} % of the excess in {100 * w['fraction']:.0f} % " \
                f"of the readings, {w['ratio']:.1f}x the noise there)"
    steps = side.get("steps") or []
    if steps:
        text += "; " + ", ".join(
            f"{s['effect']} took up {100 * s['share_explained']:.0f} %" + ("" if s["named"] else " (not named)")
            for s in steps)
    return text


def unexplained_lines(obj: dict | None) -> list[str]:
    """The text output's lines for an ``unexplained`` object (none when it is null)."""
    if not obj:
        return []
    lines = []
    for side in obj.get("sides", []):
        lines.append(f"unexplained: {side_sentence(side)}")
        lines += [f"  it follows: {f}" for f in side.get("follows", [])]
    return lines
