"""Plausibility and conditioning of a candidate's fit (docs/cli.md: "implausible").

A candidate whose fitted values are physically implausible, or whose fit is
near-singular, is never a step of the diagnosis: a significant drop of the
residual bought with a negative lost motion or a compliance of the wrong sign
says the candidate soaks up something else, not that the effect is there. Each
effect module states what is plausible for its parameters
(``Effect.plausibility``); the checks common to every fit are here.
"""

from __future__ import annotations

import numpy as np

from elastocal.formats.calibration import is_stiffness_name



#: scaled condition number above which a fit counts as near-singular
MAX_CONDITION = 1e8
def implausible_reason(effect, fit, params) -> str | None:
    """Why the candidate fit ``fit`` of ``effect`` (its added ``params``) is implausible, or None."""
    ks = [p for p in fit.parameters if is_stiffness_name(p.name)]
    neg = [p.name for p in ks if not p.value > 0]
    if neg:
        return f"the fit makes the joint stiffness {', '.join(neg)} negative"
    if not np.isfinite(fit.condition_number) or fit.condition_number > MAX_CONDITION:
        return f"the fit is near-singular (condition number {fit.condition_number:.3g})"
    check = getattr(effect, "plausibility", None)
    if check is None or not params:
        return None
    return check(tuple(p.name for p in params), np.array([p.value for p in params]),
                 np.array([p.std for p in params]))
