"""Registration of the tracker frame to the robot base (docs/physics.md, "Absolute positions").

The tracker stands anywhere in the cell (docs/formats.md §2): its readings are
``p_tracker = R p_base + t``. A closed-form rigid fit (Kabsch/Horn, an SVD of
the cross-covariance) of the model's predicted base positions to the measured
ones gives ``R, t``; the absolute fit (identify/absolute.py) refines them with
the rest of the model (effect ``tracker_frame``).

Deflections are differences of two readings, so the translation cancels and
the rotation does not: a deflection measured in the tracker frame is ``R dP``.
:func:`in_base_axes` turns the deflections of a dataset back to base axes with
the registration of the nominal model, so that a tracker which is not aligned
with the base gives the same stiffness as one that is. Kabsch is equivariant:
moving the tracker rigidly moves the fitted registration with it exactly, so the
rotated-back deflections do not depend on where the tracker stood.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from elastocal.model.robot import Robot

if TYPE_CHECKING:  # pragma: no cover
    from elastocal.identify.static import StaticDataset

#: a rigid fit of the nominal model that leaves more than this rms [m] means the
#: table's x, y, z are not absolute positions of this robot (e.g. deflections
#: written against a zero reference): the deflections are then taken as measured
#: in base axes and no absolute comparison is made
PLAUSIBLE_RMS_M = 0.05
#: with fewer poses than this, the markers of one flange cannot tell the tracker's rotation
#: from the tool's own (elastic) rotation: their registration turns the deflections only
#: when the tracker is evidently turned, by more than EVIDENT_ROTATION_RAD
MIN_POSES = 3
EVIDENT_ROTATION_RAD = 0.05


@dataclass(frozen=True)
class Registration:
    """``p_tracker = rotation @ p_base + translation``; ``rms`` the residual of the fit [m]."""

    rotation: np.ndarray
    translation: np.ndarray
    rms: float

    def apply(self, base_p: np.ndarray) -> np.ndarray:
        return base_p @ self.rotation.T + self.translation

    @property
    def base_p_tracker(self) -> np.ndarray:
        """Where the tracker's origin stands in base coordinates [m]."""
        return -self.rotation.T @ self.translation


def kabsch(base_p: np.ndarray, tracker_p: np.ndarray, weights: np.ndarray | None = None) -> Registration | None:
    """The rigid motion that best maps ``base_p`` (N, 3) onto ``tracker_p`` (N, 3)
    in (weighted) least squares; None when the points do not fix a rotation
    (fewer than three non-collinear points)."""
    base_p = np.asarray(base_p, dtype=float).reshape(-1, 3)
    tracker_p = np.asarray(tracker_p, dtype=float).reshape(-1, 3)
    ok = np.all(np.isfinite(base_p), axis=1) & np.all(np.isfinite(tracker_p), axis=1)
    w = np.ones(len(base_p)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    base_p, tracker_p, w = base_p[ok], tracker_p[ok], w[ok]
    if len(base_p) < 3:
        return None
    w = w / w.sum()
    cb = w @ base_p
    ct = w @ tracker_p
    x = base_p - cb
    y = tracker_p - ct
    sv = np.linalg.svd(x, compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        return None
    h = (x * w[:, None]).T @ y
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    trans = ct - rot @ cb
    resid = tracker_p - (base_p @ rot.T + trans)
    return Registration(rotation=rot, translation=trans, rms=float(np.sqrt(np.mean(resid ** 2))))


def nominal_positions(robot: Robot, ds: "StaticDataset", theta: np.ndarray | None = None) -> np.ndarray:
    """Base positions (S, M, 3) of every state's markers: the rigid nominal model
    at the commanded pose, or at the joint angles ``theta`` (S, 6) when given."""
    out = np.empty((ds.n_states, len(ds.markers), 3))
    data = robot.create_data()
    if theta is None:
        for pi in range(len(ds.pose_ids)):
            states = ds.state_pose == pi
            out[states] = robot.positions(robot.theta(ds.q[pi]), list(ds.markers), data=data)
    else:
        for s in range(ds.n_states):
            out[s] = robot.positions(theta[s], list(ds.markers), data=data)
    return out


def register(robot: Robot, ds: "StaticDataset", base_p: np.ndarray | None = None) -> Registration | None:
    """Closed-form registration of ``base_p`` (S, M, 3; default the nominal
    model's positions) to the dataset's absolute positions, weighted by the
    readings averaged; None when the table holds no usable absolute positions."""
    if ds.abs_xyz is None:
        return None
    base_p = nominal_positions(robot, ds) if base_p is None else base_p
    reg = kabsch(base_p.reshape(-1, 3), ds.abs_xyz.reshape(-1, 3),
                 None if ds.abs_n is None else ds.abs_n.reshape(-1))
    if reg is None or not reg.rms < PLAUSIBLE_RMS_M:
        return None
    return reg


def in_base_axes(robot: Robot, ds: "StaticDataset") -> "StaticDataset":
    """The dataset with its deflections turned back to base axes by the nominal
    registration (``tracker_rotation`` records the rotation; a dataset already
    turned is returned as it is)."""
    if ds.tracker_rotation is not None:
        return ds
    reg = register(robot, ds)
    if reg is None or not _determined(ds, reg):
        return replace(ds, tracker_rotation=np.eye(3))
    return replace(ds, dP=ds.dP @ reg.rotation, tracker_rotation=reg.rotation)


def _determined(ds: "StaticDataset", reg: Registration) -> bool:
    angle = float(np.arccos(np.clip((np.trace(reg.rotation) - 1.0) / 2.0, -1.0, 1.0)))
    return len(ds.pose_ids) >= MIN_POSES or angle > EVIDENT_ROTATION_RAD


def refine_registration(robot: Robot, ds: "StaticDataset", base_p: np.ndarray | None) -> "StaticDataset | None":
    """The (unturned) dataset with its deflections turned back by the registration
    of ``base_p`` (S, M, 3: a fitted model's absolute positions) instead of the
    nominal model's; None when there is nothing to register."""
    if base_p is None or ds.tracker_rotation is not None:
        return None
    reg = register(robot, ds, base_p)
    if reg is None or not _determined(ds, reg):
        return None
    return replace(ds, dP=ds.dP @ reg.rotation, tracker_rotation=reg.rotation)
