"""The static model's regressor for an experiment not yet made.

Experiment design (design/discriminate.py) asks how well poses and loads that
have not been measured would separate the effects of a model. The answer needs
the same regressor the fit uses (identify/static.py), evaluated on a dataset
whose deflections are not known yet: :func:`planned_dataset` makes that dataset
(the currents each state will show, from the robot's gravity and the load
through its torque constants), :func:`regressor` the first-order Jacobian of
the predicted deflections in every parameter of the effects named, each effect's
own basis (so a joint whose torque never reverses gives backlash a zero column
exactly as the fit would).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from elastocal.model.effects import get_effect
from elastocal.model.robot import MARKER_PREFIX, Robot
from elastocal.identify.dataset import StaticDataset
from elastocal.identify.staticmodel import Problem, evaluate, state_torques, static_bases, static_context
from elastocal.model.kinds import KinematicForm, TorqueSource


def planned_dataset(robot: Robot, q: np.ndarray, wrenches: Sequence[np.ndarray], markers: Sequence[str], *,
                    repeats: int, sigma_tracker: float, sigma_current: np.ndarray | None,
                    source: str = "<planned experiment>") -> StaticDataset:
    """A static dataset of poses ``q`` (P, N) with the load states ``wrenches[p]``
    (L_p, 6) after each pose's unloaded reference, ``repeats`` readings of every
    marker per state and the noise given; deflections are zero (not measured)."""
    q = np.asarray(q, dtype=float)
    pose_of, load_of, wrench = [], [], []
    for p, w in enumerate(wrenches):
        w = np.asarray(w, dtype=float).reshape(-1, 6)
        pose_of += [p] * (len(w) + 1)
        load_of += ["0"] + [str(k) for k in range(1, len(w) + 1)]
        wrench += [np.zeros(6), *w]
    state_pose = np.array(pose_of, dtype=np.intp)
    state_load = np.array(load_of, dtype=str)
    state_ref = np.searchsorted(state_pose, state_pose)
    n_states, n_markers = len(state_pose), len(markers)
    loaded = np.flatnonzero(state_ref != np.arange(n_states))
    d_state = np.repeat(loaded, n_markers)
    d_marker = np.tile(np.arange(n_markers), len(loaded))
    n_d = len(d_state)
    ds = StaticDataset(
        source=source, pose_ids=tuple(f"P{p + 1}" for p in range(len(q))), q=q, markers=tuple(markers),
        state_pose=state_pose, state_load=state_load, state_ref=state_ref,
        state_currents=np.zeros((n_states, q.shape[1])), state_n_currents=np.full(n_states, repeats),
        state_wrench=np.array(wrench), defl_state=d_state, defl_ref=state_ref[d_state], defl_marker=d_marker,
        dP=np.zeros((n_d, 3)), defl_n=np.full(n_d, repeats), defl_n_ref=np.full(n_d, repeats),
        defl_dt=np.full(n_d, np.nan), defl_t=np.full(n_d, np.nan), sigma_tracker=sigma_tracker,
        sigma_current=sigma_current, tracker_rotation=np.eye(3))
    if robot.has_torque_constants:      # the currents the drives will show: gravity and load through xi
        pr = Problem(robot, ds, (), TorqueSource.FORCE, KinematicForm.FIRST_ORDER, ())
        tau = state_torques(pr, None)
        from dataclasses import replace

        ds = replace(ds, state_currents=tau / robot.torque_constants)
    return ds


def regressor(robot: Robot, ds: StaticDataset, effects: Sequence[str], *, torque: TorqueSource = TorqueSource.CURRENT,
              beta: np.ndarray | None = None) -> tuple[np.ndarray, tuple[str, ...]]:
    """(D, 3, p) first-order Jacobian of the predicted deflections of ``ds`` in the
    parameters of ``joint_stiffness`` and ``effects`` (in that order), at ``beta``
    (default zero), and the parameter names."""
    names = tuple(dict.fromkeys(["joint_stiffness", *effects]))
    effs = tuple(get_effect(n) for n in names)
    frames = tuple(MARKER_PREFIX + m for m in ds.markers)
    pr = Problem(robot, ds, effs, torque, KinematicForm.FIRST_ORDER, frames)
    param_names = tuple(p for e in effs for p in e.parameters)
    beta = np.zeros(len(param_names)) if beta is None else np.asarray(beta, dtype=float)
    ctx = static_context(pr, state_torques(pr, None), beta)
    _, a, _ = evaluate(pr, beta, static_bases(pr, ctx), exact=False)
    return a.reshape(ds.n_deflections, 3, -1), param_names


def refusals(robot: Robot, ds: StaticDataset, effects: Sequence[str], *,
             torque: TorqueSource = TorqueSource.CURRENT) -> dict[str, str]:
    """The effects of ``effects`` these data cannot show at all, with each effect's own reason
    (``Effect.static_refusal``: static friction is no part of a current-based model; backlash
    needs a load that reverses a torque)."""
    effs = tuple(get_effect(n) for n in dict.fromkeys(["joint_stiffness", *effects]))
    pr = Problem(robot, ds, effs, torque, KinematicForm.FIRST_ORDER, ())
    ctx = static_context(pr, state_torques(pr, None))
    out = {}
    for eff in effs:
        reason = eff.static_refusal(ctx) if eff.static_refusal is not None else None
        if reason:
            out[eff.name] = reason
    return out
