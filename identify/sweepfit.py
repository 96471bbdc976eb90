"""The joint-2 sweep model as the sum of its effects' terms (pysindy style).

Along a joint-2 sweep run forward and backward, the mean of the two directions
is friction-free (identify/compensator.py, :func:`sweep_means`). What the
robot description already knows is moved to the left::

    y = xi2 (i_fwd + i_bwd)/2 - [J^T W]_2 + g2_description(theta) = -(sum of the terms)

and each effect whose module declares a ``sweep_term`` (identify/effects:
the compensator's balancing torque ``M(q2; C, l_c)``, gravity's corrections
``Y2(theta) pi``) contributes its :class:`~elastocal.model.effects.base.SweepTerm`.
Effects in the model are fitted together (nonlinear least squares, analytic
Jacobians, bounds from the terms); the others contribute their nominal torque
(the description's compensator) or nothing. The fit never looks at an effect's
name: a new sweep effect is one effect module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from elastocal.errors import UnidentifiableError
from elastocal.model.effects.base import Effect, SweepContext, SweepTerm
from elastocal.identify.static import Parameter

#: a column-scaled sweep Jacobian worse conditioned than this cannot separate its terms
MAX_CONDITION = 1e10


@dataclass(frozen=True, eq=False)
class SweepFit:
    """The sweep model fitted: parameters of the fitted terms, residuals and their leverage."""

    effects: tuple[str, ...]                 # the fitted effects, in order
    values: tuple[np.ndarray, ...]           # their parameters
    names: tuple[tuple[str, ...], ...]
    units: tuple[tuple[str, ...], ...]
    covariance: np.ndarray                   # (p, p) of all fitted parameters, s^2 (J'J)^-1
    residuals: np.ndarray                    # (n,) y + sum of the terms [N·m]
    leverage: np.ndarray                     # (n,) diagonal of the hat matrix J (J'J)^-1 J'

    @property
    def n_parameters(self) -> int:
        return int(sum(len(v) for v in self.values))

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2))) if self.residuals.size else float("nan")

    def slice_of(self, effect: str) -> slice:
        k = self.effects.index(effect)
        start = sum(len(v) for v in self.values[:k])
        return slice(start, start + len(self.values[k]))

    def parameters(self, effect: str | None = None) -> tuple[Parameter, ...]:
        std = np.sqrt(np.maximum(np.diag(self.covariance), 0.0)) if self.covariance.size else np.zeros(0)
        out = []
        for k, eff in enumerate(self.effects):
            if effect is not None and eff != effect:
                continue
            s = std[self.slice_of(eff)]
            out += [Parameter(n, float(v), float(e), u)
                    for n, v, e, u in zip(self.names[k], self.values[k], s, self.units[k])]
        return tuple(out)


def sweep_terms(robot, q2: np.ndarray, theta: np.ndarray, effects: Sequence[Effect],
                joint: int = 1) -> tuple[dict[str, SweepTerm], dict[str, str]]:
    """(effect -> its term, effect -> why these sweeps cannot hold it) for the sweep ``effects``
    of sweeps moving joint ``joint`` (0-based; 1 is joint 2)."""
    ctx = SweepContext(robot=robot, q2=np.asarray(q2, dtype=float), theta=np.asarray(theta, dtype=float),
                       joint=joint)
    terms: dict[str, SweepTerm] = {}
    refused: dict[str, str] = {}
    for eff in effects:
        if eff.sweep_term is None:
            refused[eff.name] = "its module declares no sweep term"
            continue
        term = eff.sweep_term(ctx)
        if isinstance(term, str):
            refused[eff.name] = term
        else:
            terms[eff.name] = term
    return terms, refused


def fixed_torque(terms: Sequence[SweepTerm]) -> np.ndarray | float:
    """What the terms not fitted add: their nominal torque (zero without one)."""
    out: np.ndarray | float = 0.0
    for t in terms:
        if t.nominal is not None:
            out = out + t.torque(t.nominal)
    return out


def fit_sweeps(y: np.ndarray, fitted: Sequence[tuple[str, SweepTerm]],
               fixed: Sequence[SweepTerm] = ()) -> SweepFit:
    """Least squares of ``y + fixed + sum(fitted terms) = 0`` over the fitted terms' parameters."""
    y = np.asarray(y, dtype=float)
    target = y + fixed_torque(fixed)
    if not fitted:
        return SweepFit((), (), (), (), np.zeros((0, 0)), target.copy(), np.zeros(len(y)))
    names = tuple(e for e, _ in fitted)
    terms = tuple(t for _, t in fitted)
    sizes = [len(t.names) for t in terms]
    cuts = np.cumsum([0, *sizes])
    n_par = int(cuts[-1])
    if len(y) <= n_par:
        raise UnidentifiableError(f"{len(y)} sweep means cannot determine {n_par} parameters")
    linear_cols = [t.jacobian(np.zeros(len(t.names))) for t in terms if t.linear]
    other = np.column_stack(linear_cols) if linear_cols else np.zeros((len(y), 0))
    x0 = np.zeros(n_par)
    rest = target.copy()
    for k, t in enumerate(terms):          # nonlinear terms start from their own guess
        if not t.linear:
            guess = t.start(target, other) if t.start is not None else (
                t.nominal if t.nominal is not None else np.ones(len(t.names)))
            x0[cuts[k]:cuts[k + 1]] = guess
            rest = rest + t.torque(guess)
    if other.shape[1]:                     # the linear ones by linear least squares on what is left
        beta, *_ = np.linalg.lstsq(-other, rest, rcond=None)
        idx = np.concatenate([np.arange(cuts[k], cuts[k + 1]) for k, t in enumerate(terms) if t.linear])
        x0[idx] = beta
    lower = np.concatenate([t.lower if t.lower is not None else np.full(len(t.names), -np.inf) for t in terms])

    def residual(x: np.ndarray) -> np.ndarray:
        return target + sum(t.torque(x[cuts[k]:cuts[k + 1]]) for k, t in enumerate(terms))

    def jacobian(x: np.ndarray) -> np.ndarray:
        return np.column_stack([t.jacobian(x[cuts[k]:cuts[k + 1]]) for k, t in enumerate(terms)])

    sol = least_squares(residual, np.maximum(x0, lower + 1e-9), jac=jacobian, bounds=(lower, np.inf),
                        x_scale="jac", xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=500)
    res = sol.fun
    jac = jacobian(sol.x)
    scale = np.linalg.norm(jac, axis=0)
    if np.any(scale == 0) or np.linalg.cond(jac / scale) > MAX_CONDITION:
        raise UnidentifiableError("the sweeps cannot separate " + " from ".join(names) +
                                  "; sweep the compensator's joint over a wider range (and at two or more "
                                  "values of the next joint)")
    q, _ = np.linalg.qr(jac / scale)
    s2 = float(res @ res) / (len(res) - n_par)
    cov = s2 * np.linalg.pinv(jac.T @ jac)
    return SweepFit(effects=names, values=tuple(sol.x[cuts[k]:cuts[k + 1]].copy() for k in range(len(terms))),
                    names=tuple(t.names for t in terms), units=tuple(t.units for t in terms), covariance=cov,
                    residuals=res.copy(), leverage=np.einsum("ij,ij->i", q, q))
