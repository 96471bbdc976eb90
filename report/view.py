"""What ``elastocal view`` draws: the cell at each calibration pose, in numbers.

Pure: a robot and a diagnosis in, a frozen :class:`CellView` out; the viser page
(:mod:`elastocal.commands.view`) only draws it. For each pose the robot's
skeleton (joint origins and flange) from its URDF at the commanded joint values;
for each deflection (loaded reading minus its unloaded reference, docs/formats.md §2)
the marker's rigid position at the pose (the anchor) and the measured and
predicted deflections; for each model shown (the model as given, the model with
the diagnosed effect, a calibration's prediction) the residuals and, per pose,
the residual rms against the rms that the measurement noise alone leaves there
(the noise floor of the pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.diagnose.static import Diagnosis
from elastocal.diagnose.where import where_it_fails
from elastocal.model.robot import FLANGE_FRAME, Robot

#: how much the deflections and their errors are magnified in the 3-D view
MAGNIFY = 100.0
#: pose colours: residual rms / noise floor up to these bounds is "at the floor", "above", else "far above"
RATIO_AT_FLOOR = 1.5
RATIO_ABOVE = 3.0


@dataclass(frozen=True, eq=False)
class ModelView:
    """One model's account of the deflections."""

    title: str
    predicted: np.ndarray     # (D, 3) predicted deflections [m]
    residual: np.ndarray      # (D, 3) measured - predicted [m]
    pose_rms: np.ndarray      # (P,) residual rms per pose [m]
    pose_ratio: np.ndarray    # (P,) pose_rms / pose_floor (NaN without a noise floor)
    rms: float


@dataclass(frozen=True, eq=False)
class CellView:
    """Everything the 3-D page shows."""

    robot_name: str
    pose_ids: tuple[str, ...]
    q: np.ndarray             # (P, 6) commanded joint values of each pose [rad]
    skeletons: np.ndarray     # (P, K, 3) joint origins base to flange at each pose [m]
    markers: tuple[str, ...]
    defl_pose: np.ndarray     # (D,) pose index of each deflection
    defl_marker: np.ndarray   # (D,) marker index
    defl_load: np.ndarray     # (D,) load-state id
    anchor: np.ndarray        # (D, 3) rigid marker position at the pose [m]
    measured: np.ndarray      # (D, 3) measured deflections [m]
    pose_floor: np.ndarray | None  # (P,) rms noise alone leaves at each pose [m]
    models: tuple[ModelView, ...]
    candidates: tuple[tuple[str, ...], ...]   # rows of the candidate table (header first)
    verdict: str | None
    noise_floor: float | None
    #: (P, K, 3) the same skeletons with a calibration's geometry (kinematic_errors), or None
    skeletons_calibrated: np.ndarray | None = None


