"""The chi-square distribution's survival function without scipy.

``chi2_survival(dof, x)`` is ``P(X > x)`` for ``X`` chi-square with ``dof`` degrees of freedom:
the regularized upper incomplete gamma function ``Q(dof / 2, x / 2)``, by its power series below
``a + 1`` and its continued fraction (modified Lentz) above, as in Numerical Recipes' ``gammq``;
exact to a few units in the last place of the result's leading digits, which is all a p-value
compared with a threshold needs. The commands that compare an absolute fit with its floor import
no scipy for it: scipy's import alone costs more than the whole fit of a calibration table.
"""

from __future__ import annotations

import math

_EPS = 1e-16
_TINY = 1e-300
_MAX_TERMS = 100_000


def chi2_survival(dof: float, x: float) -> float:
    """``P(X > x)``, ``X`` chi-square with ``dof`` > 0 degrees of freedom (scipy's ``chdtrc``)."""
    a, z = 0.5 * float(dof), 0.5 * float(x)
    if not a > 0.0:
        raise ValueError(f"degrees of freedom must be positive, got {dof}")
    if math.isnan(z):
        return math.nan
    if z <= 0.0:
        return 1.0
    if math.isinf(z):
        return 0.0
    log_front = a * math.log(z) - z - math.lgamma(a)
    if z < a + 1.0:
        return max(0.0, 1.0 - _lower_series(a, z) * math.exp(log_front))
    return _upper_fraction(a, z) * math.exp(log_front)


def _lower_series(a: float, z: float) -> float:
    """``sum z^n / (a (a+1) ... (a+n))``: P(a, z) = this * z^a e^-z / Gamma(a)."""
    term = total = 1.0 / a
    ap = a
    for _ in range(_MAX_TERMS):
        ap += 1.0
        term *= z / ap
        total += term
        if abs(term) < abs(total) * _EPS:
            break
    return total


def _upper_fraction(a: float, z: float) -> float:
    """The continued fraction of Q(a, z) / (z^a e^-z / Gamma(a)), by modified Lentz."""
    b = z + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, _MAX_TERMS):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = _TINY if abs(d) < _TINY else d
        c = b + an / c
        c = _TINY if abs(c) < _TINY else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return h
