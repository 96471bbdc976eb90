"""Yang's analysis of the first-order model (Y Fig. 4-6) on the simulated cell.

Over a grid of (q2, q3), the exact statics of the simulated cell give noise-free
deflections under a large load; the first-order model ``dP = J(q) C Gamma``
identifies the stiffness from them; where every relative stiffness error stays
below 5 % the first-order model is good enough. It lives with the simulation
because it runs the simulated cell's statics (identification never imports sims).
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.model.robot import DEFAULT_PRIOR_STIFFNESS, LOAD_FRAME, Robot
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.model.kinds import TorqueSource, expect

#: relative stiffness error under which the first-order model is good enough (Y §4.2)
GOOD_ENOUGH = 0.05


# ============================================================ first-order map
@dataclass(frozen=True, eq=False)
class FirstOrderMap:
    """Where the first-order model identifies the stiffness well (Y Fig. 4-6)."""

    q2: np.ndarray                # (n2,) [rad]
    q3: np.ndarray                # (n3,) [rad]
    stiffness_error: np.ndarray   # (n3, n2, 6) |k_identified - k| / k (inf: not identifiable)
    position_error: np.ndarray    # (n3, n2) eps_P = |dP(k_id) - dP(k)| / |dP(k)| at the load point
    q_base: tuple[float, ...]
    wrench: tuple[float, ...]
    torque: TorqueSource
    threshold: float = GOOD_ENOUGH

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque, "torque")

    @property
    def max_stiffness_error(self) -> np.ndarray:
        return np.max(self.stiffness_error, axis=2)

    @property
    def good(self) -> np.ndarray:
        """(n3, n2) True where every joint's relative stiffness error is below the threshold."""
        return self.max_stiffness_error < self.threshold

    @property
    def good_fraction(self) -> float:
        return float(np.mean(self.good))


def first_order_map(robot: Robot, *, q_base: Sequence[float], wrench: Sequence[float],
                    stiffness: Sequence[float] = DEFAULT_PRIOR_STIFFNESS, markers: Sequence[str] | None = None,
                    torque: TorqueSource = TorqueSource.CURRENT, n_grid: int = 25,
                    threshold: float = GOOD_ENOUGH) -> FirstOrderMap:
    """Yang's analysis over (q2, q3), the other joints at ``q_base``.

    At every grid point the exact statics of the simulated cell (links'
    gravity, compensator at its nominal parameters, ``wrench`` on the load
    point, joint springs ``stiffness``) give noise-free marker deflections;
    the first-order model ``dP = J_m(q) diag(Gamma) c`` identifies ``c`` from
    them, with ``Gamma`` from the gear torques ("current") or ``J_f(q)^T W``
    ("force")."""
    expect(TorqueSource, torque, "torque")
    if n_grid < 2:
        raise InputError(f"must be >= 2, got {n_grid}", argument="map_grid")
    markers = list(markers or robot.marker_names)
    k = np.asarray(stiffness, dtype=float)
    comp = None
    if robot.compensator is not None:
        nom = robot.compensator.nominal_parameters()
        comp = None if nom is None else (float(nom[0]), float(nom[1]))
    cell = SimCell(robot, CellTruth(stiffness=k, compensator=comp, tracker_noise_m=0.0, current_noise_a=0.0))
    w = np.asarray(wrench, dtype=float)
    q2 = np.linspace(robot.lower[1], robot.upper[1], n_grid)
    q3 = np.linspace(robot.lower[2], robot.upper[2], n_grid)
    err = np.full((n_grid, n_grid, 6), np.inf)
    eps = np.full((n_grid, n_grid), np.inf)
    frames = [LOAD_FRAME, *markers]
    for a, v3 in enumerate(q3):
        for b_, v2 in enumerate(q2):
            q = np.array(q_base, dtype=float)
            q[1], q[2] = v2, v3
            eq0 = cell.equilibrium(q)
            eq1 = cell.equilibrium(q, w, reference=eq0)
            d_markers = cell.marker_positions(eq1, markers) - cell.marker_positions(eq0, markers)
            jac = robot.jacobians(robot.theta(q), frames)
            gam = eq1.gear_torque - eq0.gear_torque if torque == TorqueSource.CURRENT else jac[0].T @ w
            a_mat = (jac[1:, :3, :] * gam[None, None, :]).reshape(-1, 6)
            scale = np.linalg.norm(a_mat, axis=0)
            ok = scale > 1e-9 * max(float(scale.max()), 1e-300)
            if not np.all(ok):
                continue
            sv = np.linalg.svd(a_mat / scale, compute_uv=False)
            if sv[-1] < 1e-9 * sv[0]:
                continue
            c_id = np.linalg.lstsq(a_mat / scale, d_markers.reshape(-1), rcond=None)[0] / scale
            with np.errstate(divide="ignore"):
                k_id = np.where(c_id > 0, 1.0 / c_id, np.inf)
            err[a, b_] = np.abs(k_id - k) / k
            true_d = jac[0][:3] @ (gam / k)
            eps[a, b_] = float(np.linalg.norm(jac[0][:3] @ (gam * (c_id - 1.0 / k))) /
                               max(np.linalg.norm(true_d), 1e-300))
    return FirstOrderMap(q2=q2, q3=q3, stiffness_error=err, position_error=eps,
                         q_base=tuple(float(v) for v in q_base), wrench=tuple(float(v) for v in w), torque=torque,
                         threshold=threshold)


