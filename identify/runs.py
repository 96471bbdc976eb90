"""Identification from run data (docs/formats.md §3): compensator, gravity and friction.

The run-data effects of the model are fitted together by the run model of
identify/runmodel.py: the friction effects (each module's ``run_column``) on the
half-differences of every forward/backward pair — UV/VU runs and ``+``/``-``
joint sweeps alike — and the sweep effects (each module's ``sweep_term``: the
compensator, gravity) on the joint-2 sweep means. The result holds the torque
residual of docs/cli.md (measured ``xi i`` minus the torque model, in those
reduced forms) and its noise floor (current repeatability through the
half-differences and sweep means).

Run data alone place the sweeps at the deflected configuration with robot.toml's
nominal joint stiffness when it gives one, else with the rigid model, whose bias
is stated (``stiffness`` of the result).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.model.effects import BASE_EFFECT, get_effect, run_effects
from elastocal.model.robot import Robot
from elastocal.identify.runmodel import RunModelFit, StiffnessUsed, fit_run_model, prepare_run_data, with_rigid_bias
from elastocal.identify.static import Parameter
from elastocal.formats.tables import RunTable

#: the effects run data show, as each effect module declares (run_part)
RUN_EFFECTS = run_effects()
SWEEP_EFFECTS = run_effects("sweep")
FRICTION_EFFECTS = run_effects("uv/vu")


@dataclass(frozen=True, eq=False)
class RunFit:
    """The run-data effects fitted: typed parameters (docs/formats.md §4 names), the torque residuals."""

    model: tuple[str, ...]
    parameters: tuple[Parameter, ...]
    residuals: np.ndarray            # torque residuals [N·m], half-differences then sweep means
    unidentifiable: tuple[str, ...] = ()
    noise_floor: float | None = None   # [N·m], the rms current noise alone would leave
    stiffness: StiffnessUsed | None = None   # what placed the sweeps (None without sweeps)
    fit: RunModelFit | None = field(default=None, repr=False)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2))) if self.residuals.size else float("nan")

    def to_json(self) -> dict:
        out = {"model": list(self.model), "torque": "current",
               "parameters": {p.name: {"value": p.value, "std": p.std, "unit": p.unit} for p in self.parameters},
               "residual": {"rms": self.rms, "max": float(np.max(np.abs(self.residuals))) if self.residuals.size
                            else float("nan"), "n": int(self.residuals.size), "unit": "N*m"},
               "noise_floor": self.noise_floor}
        if self.unidentifiable:
            out["unidentifiable"] = list(self.unidentifiable)
        if self.stiffness is not None:
            out["stiffness"] = self.stiffness.to_json()
        return out


def identify_runs(robot: Robot, table: RunTable, *, model: Sequence[str] = ("joint_stiffness",),
                  stiffness: Sequence[float] | None = None) -> RunFit:
    """Fit the run-data effects named in ``model`` to a run table.

    ``stiffness`` (k1..kN from a static fit) places the sweeps; without it robot.toml's
    nominal stiffness, else the rigid model (its bias stated in the result).
    """
    wanted = [m for m in model if m != BASE_EFFECT]
    unknown = [m for m in wanted if m not in RUN_EFFECTS]
    if unknown:
        raise InputError(f"{unknown[0]} cannot be identified from run data alone; it needs a static table",
                         argument="model")
    if not wanted:
        raise InputError("run data alone do not give the joint stiffness; name the run effects to fit, e.g. "
                         "compensator,coulomb_friction,viscous_friction", argument="model")
    effects = [get_effect(m, robot) for m in wanted]
    sweep_effects = [e for e in effects if e.run_part == "sweep"]
    data = prepare_run_data(robot, table, stiffness=stiffness,
                            sweep_effects=[get_effect(e, robot) for e in SWEEP_EFFECTS])
    if sweep_effects and data.sweeps is None:
        raise InputError(f"the table has no joint-{robot.sweep_joint} sweeps (direction + and -)",
                         source=table.source,
                         column="direction")
    for e in sweep_effects:
        if e.name in data.sweep_refused:
            raise InputError(f"{e.name}: {data.sweep_refused[e.name]}", argument="model")
    if any(e.run_part == "uv/vu" for e in effects) and data.friction is None:
        raise InputError("the table has no UV/VU runs and no +/- sweeps (the same path forward and backward)",
                         source=table.source, column="direction")
    fit = fit_run_model(data, effects)
    if sweep_effects:
        data = with_rigid_bias(data, table, [get_effect(e, robot) for e in SWEEP_EFFECTS], fit.model)
    residuals = []
    if any(e.run_part == "uv/vu" for e in effects) and fit.friction_residual is not None:
        r = fit.friction_residual
        residuals.append(r[np.isfinite(r)])
    if sweep_effects and fit.sweep is not None:
        residuals.append(fit.sweep.residuals)
    names = tuple(dict.fromkeys(["joint_stiffness", *wanted, *fit.model]))
    floor = _floor(fit, any(e.run_part == "uv/vu" for e in effects), bool(sweep_effects))
    return RunFit(model=names, parameters=fit.parameters,
                  residuals=np.concatenate(residuals) if residuals else np.zeros(0),
                  unidentifiable=fit.unidentifiable, noise_floor=floor,
                  stiffness=data.stiffness if sweep_effects else None, fit=fit)


def _floor(fit: RunModelFit, friction: bool, sweeps: bool) -> float | None:
    """The noise floor of the parts the model was fitted to."""
    n = (int(fit.friction_n.sum()) if friction else 0) + (fit.sweep_n if sweeps else 0)
    ss = (float(fit.friction_floor_ss.sum()) if friction else 0.0) + (fit.sweep_floor_ss if sweeps else 0.0)
    return float(np.sqrt(ss / n)) if n and np.isfinite(ss) and ss > 0 else None
