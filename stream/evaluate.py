"""What the stream achieved on a simulated cell, judged by the simulated cell's own physics.

The tool-point error of a cycle is where the simulated robot's load point truly is, running
the joints the stream sent under the true process wrench of that instant, minus where the
plan puts it (the simulated robot running the planned joints without the process load:
compensation's ``unloaded`` reference). The same for the path run without any correction
and for the offline program compensated for one constant wrench (``elastocal compensate``).
The physics is the simulator's (:func:`elastocal.sims.guided.statics`), never the model's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.compensation.model import CompensationModel
from elastocal.compensation.trajectory import compensate_path
from elastocal.model.kinds import KinematicForm
from elastocal.sims.guided import ProcessLoad, statics
from elastocal.stream.loop import CycleRecord


@dataclass(frozen=True)
class ErrorStats:
    rms_m: float               # rms of the 3-D error's norm over the evaluated points
    max_m: float
    n: int

    @classmethod
    def of(cls, error: np.ndarray) -> "ErrorStats":
        d = np.linalg.norm(np.asarray(error).reshape(-1, 3), axis=1)
        return cls(rms_m=float(np.sqrt(np.mean(d * d))), max_m=float(np.max(d)), n=int(len(d)))

    def to_json(self) -> dict:
        return {"rms": self.rms_m, "max": self.max_m, "n": self.n, "unit": "m"}


def _error(cell, q_run: np.ndarray, wrench: np.ndarray, q_plan: np.ndarray) -> np.ndarray:
    return statics(cell, q_run, wrench).load_point - statics(cell, q_plan, None).load_point


def stream_errors(cell, load: ProcessLoad, records: Sequence[CycleRecord], *, every: int = 1) -> np.ndarray:
    """Tool-point errors (k, 3) [m] of every ``every``-th cycle the stream ran."""
    picked = list(records)[::max(1, int(every))]
    return np.array([_error(cell, r.q_sent, load.at(r.t_path_s), r.q_planned) for r in picked]).reshape(-1, 3)


def path_errors(cell, load: ProcessLoad, t: np.ndarray, q_planned: np.ndarray, q_run: np.ndarray) -> np.ndarray:
    """Tool-point errors (m, 3) [m] of a program ``q_run`` sampled like the plan (times ``t``)."""
    return np.array([_error(cell, q_run[i], load.at(t[i]), q_planned[i]) for i in range(len(t))]).reshape(-1, 3)


def offline_commands(model: CompensationModel, q: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """The offline program compensated for one constant ``wrench`` (exact form, unloaded reference:
    what ``elastocal compensate --wrench`` writes)."""
    return compensate_path(model, q, np.asarray(wrench, dtype=float), form=KinematicForm.EXACT,
                           reference="unloaded").q_command