def plot_first_order_map(fmap: FirstOrderMap, path: str | pathlib.Path, *, test_q: Sequence[float] | None = None,
                         poses: np.ndarray | None = None) -> None:
    """Write the map as PNG or SVG (by the file's suffix): (a) the largest
    relative stiffness error over the joints (blank above 10 %, Y Fig. 4),
    (b) the relative position error eps_P (Y Fig. 5), both with the good
    zone's border (Y Fig. 6), the test pose and the planned poses."""
    from matplotlib.figure import Figure

    path = pathlib.Path(path)
    if path.suffix.lower() not in (".png", ".svg"):
        raise InputError("the map is written as .png or .svg", source=str(path))
    fig = Figure(figsize=(10.0, 4.4), layout="constrained")
    axes = fig.subplots(1, 2)
    x, y = np.degrees(fmap.q2), np.degrees(fmap.q3)
    panels = ((fmap.max_stiffness_error, "(a) largest relative stiffness error"),
              (fmap.position_error, "(b) relative position error $\\epsilon_P$"))
    for ax, (values, title) in zip(axes, panels):
        shown = np.where(np.isfinite(values) & (values <= 0.10), values * 100.0, np.nan)
        mesh = ax.pcolormesh(x, y, shown, shading="nearest", cmap="viridis", vmin=0.0, vmax=10.0)
        fig.colorbar(mesh, ax=ax, label="%")
        if not np.all(fmap.good):
            ax.contourf(x, y, (~fmap.good).astype(float), levels=[0.5, 1.5], colors="none", hatches=["///"])
            ax.contour(x, y, fmap.good.astype(float), levels=[0.5], colors="red", linewidths=1.0)
        if poses is not None and len(poses):
            ax.plot(np.degrees(poses[:, 1]), np.degrees(poses[:, 2]), "o", mfc="white", mec="black", ms=5,
                    label="planned poses (their q2, q3)")
        if test_q is not None:
            ax.plot(math.degrees(test_q[1]), math.degrees(test_q[2]), "*", color="orange", mec="black", ms=13,
                    label="test pose")
        ax.set_xlabel("q2 [deg]")
        ax.set_ylabel("q3 [deg]")
        ax.set_title(title, fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        axes[0].legend(loc="lower left", fontsize=8)
    w = fmap.wrench
    fig.suptitle(f"first-order model, {fmap.torque}-based torques, load ({w[0]:.0f}, {w[1]:.0f}, {w[2]:.0f}) N\n"
                 f"good enough where every stiffness error < {fmap.threshold * 100:.0f} % "
                 f"(not hatched, {fmap.good_fraction * 100:.0f} % of the grid); blank: above 10 %", fontsize=9)
    fig.savefig(path, dpi=110)
