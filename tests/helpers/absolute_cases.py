"""Absolute data with an effect outside the diagnosis's vocabulary, drawn here with numpy
around the simulator's public API: a cyclic gear error of joint 2 (the arm stands at
``q2 + A sin(n q2 + phi)`` while the controller reports ``q2``), which neither geometry,
registration, elasticity nor a drift can take up; on a robot with the simulator's kinematic
errors, so the kinematic step is genuine."""

from dataclasses import replace

import numpy as np

from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, random_poses, simulate_static

KINEMATIC = CellTruth().with_hidden("kinematic_errors")
#: amplitude [rad], harmonic and phase of the gear error
GEAR_ERROR = (60e-6, 3, 0.4)


def with_gear_error(robot, seed: int, *, amplitude: float = GEAR_ERROR[0], truth: CellTruth = KINEMATIC,
                    plan: StaticPlan = StaticPlan()):
    """A simulated static table whose joint 2 runs off its reported angle cyclically."""
    rng = np.random.default_rng(seed)
    commanded = random_poses(robot, plan.n_poses, rng)
    actual = commanded.copy()
    _, n, phi = GEAR_ERROR
    actual[:, 1] += amplitude * np.sin(n * commanded[:, 1] + phi)
    table = simulate_static(robot, truth, seed=seed, plan=plan, poses=actual)
    index = np.array([int(p) - 1 for p in table.pose])
    return replace(table, q=commanded[index])


#: the procedure's start: 13:30 UTC (the table's t are Unix times, so places are named by clock)
START_UNIX_S = 1_764_682_200.0


def with_bumped_reflector(robot, seed: int, *, marker: str = "R2", bump_m=(0.25e-3, -0.2e-3, 0.15e-3),
                          at_pose: int = 7, truth: CellTruth = CellTruth(), plan: StaticPlan = StaticPlan()):
    """A simulated static table (Unix times) whose reflector ``marker`` was knocked on the tool by
    ``bump_m`` (flange frame) just before pose ``at_pose``'s first loaded state: every later
    reading of it is of the moved reflector. Returns (table, Unix time of the first moved reading)."""
    moved = replace(truth, kinematic_errors=tuple(truth.kinematic_errors) + tuple(
        (f"d{axis}_{marker}", float(v)) for axis, v in zip("xyz", bump_m)))
    before = simulate_static(robot, truth, seed=seed, plan=plan)
    after = simulate_static(robot, moved, seed=seed, plan=plan)       # the same draws: only the reflector moved
    t = before.t + START_UNIX_S
    first = (before.pose == str(at_pose)) & (before.load != "0")
    t_bump = float(t[first].min())
    late = (before.marker == marker) & (t >= t_bump)
    xyz = np.where(late[:, None], after.xyz, before.xyz)
    return replace(before, t=t, xyz=xyz), t_bump
