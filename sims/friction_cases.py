"""Held-out friction cases: UV/VU run tables drawn per seed on the simulator's own physics.

Each seed draws a cell the identification has never seen: friction coefficients
of every joint (Coulomb, viscous, load-dependent, each between 0.5 and 1.5 times
a heavy robot's typical size), a joint-space path on which every joint travels
0.5-1.5 rad, three speeds (the slowest 0.04-0.06 rad/s for the joint that travels
furthest, then about 3 and 6 times it) and two loaded states (cable pulls of 1-2 kN
in random directions with 200-400 N·m moments) besides the unloaded one, 1000
samples a run (a 100 Hz drive over a slow pass). The currents are
written from the motor's torque balance by sims/physics.py — the load torque from
``pin.rnea`` and the frame Jacobian at the deflected equilibrium, plus the friction
the drive supplies in the direction of motion — with Gaussian current noise.
Nothing of identify/ is used: a wrong sign or a wrong model in the fits shows.

The path's equilibria do not depend on the speed or the direction, so each load's
are solved once and every run at that load reads them (forward, or backward in
reverse order).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from elastocal.formats.tables import RunTable, run_table_from_arrays
from elastocal.model.robot import Robot
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.runs import default_run_truth

#: relative spread of each drawn friction coefficient around the typical size
SPREAD = (0.5, 1.5)
#: travel of each joint along a drawn path [rad, m]: every joint moves, none so far that the
#: others crawl (the path's duration is set by the joint that travels furthest)
TRAVEL = (0.5, 1.5)


@dataclass(frozen=True, eq=False)
class FrictionCase:
    """One held-out case: the run table, the truth that made it and the drawn plan."""

    table: RunTable
    truth: CellTruth
    seed: int
    q_u: np.ndarray          # (N,) path start
    q_v: np.ndarray          # (N,) path end
    speeds_rad_s: tuple[float, ...]
    wrenches: np.ndarray     # (n_loads, 6) the loaded states' wrenches on the load point [N, N·m]

    def coefficients(self) -> dict[str, float]:
        """True friction under docs/formats.md §4 names (fc1.., fv1.., fl1..)."""
        out: dict[str, float] = {}
        for prefix, values in (("fc", self.truth.coulomb), ("fv", self.truth.viscous),
                               ("fl", self.truth.load_friction)):
            out.update({f"{prefix}{j}": float(v) for j, v in enumerate(values, start=1)})
        return out


def _path(robot: Robot, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A straight joint-space path inside the middle 80 % of each joint's range on which each
    joint travels TRAVEL (at most 60 % of its range), in a random direction."""
    lo, hi = robot.lower, robot.upper
    mid, half = (lo + hi) / 2, 0.4 * (hi - lo)
    travel = np.minimum(rng.uniform(*TRAVEL, robot.n_joints), 1.5 * half) * rng.choice((-1.0, 1.0), robot.n_joints)
    u = rng.uniform(mid - half + np.maximum(-travel, 0.0), mid + half - np.maximum(travel, 0.0))
    return u, u + travel


def _wrench(rng: np.random.Generator) -> np.ndarray:
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    force = rng.uniform(1000.0, 2000.0) * direction
    force[2] = -abs(force[2])                       # a hung or pulled load: downward part
    moment = rng.uniform(200.0, 400.0, 3) * rng.choice((-1.0, 1.0), 3)
    return np.concatenate([force, moment])


def draw_truth(base: CellTruth, rng: np.random.Generator, *, friction: bool = True) -> CellTruth:
    """``base`` with friction of every joint drawn around a heavy robot's typical size."""
    n = base.n_joints
    if not friction:
        zero = np.zeros(n)
        return replace(base, coulomb=zero, viscous=zero, load_friction=zero)
    typical = default_run_truth(base)
    return replace(base, coulomb=typical.coulomb * rng.uniform(*SPREAD, n),
                   viscous=typical.viscous * rng.uniform(*SPREAD, n),
                   load_friction=typical.load_friction * rng.uniform(*SPREAD, n))


def friction_case(robot: Robot, seed: int, *, friction: bool = True, samples: int = 1000,
                  speed_factors: tuple[float, ...] = (1.0, 3.0, 6.0), n_loads: int = 2,
                  base: CellTruth | None = None, source: str | None = None) -> FrictionCase:
    """The held-out case of ``seed`` (module docstring); ``friction=False`` draws the same
    kind of cell with no friction at all (a diagnosis must then find nothing)."""
    rng = np.random.default_rng(seed)
    base = CellTruth.for_robot(robot, compensator=(4771.4, 0.9112)) if base is None else base
    truth = draw_truth(base, rng, friction=friction)
    cell = SimCell(robot, truth)
    q_u, q_v = _path(robot, rng)
    slow = float(rng.uniform(0.04, 0.06))
    speeds = tuple(slow * f * float(rng.uniform(0.85, 1.15)) if f != 1.0 else slow for f in speed_factors)
    wrenches = np.array([_wrench(rng) for _ in range(n_loads)])
    s = np.linspace(0.0, 1.0, samples)
    q_path = q_u + np.outer(s, q_v - q_u)
    span = float(np.max(np.abs(q_v - q_u)))
    rows: dict[str, list] = {k: [] for k in ("run", "direction", "load", "t", "q", "dq", "currents", "wrench")}
    xi = robot.torque_constants
    noise = truth.current_noise_a
    t = 0.0
    for load, w in (("0", np.zeros(6)), *((str(k), w) for k, w in enumerate(wrenches, start=1))):
        gear = np.array([cell.equilibrium(q, w).gear_torque for q in q_path])     # once per load
        for speed in speeds:
            duration = span / speed
            for direction, order, sign in (("UV", slice(None), 1.0), ("VU", slice(None, None, -1), -1.0)):
                dq = np.tile(sign * (q_v - q_u) / duration, (samples, 1))
                tau = gear[order]
                current = (tau + cell.friction_torque(dq, tau)) / xi + rng.normal(0.0, noise, tau.shape)
                rows["run"] += [f"{direction}-{speed:.3g}-{load}"] * samples
                rows["direction"] += [direction] * samples
                rows["load"] += [load] * samples
                rows["t"] += list(t + s * duration)
                rows["q"] += list(q_path[order])
                rows["dq"] += list(dq)
                rows["currents"] += list(current)
                rows["wrench"] += [w] * samples
                t += duration + 5.0
    table = run_table_from_arrays(**rows, source=source or f"<friction case {seed}>")
    return FrictionCase(table=table, truth=truth, seed=seed, q_u=q_u, q_v=q_v, speeds_rad_s=speeds,
                        wrenches=wrenches)
