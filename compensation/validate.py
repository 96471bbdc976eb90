"""Compensation checked on the simulated cell (Yang §6, Fig. 17).

The planned path and its compensated versions run on a simulated cell (any object
with the :class:`RunnableCell` methods, in practice :class:`elastocal.sims.cell.SimCell`,
which the caller builds: compensation never imports the simulation) under the
process wrench; the tool-point error along the path is measured against the
reference pose (:mod:`elastocal.compensation.trajectory`): the simulated robot
running the plan without process load (``reference="unloaded"``) or the rigid
kinematic pose (``"rigid"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from elastocal.compensation.ik import PlannedPath, yang_path
from elastocal.compensation.model import CompensationModel
from elastocal.compensation.trajectory import compensate_path
from elastocal.model.kinds import KinematicForm
from elastocal.model.robot import LOAD_FRAME, Robot

#: Yang Table 8: W = 1500 N. Taken as the workpiece pushing the tool up.
YANG_WRENCH = (0.0, 0.0, 1500.0, 0.0, 0.0, 0.0)


class RunnableCell(Protocol):
    """What validation needs of a simulated cell: its robot, its true parameters
    (``truth.stiffness``, ``truth.compensator``) and its statics."""

    robot: Robot
    truth: object

    def equilibrium(self, q, wrench=None): ...

    def load_point(self, equilibrium) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class ValidationResult:
    """Tool-point errors (n, 3) [m] along a path on the simulated cell."""

    t: np.ndarray
    reference: str
    wrench: np.ndarray                   # (n, 6)
    error_uncompensated: np.ndarray      # planned path under load
    error_first_order: np.ndarray        # first-order compensated path under load
    error_exact: np.ndarray              # exact compensated path under load
    predicted_deflection: np.ndarray     # model's prediction of error_uncompensated (exact form)
    unloaded_sag: np.ndarray             # unloaded run minus rigid plan: what the controller must handle

    @staticmethod
    def _stats(err: np.ndarray) -> dict[str, float]:
        d = np.linalg.norm(err, axis=1)
        return {"rms": float(np.sqrt(np.mean(d ** 2))), "max": float(np.max(d))}

    def summary(self) -> dict:
        """Error norms (rms and max over the path, metres) and the ratios to the
        uncompensated error."""
        unc = self._stats(self.error_uncompensated)
        fo = self._stats(self.error_first_order)
        ex = self._stats(self.error_exact)
        return {"reference": self.reference, "n": int(len(self.t)), "unit": "m",
                "uncompensated": unc, "first_order": fo, "exact": ex,
                "ratio_first_order": fo["max"] / unc["max"], "ratio_exact": ex["max"] / unc["max"],
                "prediction_error_max": float(np.max(np.linalg.norm(
                    self.predicted_deflection - self.error_uncompensated, axis=1))),
                "unloaded_sag": self._stats(self.unloaded_sag)}


def validate_on_sim(cell: RunnableCell, model: CompensationModel, path: PlannedPath, wrench, *,
                    reference: str = "unloaded") -> ValidationResult:
    """Run the planned, first-order and exact compensated paths on ``cell``."""
    robot = cell.robot
    q = np.asarray(path.q, dtype=float)
    w = np.asarray(wrench, dtype=float)
    w = np.tile(w, (len(q), 1)) if w.shape == (6,) else w
    exact = compensate_path(model, q, w, form=KinematicForm.EXACT, reference=reference)
    first = compensate_path(model, q, w, form=KinematicForm.FIRST_ORDER, reference=reference)

    def tcp(qs: np.ndarray, ws: np.ndarray | None) -> np.ndarray:
        return np.array([cell.load_point(cell.equilibrium(qi, None if ws is None else ws[i]))
                         for i, qi in enumerate(qs)])

    data = robot.create_data()
    rigid = np.array([robot.positions(robot.theta(qi), [LOAD_FRAME], data=data)[0] for qi in q])
    unloaded = tcp(q, None)
    target = unloaded if reference == "unloaded" else rigid
    return ValidationResult(t=np.asarray(path.t, dtype=float), reference=reference, wrench=w,
                            error_uncompensated=tcp(q, w) - target,
                            error_first_order=tcp(first.q_command, w) - target,
                            error_exact=tcp(exact.q_command, w) - target,
                            predicted_deflection=exact.tcp_deflection, unloaded_sag=unloaded - rigid)


def yang_validation(cell: RunnableCell, model: CompensationModel | None = None, *,
                    wrench=YANG_WRENCH, reference: str = "unloaded", step_m: float = 0.005) -> ValidationResult:
    """The Yang Table 8 path (x 1.2 -> 1.8 m at z 0.116 m, 10 mm/s, 1500 N) on the
    simulated ``cell``. ``model`` defaults to the cell's true stiffness and
    compensator (a perfect calibration); pass an identified one to see what a
    calibration achieves."""
    robot = cell.robot
    if model is None:
        model = CompensationModel(robot=robot, stiffness=cell.truth.stiffness, compensator=cell.truth.compensator)
    return validate_on_sim(cell, model, yang_path(robot, step_m=step_m), wrench, reference=reference)