def urdf_skeletons(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(P, N + 2, 3): the base, the joint origins and the flange at each row of ``q``,
    from the robot's own Pinocchio model (the chain its URDF export writes)."""
    model = robot.model
    data = robot.create_data()
    joint_ids = [model.getJointId(f"joint{i}") for i in range(1, robot.n_joints + 1)]
    out = []
    for row in np.atleast_2d(q):
        pin.forwardKinematics(model, data.rigid, robot.theta(row))
        points = [np.zeros(3)] + [np.array(data.rigid.oMi[j].translation) for j in joint_ids]
        points.append(robot.positions(robot.theta(row), [FLANGE_FRAME], data=data)[0])
        out.append(points)
    return np.array(out)


def _per_pose(values: np.ndarray, pose: np.ndarray, n_poses: int) -> np.ndarray:
    n = np.bincount(pose, minlength=n_poses) * 3
    return np.sqrt(np.bincount(pose, weights=values, minlength=n_poses) / np.maximum(n, 1))


def _model_view(title: str, measured: np.ndarray, predicted: np.ndarray, pose: np.ndarray, n_poses: int,
                floor: np.ndarray | None) -> ModelView:
    residual = measured - predicted
    rms = _per_pose((residual ** 2).sum(axis=1), pose, n_poses)
    ratio = rms / floor if floor is not None else np.full(n_poses, np.nan)
    return ModelView(title, predicted, residual, rms, ratio, float(np.sqrt(np.mean(residual ** 2))))


def _candidate_rows(diag: Diagnosis) -> tuple[tuple[str, ...], ...]:
    """Candidate table rows (header first); the effects the data cannot show come last."""
    rows = [("effect", "rms after [µm]", "ΔBIC", "p")]
    for c in diag.candidates:
        mark = " (verdict)" if c.effect == diag.verdict else (" (implausible)" if c.implausible else "")
        rows.append((c.effect + mark, f"{c.rms_after * 1e6:.1f}", f"{c.delta_bic:.1f}",
                     "-" if c.p_value is None else f"{c.p_value:.2g}"))
    for n in diag.not_testable:
        rows.append((n.effect + " (not testable here)", "-", "-", "-"))
    return tuple(rows)


def cell_view(robot: Robot, diag: Diagnosis, *, add: str | None = None,
              calibrated: tuple[str, np.ndarray] | None = None, calibrated_robot: Robot | None = None) -> CellView:
    """The view of a static diagnosis: the model as given, the model with ``add``
    (default: the verdict, else the best plausible candidate), and optionally a
    calibration's predicted deflections ``(title, (D, 3))``; ``calibrated_robot``: the robot
    with a calibration's geometry, whose skeletons are kept beside the nominal ones."""
    where = diag.where
    n_poses = len(where.pose_ids)
    first = np.array([np.flatnonzero(where.pose == p)[0] for p in range(n_poses)])
    q = where.q[first]
    data = robot.create_data()
    anchor = np.array([robot.positions(robot.theta(where.q[i]), [where.markers[where.marker[i]]], data=data)[0]
                       for i in range(len(where.pose))])
    floor = None
    if where.noise_var is not None:
        floor = _per_pose(where.noise_var, where.pose, n_poses)
    models = [_model_view(f"model: {', '.join(diag.model)}", where.measured, where.predicted, where.pose, n_poses,
                          floor)]
    effect = add or diag.verdict or next((c.effect for c in diag.candidates if not c.implausible), None)
    if effect is not None:
        cand = next((c for c in diag.candidates if c.effect == effect), None)
        if cand is None and add is not None:
            raise ValueError(f"{effect!r} is not among the tested candidates")
        if cand is not None:   # (a verdict on the absolute positions, e.g. kinematic_errors, has no deflection fit)
            after = where_it_fails(robot, cand.fit, noise=diag.noise_known)
            models.append(_model_view(f"model + {effect}", where.measured, after.predicted, where.pose, n_poses,
                                      floor))
    if calibrated is not None:
        title, predicted = calibrated
        models.append(_model_view(title, where.measured, predicted, where.pose, n_poses, floor))
    return CellView(robot_name=robot.name, pose_ids=tuple(where.pose_ids), q=q, skeletons=urdf_skeletons(robot, q),
                    markers=tuple(where.markers), defl_pose=where.pose, defl_marker=where.marker,
                    defl_load=where.load, anchor=anchor, measured=where.measured, pose_floor=floor,
                    models=tuple(models), candidates=_candidate_rows(diag), verdict=diag.verdict,
                    noise_floor=diag.noise_floor,
                    skeletons_calibrated=None if calibrated_robot is None else urdf_skeletons(calibrated_robot, q))


def geometry_skeletons(view: CellView, calibrated: bool, magnify: float = MAGNIFY) -> np.ndarray:
    """Skeletons to draw: nominal, or calibrated with its difference from nominal magnified."""
    if not calibrated or view.skeletons_calibrated is None:
        return view.skeletons
    return view.skeletons + magnify * (view.skeletons_calibrated - view.skeletons)


def ratio_colours(ratio: np.ndarray) -> np.ndarray:
    """(P, 3) uint8: green at the noise floor, amber above it, red far above; grey without a floor."""
    out = np.tile(np.array([150, 150, 150], dtype=np.uint8), (len(ratio), 1))
    out[ratio <= RATIO_AT_FLOOR] = (40, 170, 80)
    out[(ratio > RATIO_AT_FLOOR) & (ratio <= RATIO_ABOVE)] = (240, 160, 30)
    out[ratio > RATIO_ABOVE] = (210, 40, 40)
    return out


def arrows(view: CellView, model: ModelView, magnify: float = MAGNIFY,
           magnify_errors: float = MAGNIFY) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of the magnified picture: measured marker ``anchor + m·measured``, predicted
    marker ``anchor + m·predicted``, the deflection segments (D, 2, 3) from the anchor to the
    measured marker, and the error segments (D, 2, 3) from the measured marker along
    ``e·(measured - predicted)`` (``m`` magnifies deflections, ``e`` errors)."""
    measured = view.anchor + magnify * view.measured
    predicted = view.anchor + magnify * model.predicted
    errors = np.stack([measured, measured + magnify_errors * model.residual], axis=1)
    return measured, predicted, np.stack([view.anchor, measured], axis=1), errors


#: the longest error arrow the automatic magnification draws [m]: visible beside a 2 m robot
ERROR_ARROW_M = 0.15


def auto_magnify_errors(view: CellView) -> float:
    """A round magnification (1, 2 or 5 times a power of ten) that draws the largest error of
    the first model ERROR_ARROW_M long: errors of 10-50 µm are invisible at the deflections' ×100."""
    largest = float(np.max(np.linalg.norm(view.models[0].residual, axis=1))) if len(view.measured) else 0.0
    if not largest > 0:
        return MAGNIFY
    target = ERROR_ARROW_M / largest
    exponent = np.floor(np.log10(target))
    mantissa = max(m for m in (1.0, 2.0, 5.0) if m * 10 ** exponent <= target)
    return float(mantissa * 10 ** exponent)


def arrow_heads(segments: np.ndarray, fraction: float = 0.3) -> np.ndarray:
    """Two barbs (2·S, 2, 3) at the tip of each segment (S, 2, 3): ``fraction`` of its length long,
    30° off its axis, in the plane of the segment and the vertical (or x for a vertical one)."""
    tail, tip = segments[:, 0], segments[:, 1]
    axis = tip - tail
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    u = axis / np.where(length > 0, length, 1.0)
    ref = np.where(np.abs(u[:, 2:3]) > 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    side = np.cross(u, ref)
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-12)
    back = -u * np.cos(np.radians(30.0)) * fraction * length
    out = np.sin(np.radians(30.0)) * fraction * length * side
    left = np.stack([tip, tip + back + out], axis=1)
    right = np.stack([tip, tip + back - out], axis=1)
    return np.concatenate([left, right])


def worst_pose(view: CellView) -> str:
    """The pose the first model explains least (the highest residual rms): what the page shows first."""
    return view.pose_ids[int(np.argmax(view.models[0].pose_rms))]


def pose_summary(view: CellView, model: ModelView) -> Sequence[str]:
    """One line per pose: id, residual rms and its ratio to the pose's noise floor."""
    lines = []
    for p, pid in enumerate(view.pose_ids):
        ratio = model.pose_ratio[p]
        lines.append(f"{pid}: {model.pose_rms[p] * 1e6:.1f} µm" + ("" if np.isnan(ratio) else f" ({ratio:.1f}× floor)"))
    return lines
