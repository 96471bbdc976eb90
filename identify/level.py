"""The weight's direction: a robot base out of level beside self-weight springs.

On a table without loads the joints twist under the robot's own weight (identify/absolute_only.py),
and the weight pulls along gravity, not along the base's z axis: a base (or a first link) that
stands out of level by a fraction of a milliradian turns the weight's torques. The tracker does not
see that tilt directly, since the registration absorbs a rotation of the whole arm, but the twists
under the turned weight differ from those under a level one by micrometres (docs/physics.md,
"Absolute positions"): a vertical first axis, which carries no weight torque on a level base,
twists under the tilted weight, and every other joint's torque turns with it. Left out, that
difference lands in the registration: beside self-weight springs its intervals covered 81 % of a
URDF robot's seeds whose joint-1 origins were tilted as the geometry's errors are drawn, 95 % when
level.

So the absolute fit of a table without loads fits the base's tilt from level, ``tilt_x`` and
``tilt_y`` [rad] (the base turned about its own x and y axes from level: gravity in base axes is
``exp(tilt)^T (0, 0, -g)``), beside the springs. To first order in the tilt the joints' twists change
by the springs' bases at the tilt's torques (:func:`tilt_torques`): for a spring the table determines,
its first-pass value times that basis, one column per axis, shared by all joints; for a spring the
level weight does not load (its column is zero on a level base), its compliance times the tilt, one
nuisance column per axis, fitted and written to the calibration (``c1_tilt_x``: validate reads it
back), never a finding on its own (the product cannot tell a soft joint under a small tilt from a
stiff one under a larger; the spring stays unidentifiable). The first pass (the weight's torques at
the commanded pose, level) gives the springs; the second (at the sagged pose, on the geometry the
first found) fits the tilt with them. Without the joint-1 products the registration still covered
81 %: the vertical axis's twist is most of what the tilt does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import pinocchio as pin

from elastocal.model.robot import Robot
from elastocal.identify.staticmodel import Problem, absolute_bases, static_context, state_torques

#: the base's tilt from level, about its x and y axes [rad]: reported beside the springs
TILT_NAMES = ("tilt_x", "tilt_y")
#: a torque basis this small next to the largest of the springs' tilt bases is no column
ZERO_BASIS = 1e-9


@dataclass(frozen=True, eq=False)
class LevelBases:
    """The joint-angle columns (S, N, n) of the base's tilt: ``names[:2]`` the tilt, the rest a
    spring's compliance times the tilt where the level weight does not load it (a nuisance the
    calibration carries so that what reads it predicts what the fit did)."""

    theta: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]


def tilt_torques(robot: Robot, theta: np.ndarray) -> np.ndarray:
    """(S, N, 2) change of each state's gear torques per radian of the base's tilt about x and y,
    at the link-side angles ``theta`` (S, N): the weight's torques are linear in gravity's vector,
    and turning the base by ``t`` about x (y) turns gravity in base axes by ``(0, -g t, 0)``
    (``(g t, 0, 0)``). A copy of the model carries each direction (the robot's stays as it is)."""
    g = float(np.linalg.norm(robot.model.gravity.linear))
    out = np.zeros((theta.shape[0], robot.n_joints, 2))
    if not robot.has_masses or g == 0.0:
        return out
    model = pin.Model(robot.model)
    for k, direction in enumerate((np.array([0.0, -g, 0.0]), np.array([g, 0.0, 0.0]))):
        model.gravity = pin.Motion(direction, np.zeros(3))
        data = model.createData()
        for s in range(theta.shape[0]):
            out[s, :, k] = -pin.computeGeneralizedGravity(model, data, np.ascontiguousarray(theta[s]))
    return out


def gravity_in_base(gravity: np.ndarray, tilt: Sequence[float]) -> np.ndarray:
    """Gravity's vector in base axes for a base turned from level by ``tilt`` = (about x, about y)
    [rad] (:data:`TILT_NAMES`): ``exp(tilt)^T g``, ``g`` the level one (the robot model's)."""
    return pin.exp3(np.array([float(tilt[0]), float(tilt[1]), 0.0])).T @ np.asarray(gravity, dtype=float)


def _tilt_bases(pr: Problem, theta: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per axis, the change (S, N, p) of the springs' joint-angle bases per radian of tilt at ``theta``."""
    tau0 = state_torques(pr, theta)
    per_axis = tilt_torques(pr.robot, theta)
    b0 = absolute_bases(pr, static_context(pr, tau0))[0]
    out = []
    for k in range(len(TILT_NAMES)):
        # the springs' bases are linear in the torque for a spring, piecewise for a play: a
        # difference over a torque step of a milliradian's tilt is the derivative either way
        step = 1e-3
        b1 = absolute_bases(pr, static_context(pr, tau0 + step * per_axis[:, :, k]))[0]
        out.append((b1 - b0) / step)
    return tuple(out)


def product_name(beta_name: str, axis: str) -> str:
    """The nuisance product of a spring's compliance and the tilt about one axis (``c1_tilt_x``)."""
    return f"{beta_name}_{axis}"


def level_bases(pr: Problem, theta: np.ndarray, beta: np.ndarray, identified: np.ndarray,
                beta_names: tuple[str, ...], beta_units: tuple[str, ...]) -> LevelBases | None:
    """The tilt's joint-angle columns at the sagged angles ``theta`` (S, N) of the problem's robot,
    the first pass's elastic parameters ``beta`` (named ``beta_names``, in ``beta_units``) and which
    of them the table determines (``identified``); None when the weight's direction moves no twist."""
    d_bases = _tilt_bases(pr, theta)
    scale = max(float(np.max(np.abs(d), initial=0.0)) for d in d_bases)
    if not scale > 0.0:
        return None
    shared = np.stack([d @ np.where(identified, beta, 0.0) for d in d_bases], axis=2)
    columns, names, units = [shared], list(TILT_NAMES), ["rad"] * len(TILT_NAMES)
    for i in np.flatnonzero(~np.asarray(identified, dtype=bool)):
        cols = np.stack([d[:, :, i] for d in d_bases], axis=2)
        if float(np.max(np.abs(cols))) > ZERO_BASIS * scale:
            columns.append(cols)
            names += [product_name(beta_names[i], axis) for axis in TILT_NAMES]
            units += [f"{beta_units[i]}*rad"] * len(TILT_NAMES)
    return LevelBases(theta=np.concatenate(columns, axis=2), names=tuple(names), units=tuple(units))


def tilt_twist(pr: Problem, beta: np.ndarray, beta_names: tuple[str, ...],
               values: Mapping[str, float]) -> np.ndarray | None:
    """The joints' twist (S, N) under the tilted weight at the problem's commanded angles for a
    calibration's ``values`` (the tilt and the products, by name; absent ones zero) and its springs
    ``beta``: what :func:`level_bases` fits, for the model that reads the calibration back. None
    when the calibration holds no tilt."""
    names = [*TILT_NAMES, *(product_name(b, a) for b in beta_names for a in TILT_NAMES)]
    if not any(n in values for n in names):
        return None
    d_bases = _tilt_bases(pr, pr.nominal_theta)
    twist = np.zeros(d_bases[0].shape[:2])
    for k, axis in enumerate(TILT_NAMES):
        twist += float(values.get(axis, 0.0)) * (d_bases[k] @ beta)
        for i, b in enumerate(beta_names):
            twist += float(values.get(product_name(b, axis), 0.0)) * d_bases[k][:, :, i]
    return twist
