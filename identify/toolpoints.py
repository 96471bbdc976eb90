"""The tool-point pre-fit: where the markers really are on the tool, before the full model.

A tool's markers are often known to a few centimetres only, or not at all (a
reflector nest moved, a motion-capture body glued on, robot.toml's ``[tool.markers]``
copied from another tool). Off by tens of centimetres, the nominal model cannot be
registered to the readings (a rigid fit leaves more than
:data:`~elastocal.identify.registration.PLAUSIBLE_RMS_M`) and the full model's
linearised marker corrections would start too far away. The pre-fit solves the
rigid problem that remains when the marker positions are unknown:

    p_tracker[s, m] = R (p_flange[s] + R_flange[s] · p_m) + t

for the registration ``R, t`` and each marker's flange coordinates ``p_m``, with the
flange poses of the nominal rigid model at the commanded joints. It alternates the
two exact block solutions (Kabsch for ``R, t`` given the markers; the marker's mean
over the poses given ``R, t``: ``R_flange`` is orthonormal), a descent on the same
cost, from the robot.toml markers and from the flange itself, and keeps the best.

A placement *explains* the readings when its rms is below the registration's
plausibility limit and every marker sits within :data:`MAX_TOOL_M` of the flange.
When no placement explains all markers, each marker is left out in turn: a marker
without which the others are explained is the one the error names.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.identify.registration import PLAUSIBLE_RMS_M, Registration, kabsch
from elastocal.model.robot import FLANGE_FRAME, Robot

if TYPE_CHECKING:  # pragma: no cover
    from elastocal.identify.static import StaticDataset

#: a marker farther than this from the flange is no point of a tool [m]
MAX_TOOL_M = 1.0
#: the nominal registration leaving more than this rms starts the full model from the pre-fit [m]
PREFIT_RMS_M = 0.01
#: a pre-fit placement must move a marker by more than this to be used [m]
MIN_MOVE_M = 0.002
MAX_ITERATIONS = 2000
REL_TOL = 1e-12


@dataclass(frozen=True)
class ToolPoints:
    """The markers' flange coordinates the pre-fit found, and its registration."""

    markers: tuple[str, ...]
    flange_p_markers: np.ndarray            # (M, 3) [m]
    registration: Registration
    rms: float                              # rms of the readings' residual, per coordinate [m]
    marker_rms: np.ndarray                  # (M,) rms per marker [m]

    def moved(self, robot: Robot) -> dict[str, np.ndarray]:
        """Each marker's offset from robot.toml's position [m]."""
        nominal = dict(robot.tool.flange_p_markers)
        return {m: p - np.asarray(nominal[m]) for m, p in zip(self.markers, self.flange_p_markers)}

    def robot(self, robot: Robot) -> Robot:
        """``robot`` with its markers where the pre-fit found them."""
        found = dict(zip(self.markers, self.flange_p_markers))
        tool = replace(robot.tool, flange_p_markers=tuple(
            (m, tuple(float(x) for x in found[m]) if m in found else p) for m, p in robot.tool.flange_p_markers))
        return replace(robot, tool=tool)


def _flange_poses(robot: Robot, ds: "StaticDataset") -> tuple[np.ndarray, np.ndarray]:
    """(S, 3, 3) rotations and (S, 3) positions of the flange at every state's commanded pose."""
    model = robot.model
    data = model.createData()
    fid = model.getFrameId(FLANGE_FRAME)
    rot = np.empty((len(ds.pose_ids), 3, 3))
    pos = np.empty((len(ds.pose_ids), 3))
    for pi in range(len(ds.pose_ids)):
        pin.framesForwardKinematics(model, data, robot.theta(ds.q[pi]))
        rot[pi], pos[pi] = data.oMf[fid].rotation, data.oMf[fid].translation
    return rot[ds.state_pose], pos[ds.state_pose]


def _alternate(rf: np.ndarray, pf: np.ndarray, y: np.ndarray, w: np.ndarray,
               start: np.ndarray) -> tuple[np.ndarray, Registration, float] | None:
    """Markers (M, 3), registration and rms from the alternating block solutions (module docstring)."""
    markers = start.copy()
    cost = np.inf
    reg = None
    for _ in range(MAX_ITERATIONS):
        base_p = pf[:, None, :] + np.einsum("sij,mj->smi", rf, markers)
        reg = kabsch(base_p.reshape(-1, 3), y.reshape(-1, 3), w.reshape(-1))
        if reg is None:
            return None
        back = (y - reg.translation) @ reg.rotation                 # R^T (y - t), base frame
        local = np.einsum("sji,smj->smi", rf, back - pf[:, None, :])  # R_f^T (…): flange frame
        markers = (local * w[..., None]).sum(axis=0) / w.sum(axis=0)[:, None]
        r = back - pf[:, None, :] - np.einsum("sij,mj->smi", rf, markers)
        new = float(np.sum(w[..., None] * r ** 2))
        done = cost - new <= REL_TOL * max(new, 1e-300)
        cost = new
        if done:
            break
    base_p = pf[:, None, :] + np.einsum("sij,mj->smi", rf, markers)
    reg = kabsch(base_p.reshape(-1, 3), y.reshape(-1, 3), w.reshape(-1))
    if reg is None:
        return None
    resid = y - reg.apply(base_p)
    return markers, reg, float(np.sqrt(np.mean(resid ** 2)))


