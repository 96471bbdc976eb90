"""Identification from run data (docs/formats.md §3): compensator and friction.

Dispatches the run-data effects of ``--model`` to their fits —
``compensator`` (and ``gravity``) to identify/compensator.py on the joint-2
sweeps, the friction effects to identify/friction.py on the UV/VU pairs — and
gathers one result with the torque residual of docs/cli.md: measured ``xi i`` minus
the torque model, in the reduced form each fit uses (forward/backward means of
joint 2 along the sweeps; UV/VU half-differences per moving joint).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.identify.effects import run_effects
from elastocal.identify.robot import Robot
from elastocal.identify.static import Parameter
from elastocal.identify.tables import RunTable

#: the effects run data show, as each effect module declares (run_part)
RUN_EFFECTS = run_effects()
SWEEP_EFFECTS = run_effects("sweep")
FRICTION_EFFECTS = run_effects("uv/vu")


@dataclass(frozen=True, eq=False)
class RunFit:
    """The run-data effects fitted: typed parameters (docs/formats.md §4 names), the torque residuals."""

    model: tuple[str, ...]
    parameters: tuple[Parameter, ...]
    residuals: np.ndarray            # torque residuals [N·m], all fits together
    unidentifiable: tuple[str, ...] = ()
    fits: dict = field(default_factory=dict, repr=False)   # "compensator" / "friction" -> fit object

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2))) if self.residuals.size else float("nan")

    def to_json(self) -> dict:
        out = {"model": list(self.model), "torque": "current",
               "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in self.parameters},
               "residual": {"rms": self.rms, "max": float(np.max(np.abs(self.residuals))) if self.residuals.size
                            else float("nan"), "n": int(self.residuals.size), "unit": "N*m"},
               "noise_floor": None}
        if self.unidentifiable:
            out["unidentifiable"] = list(self.unidentifiable)
        return out


def identify_runs(robot: Robot, table: RunTable, *, model: Sequence[str] = ("joint_stiffness",),
                  stiffness: Sequence[float] | None = None) -> RunFit:
    """Fit the run-data effects named in ``model`` to a run table."""
    from elastocal.identify.compensator import compensator_from_run_table
    from elastocal.identify.friction import friction_from_run_table

    wanted = [m for m in model if m != "joint_stiffness"]
    unknown = [m for m in wanted if m not in RUN_EFFECTS]
    if unknown:
        raise InputError(f"{unknown[0]} cannot be identified from run data alone; it needs a static table",
                         argument="model")
    if not wanted:
        raise InputError("run data alone do not give the joint stiffness; name the run effects to fit, e.g. "
                         "--model compensator,coulomb_friction,viscous_friction", argument="model")
    params: dict = {}
    residuals = []
    unident: list[str] = []
    fits: dict = {}
    if any(m in SWEEP_EFFECTS for m in wanted):
        if robot.compensator is None:
            raise InputError("the robot description has no [compensator]", argument="model")
        gravity = "identify" if "gravity" in wanted else "auto"
        fit = compensator_from_run_table(robot, table, gravity=gravity, stiffness=stiffness)
        fits["compensator"] = fit
        params.update(fit.parameters())
        residuals.append(np.asarray(fit.residuals, dtype=float).ravel())
    terms = tuple(m.removesuffix("_friction") for m in wanted if m in FRICTION_EFFECTS)
    if terms:
        fit = friction_from_run_table(table, robot.torque_constants, terms=terms)
        fits["friction"] = fit
        params.update(fit.parameters())
        unident.extend(fit.unidentified)
        half = fit.samples.friction
        predicted = fit.torque(np.where(np.isfinite(fit.samples.speed), fit.samples.speed, 0.0),
                               fit.samples.load_torque)
        r = half - predicted
        residuals.append(r[np.isfinite(r)])
    names = tuple(dict.fromkeys(["joint_stiffness", *wanted]))
    return RunFit(model=names, parameters=tuple(Parameter(n, float(p["value"]), float(p["std"]), str(p["unit"]))
                                                for n, p in params.items()), residuals=np.concatenate(residuals) if residuals else np.zeros(0),
                  unidentifiable=tuple(unident), fits=fits)
