"""The verdict rule of docs/cli.md, shared by static and run diagnosis: a candidate is
significant when its own test gives p < VERDICT_P and delta_bic < VERDICT_DELTA_BIC; and
the effects a diagnosis could not test, with the reason."""

from __future__ import annotations

from dataclasses import dataclass

#: verdict rule of docs/cli.md
VERDICT_P = 0.01
VERDICT_DELTA_BIC = -10.0


@dataclass(frozen=True)
class NotTestable:
    """An effect the model lacks that these data cannot show, and why."""

    effect: str
    reason: str
