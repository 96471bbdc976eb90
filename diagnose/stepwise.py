"""Stepwise diagnosis and the verdict rule (docs/cli.md, ``diagnose --json``).

As a user would work: test every candidate effect against the model, add the
best significant one that is physically plausible, test the rest again
against the model with it, until none is significant. ``steps`` are the effects
added in order; ``final`` is the model with all of them.

The verdict is the first step **only when the final model sits at the noise
floor**: its residual within :data:`FLOOR_RATIO` x the floor, or its excess
over the floor not significant (``excess_p >= EXCESS_P``). Otherwise the
verdict is None and :class:`Unexplained` says what remains: how far above the
floor, what the excess follows, and which steps explained part of it. A named
verdict that leaves the residual well above the floor would be a wrong answer
(the steps may only have soaked up part of an effect no candidate knows).

Pure functions over duck-typed candidates (``effect``, ``significant``,
``implausible``, ``delta_bic``, ``fit`` with ``rms``, ``noise_floor``): the
static diagnosis (diagnose/static.py) and the run diagnosis share them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

#: the final residual within this factor of the floor sits at it (docs/cli.md)
FLOOR_RATIO = 1.3
#: an excess of the residual over the floor below this p-value is significant
EXCESS_P = 1e-3
#: at most this many effects are added
MAX_STEPS = 6


@dataclass(frozen=True, eq=False)
class Step:
    """One effect added: the candidate as tested against the model before it."""

    effect: str
    candidate: object           # Candidate (static) or RunCandidate (runs)
    rms_before: float
    rms_after: float
    noise_floor_after: float | None


@dataclass(frozen=True)
class Unexplained:
    """What remains above the floor that no candidate explains."""

    rms: float                          # final residual rms
    noise_floor: float
    unit: str
    follows: tuple[str, ...]            # sentences: what the excess follows
    explained: tuple[tuple[str, float], ...]  # (step effect, share of the first excess it removed)

    @property
    def ratio(self) -> float:
        return self.rms / self.noise_floor if self.noise_floor > 0 else math.inf

    def summary(self, scale: float = 1e6, unit_text: str = "µm") -> str:
        """The plain-words sentence of the text output."""
        parts = [f"{_share_words(share)} explained by {effect}" if share < 0.995 else f"{effect} explains it all"
                 for effect, share in self.explained if share > 0.0]
        excess = math.sqrt(max(self.rms**2 - self.noise_floor**2, 0.0)) * scale
        head = "; ".join(parts)
        tail = (f"{excess:.3g} {unit_text} rms remain above the noise floor ({self.ratio:.2f}x it) that no effect "
                f"in the model explains")
        if self.follows:
            tail += f"; {self.follows[0]}"
        return f"{head}; {tail}" if head else tail

    def to_json(self) -> dict:
        return {"rms": self.rms, "noise_floor": self.noise_floor, "ratio": self.ratio, "unit": self.unit,
                "follows": list(self.follows),
                "steps": [{"effect": e, "share_explained": s} for e, s in self.explained]}


def _share_words(share: float) -> str:
    for limit, words in ((0.15, "a little"), (0.3, "a quarter"), (0.4, "a third"), (0.6, "half"),
                         (0.72, "two thirds"), (0.85, "three quarters"), (1.0, "most")):
        if share < limit:
            return words
    return "all"


def admissible(candidate) -> bool:
    """A candidate that can be a step: significant and physically plausible."""
    return bool(candidate.significant) and not getattr(candidate, "implausible", None)


def stepwise(base_fit, test: Callable[[object, Sequence[str]], Sequence], *, max_steps: int = MAX_STEPS):
    """Add the best admissible candidate and test the rest again, until none is.

    ``test(fit, added)`` -> candidates against ``fit`` (``added``: the effects
    already added, which are no longer candidates), best first. Returns
    (candidates of the first round, steps, final fit, candidates of the last round).
    """
    fit = base_fit
    steps: list[Step] = []
    first = None
    last: Sequence = ()
    while True:
        cands = test(fit, tuple(s.effect for s in steps))
        if first is None:
            first = cands
        last = cands
        best = next((c for c in cands if admissible(c)), None)
        if best is None or len(steps) >= max_steps:
            break
        steps.append(Step(best.effect, best, fit.rms, best.fit.rms,
                          getattr(best.fit, "noise_floor", None)))
        fit = best.fit
    return first, tuple(steps), fit, last


def at_floor(rms: float, noise_floor: float | None, excess_p: float | None) -> bool:
    """docs/cli.md's rule: the final residual sits at the floor."""
    if noise_floor is None or not noise_floor > 0:
        return True
    if rms <= FLOOR_RATIO * noise_floor:
        return True
    return excess_p is not None and excess_p >= EXCESS_P


def verdict_of(steps: Sequence[Step], final_rms: float, noise_floor: float | None,
               excess_p: float | None) -> str | None:
    if not steps:
        return None
    return steps[0].effect if at_floor(final_rms, noise_floor, excess_p) else None


def explained_shares(base_rms: float, steps: Sequence[Step], noise_floor: float) -> tuple[tuple[str, float], ...]:
    """Share of the first model's excess over the floor (in mean square) that each step removed."""
    first = base_rms**2 - noise_floor**2
    if first <= 0:
        return tuple((s.effect, 0.0) for s in steps)
    out = []
    for s in steps:
        removed = max(s.rms_before**2 - s.rms_after**2, 0.0)
        out.append((s.effect, min(removed / first, 1.0)))
    return tuple(out)


def unexplained_of(base_rms: float, steps: Sequence[Step], final_rms: float, noise_floor: float | None,
                   excess_p: float | None, follows: Sequence[str], unit: str = "m") -> Unexplained | None:
    """The :class:`Unexplained` report when the final model stays significantly above the floor."""
    if noise_floor is None or not noise_floor > 0 or excess_p is None or excess_p >= EXCESS_P:
        return None
    if final_rms <= FLOOR_RATIO * noise_floor and not follows:
        return None
    return Unexplained(final_rms, noise_floor, unit, tuple(follows), explained_shares(base_rms, steps, noise_floor))