def fit_tool_points(robot: Robot, ds: "StaticDataset", markers: Sequence[str] | None = None) -> ToolPoints | None:
    """The best rigid placement of ``markers`` (default: the dataset's) on the flange and the
    tracker registration that go with it; None when the readings cannot fix them."""
    if ds.abs_xyz is None:
        return None
    names = list(ds.markers)
    chosen = list(markers) if markers is not None else names
    cols = [names.index(m) for m in chosen]
    y = ds.abs_xyz[:, cols]
    w = np.ones(y.shape[:2]) if ds.abs_n is None else np.asarray(ds.abs_n, dtype=float)[:, cols]
    ok = np.all(np.isfinite(y), axis=2)
    y = np.where(ok[..., None], y, 0.0)
    w = np.where(ok, w, 0.0)
    if np.any(w.sum(axis=0) <= 0):
        return None
    rf, pf = _flange_poses(robot, ds)
    nominal = np.array([dict(robot.tool.flange_p_markers)[m] for m in chosen], dtype=float)
    best = None
    for start in (nominal, np.zeros_like(nominal)):
        got = _alternate(rf, pf, y, w, start)
        if got is not None and (best is None or got[2] < best[2]):
            best = got
    if best is None:
        return None
    found, reg, rms = best
    base_p = pf[:, None, :] + np.einsum("sij,mj->smi", rf, found)
    resid = np.where(ok[..., None], y - reg.apply(base_p), np.nan)
    per_marker = np.sqrt(np.nanmean(resid ** 2, axis=(0, 2)))
    return ToolPoints(tuple(chosen), found, reg, rms, per_marker)


def explains(tools: ToolPoints | None) -> bool:
    """Whether a placement explains the readings (module docstring)."""
    return (tools is not None and tools.rms < PLAUSIBLE_RMS_M
            and bool(np.all(np.linalg.norm(tools.flange_p_markers, axis=1) <= MAX_TOOL_M)))


def find_tool_points(robot: Robot, ds: "StaticDataset") -> ToolPoints:
    """The pre-fit's placement of every marker; refused naming the marker whose readings no
    placement explains (the others being explained without it), else naming the table."""
    tools = fit_tool_points(robot, ds)
    if explains(tools):
        return tools                                                  # type: ignore[return-value]
    if len(ds.markers) > 1:
        culprits = []
        for m in ds.markers:
            rest = [n for n in ds.markers if n != m]
            without = fit_tool_points(robot, ds, rest)
            if explains(without):
                culprits.append((without.rms, m, without))                # type: ignore[union-attr]
        if culprits:
            rms, m, without = min(culprits)
            raise InputError(f"marker {m}'s readings fit no placement on the tool: with it no rigid placement of "
                             f"the markers leaves less than {PLAUSIBLE_RMS_M * 100:g} cm "
                             f"({(tools.rms if tools else float('nan')) * 100:.3g} cm rms), without it "
                             f"{', '.join(without.markers)} fit to {rms * 1e3:.3g} mm; is {m} on this tool, "
                             "and named right in the table?", source=ds.source, column="marker")
    where = f" (the best placement leaves {tools.rms * 100:.3g} cm rms)" if tools is not None else ""
    raise InputError(f"no placement of the markers on the tool explains the readings{where}: not absolute positions "
                     "of this robot's markers, or not this robot", source=ds.source)


def needs_prefit(nominal: Registration | None) -> bool:
    """Whether the nominal registration leaves enough to start the full model from the pre-fit."""
    return nominal is None or nominal.rms > PREFIT_RMS_M


def usable(robot: Robot, tools: ToolPoints, nominal: Registration | None) -> bool:
    """Whether the pre-fit's placement is a better start than robot.toml's markers."""
    moved = max(float(np.linalg.norm(v)) for v in tools.moved(robot).values())
    return explains(tools) and moved > MIN_MOVE_M and (nominal is None or tools.rms < nominal.rms)
