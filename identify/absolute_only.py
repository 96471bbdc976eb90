"""Absolute-only tables: where the absolute fit starts when there are no deflections.

A geometric calibration table (docs/formats.md "Absolute-only tables") holds one
absolute reading per pose and marker, no loads: there is no deflection fit to
start from. The absolute fit (identify/absolute.py) then starts rigid: the
elastic parameters at zero, the registration in closed form. The only elastic
effect such data can show is the joints' twist under the robot's own weight
(``joint_stiffness``, optional there): its torques are the gravity torques of the
description's masses at each pose (``torque = "force"`` with no external wrench),
so it needs the masses, and a joint whose gravity torque does not change across
the poses is not determined (a constant twist is a joint offset; no torque is
no twist): it stays rigid and is reported as such, never guessed. The weight's
torques are those at the configuration the arm sags to (identify/absolute.py refits
once from the first fit's sag: at the commanded one, the stiffest joint's estimate
was biased by a standard deviation).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from elastocal.errors import EffectRefused
from elastocal.model.effects import get_effect
from elastocal.model.kinds import KinematicForm, TorqueSource
from elastocal.model.robot import MARKER_PREFIX, Robot
from elastocal.identify.dataset import StaticDataset
from elastocal.identify.static import StaticFit
from elastocal.identify.staticmodel import Problem, state_torques, static_context

#: a parameter whose angle basis spans, across the poses, less than this fraction of the widest
#: span among its effect's parameters is not determined (its angle does not change from pose to
#: pose: a constant twist is a joint offset; a joint whose gravity torque keeps its sign shows no play)
MIN_TORQUE_SPAN = 1e-3
#: the torque source of an absolute-only table: the model's gravity, no external wrench
SELF_WEIGHT_TORQUE = TorqueSource.FORCE


def is_absolute_only(ds: StaticDataset) -> bool:
    """A dataset without deflections: every state is its pose's reference."""
    return ds.n_deflections == 0


def self_weight_dataset(ds: StaticDataset) -> StaticDataset:
    """The dataset with no external wrench on any state (the robot carries its own weight only)."""
    return replace(ds, state_wrench=np.zeros_like(ds.state_wrench))


def absolute_only_start(robot: Robot, ds: StaticDataset, static_model: Sequence[str]) -> StaticFit:
    """The rigid start of the absolute fit of an absolute-only table, as a :class:`StaticFit` with
    no deflections: the elastic parameters of ``static_model`` at zero, those the poses cannot
    determine listed in ``unidentifiable``. Refuses an effect such a table cannot show, by name."""
    for name in static_model:
        eff = get_effect(name)
        if not (eff.self_weight or eff.shown_by_times):     # shown beside the geometry and the registration
            words = (f"{name} cannot be shown by a table without loads (one absolute reading per pose); "
                     "it takes kinematic_errors, tracker_frame, joint_stiffness and backlash under the robot's own "
                     "weight, and thermal_drift from the readings' times")
            raise EffectRefused(name, words, message=words, argument="model")
        reason = eff.absolute_only_refusal(robot, ds) if eff.shown_by_times else None
        if reason:                               # the effect's own words on what this table lacks
            raise EffectRefused(name, reason, argument="model")
    weighty = [n for n in static_model if get_effect(n).self_weight]
    if weighty and not robot.has_masses:
        name = weighty[0]
        words = (f"{name} on a table without loads is seen under the robot's own weight: it needs "
                 "the link masses (mass and com of each [[joint]] in robot.toml)")
        raise EffectRefused(name, words, message=words, argument="model")
    ds = self_weight_dataset(ds)
    effects = tuple(get_effect(n, robot) for n in static_model)
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    pr = Problem(robot, ds, effects, SELF_WEIGHT_TORQUE, KinematicForm.EXACT, frames)
    names = tuple(p for eff in effects for p in eff.parameters)
    unident: list[str] = []
    if static_model:
        tau = state_torques(pr, None)
        ctx = static_context(pr, tau)
        unident = _undetermined(effects, ctx)
    else:
        ctx = None
    n = len(names)
    empty = np.zeros((0, 3))
    return StaticFit(model=tuple(static_model), torque=SELF_WEIGHT_TORQUE, form=KinematicForm.EXACT, parameters=(),
                     unidentifiable=tuple(unident), beta_names=names, beta=np.zeros(n), beta_cov=np.zeros((n, n)),
                     predicted=empty, residuals=empty, rms=0.0, max=0.0, n=0, rss=0.0, n_params=0,
                     noise_floor=None, expected_rss=None, condition_number=1.0, iterations=0, dataset=ds,
                     absolute_model=None if ctx is None else (pr, np.zeros(n), ctx), effects=effects)


def _undetermined(effects, ctx) -> list[str]:
    """The parameters the poses do not determine (:data:`MIN_TORQUE_SPAN`), by the names the fit
    reports (a stiffness by its ``k``); refuses an effect the data cannot show at all, by name."""
    out: list[str] = []
    for eff in effects:
        if eff.shown_by_times:        # no torque in it: its table was checked by absolute_only_refusal
            continue
        reason = eff.static_refusal(ctx) if eff.static_refusal is not None else None
        if reason:
            raise EffectRefused(eff.name, reason, argument="model")
        theta = eff.static_basis(ctx).theta                     # (S, N, p) joint angle per parameter
        if theta is None:
            continue
        span = np.ptp(theta, axis=0).max(axis=0)                # (p,)
        weak = span <= MIN_TORQUE_SPAN * float(span.max())
        # under the names the fits report (a compliance c_j as its stiffness k_j: Effect.report_names)
        names = eff.parameters if eff.report_with_model is not None else eff.reported_names
        out += [names[i] for i in np.flatnonzero(weak)]
    return out
