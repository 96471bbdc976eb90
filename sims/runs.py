"""Slow motions on the simulated cell: compensator-joint sweeps and UV/VU friction runs (docs/formats.md §3).

* Joint sweeps (Y §5, Table 7): the compensated joint (joint 2 of a six-axis arm,
  the joint the robot's ``[compensator]`` names on any chain) moves at constant
  speed through a range, forward (``+``) and backward (``-``), the other joints
  held, at one or more values of the next joint (q3 on a six-axis arm). Friction changes sign with the direction; the mean of the
  two directions leaves gravity, payload and compensator (Y32-34).
* UV/VU runs (Y §6): the same joint-space straight line from U to V and back,
  at two speeds (viscous friction) and two loads (load-dependent friction),
  every joint moving so every joint's friction shows.

The motion is quasi-static: each sample is the static equilibrium at the
commanded ``q`` with friction on (:meth:`SimCell.motion_currents`), so
``xi i = tau_load + (fc sign(dq) + fv dq + fl |tau_load| sign(dq))`` (the drive
supplies friction in the direction of motion), plus
current noise from the caller's seeded generator. No tracker readings.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass, replace

import numpy as np

from elastocal.model.kinds import JointKind
from elastocal.model.robot import Robot
from elastocal.formats.tables import RunTable, run_table_from_arrays, write_run_table
from elastocal.sims.cell import CellTruth, SimCell

#: plausible friction of a 150 kg-class robot (per joint): Coulomb [N·m],
#: viscous [N·m·s/rad], load-dependent [-]
DEFAULT_COULOMB = (110.0, 180.0, 140.0, 35.0, 30.0, 22.0)
DEFAULT_VISCOUS = (650.0, 1100.0, 800.0, 160.0, 140.0, 90.0)
DEFAULT_LOAD_FRICTION = (0.04, 0.03, 0.035, 0.04, 0.045, 0.05)
#: a linear track's carriage: Coulomb [N], viscous [N·s/m], load-dependent [-] (the simulator's
#: choice of a plausible size, not a measured value)
TRACK_FRICTION = (400.0, 3000.0, 0.03)


def default_run_truth(base: CellTruth) -> CellTruth:
    """``base`` with plausible Coulomb, viscous and load-dependent friction (a six-axis arm's
    values on the revolute joints, the last one repeated beyond six; a track's on a prismatic one)."""
    return replace(base, coulomb=base.per_joint(DEFAULT_COULOMB, TRACK_FRICTION[0]),
                   viscous=base.per_joint(DEFAULT_VISCOUS, TRACK_FRICTION[1]),
                   load_friction=base.per_joint(DEFAULT_LOAD_FRICTION, TRACK_FRICTION[2]))


def _six(value, name: str, n: int | None = 6) -> tuple[float, ...]:
    """Finite numbers, ``n`` of them (any number for None: one per joint, checked against the robot)."""
    out = tuple(float(v) for v in value)
    if (n is not None and len(out) != n) or not out or not all(np.isfinite(out)):
        raise ValueError(f"{name}: expected {n if n is not None else 'one per joint,'} finite numbers")
    return out


def _check_size(robot: Robot, name: str, value: tuple[float, ...]) -> None:
    if len(value) != robot.n_joints:
        raise ValueError(f"{name}: {len(value)} values for the {robot.n_joints} joints of {robot.name!r}")


def _place(robot: Robot, revolute: tuple[float, ...], fraction: float) -> tuple[float, ...]:
    """One value per joint of ``robot``: a six-axis arm's ``revolute`` values in order for its
    revolute joints (the last one repeated beyond six), a prismatic joint at ``fraction`` of its
    travel between its limits [m]."""
    out, r = [], 0
    for joint in robot.joints:
        if joint.kind is JointKind.PRISMATIC:
            out.append(joint.lower + fraction * (joint.upper - joint.lower))
        else:
            out.append(revolute[min(r, len(revolute) - 1)])
            r += 1
    return tuple(float(v) for v in out)


@dataclass(frozen=True)
class SweepPlan:
    """Sweeps of joint ``joint`` forward and backward at each value of the next joint (Y Table 7
    style; the field names are a six-axis arm's, where ``joint`` is 2 and the next one q3)."""

    q_base: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 1.5707963267948966, 0.0)
    q2_start: float = -0.6          # [rad] the swept joint's range
    q2_end: float = 1.7             # [rad]
    q3_values: tuple[float, ...] = (0.0, -0.7)   # the next joint's values [rad]
    speed_rad_s: float = 0.05
    step_rad: float = 0.01          # the swept joint's travel between two samples
    wrench: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # payload on the load point
    joint: int = 2                  # the swept joint (1-based), followed by the one q3_values sets

    @classmethod
    def for_robot(cls, robot: Robot, **changes) -> "SweepPlan":
        """The default plan placed on ``robot``'s joints: the compensator's joint swept (joint 2
        without one), the others held at a six-axis arm's values, a prismatic joint mid-travel."""
        base = cls()
        if robot.n_joints == 6 and not np.any(robot.prismatic) and robot.sweep_joint == 2:
            return replace(base, **changes) if changes else base
        return replace(base, q_base=_place(robot, base.q_base, 0.5), joint=robot.sweep_joint, **changes)

    def __post_init__(self) -> None:
        object.__setattr__(self, "q_base", _six(self.q_base, "q_base", None))
        if isinstance(self.joint, bool) or not isinstance(self.joint, int) or not 1 <= self.joint < len(self.q_base):
            raise ValueError("joint: the swept joint's number, with a joint after it")
        object.__setattr__(self, "wrench", _six(self.wrench, "wrench"))
        if not self.q2_end > self.q2_start:
            raise ValueError("q2_end must be above q2_start")
        if self.speed_rad_s <= 0 or self.step_rad <= 0:
            raise ValueError("speed_rad_s and step_rad must be positive")
        if not self.q3_values:
            raise ValueError("q3_values: give at least one q3")


@dataclass(frozen=True)
class FrictionPlan:
    """UV/VU runs along one joint-space line, at each speed and each load."""

    q_u: tuple[float, ...] = (-0.5, -0.1, -0.6, -0.9, 0.7, -1.2)
    q_v: tuple[float, ...] = (0.5, 0.7, 0.1, 0.9, 1.7, 1.2)
    #: speed of the fastest-moving joint in each pair of runs [rad/s]
    speeds_rad_s: tuple[float, ...] = (0.05, 0.15)
    #: (load name, wrench on the load point [N, N·m]); "0" is unloaded
    loads: tuple[tuple[str, tuple[float, ...]], ...] = (
        ("0", (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)),
        ("1", (900.0, -700.0, -1500.0, 200.0, -200.0, 250.0)),
    )
    samples: int = 240              # samples per run

    @classmethod
    def for_robot(cls, robot: Robot, **changes) -> "FrictionPlan":
        """The default runs placed on ``robot``'s joints: a six-axis arm's U and V on its revolute
        joints, a prismatic joint from 45 % to 55 % of its travel (it then moves at a tenth of a
        metre or so per second at most, a carriage's slow run)."""
        base = cls()
        if robot.n_joints == 6 and not np.any(robot.prismatic):
            return replace(base, **changes) if changes else base
        return replace(base, q_u=_place(robot, base.q_u, 0.45), q_v=_place(robot, base.q_v, 0.55), **changes)

    def __post_init__(self) -> None:
        object.__setattr__(self, "q_u", _six(self.q_u, "q_u", None))
        object.__setattr__(self, "q_v", _six(self.q_v, "q_v", len(self.q_u)))
        object.__setattr__(self, "loads", tuple((str(n), _six(w, f"load {n}")) for n, w in self.loads))
        if self.samples < 2 or any(s <= 0 for s in self.speeds_rad_s):
            raise ValueError("samples must be >= 2 and speeds positive")


@dataclass
class _Columns:
    run: list
    direction: list
    load: list
    t: list
    q: list
    dq: list
    currents: list
    wrench: list

    @classmethod
    def empty(cls) -> "_Columns":
        return cls([], [], [], [], [], [], [], [])


def _record(cols: _Columns, cell: SimCell, rng: np.random.Generator, *, run: str, direction: str, load: str,
            t: np.ndarray, q: np.ndarray, dq: np.ndarray, wrench: np.ndarray) -> None:
    noise = cell.truth.current_noise_a
    w = np.asarray(wrench, dtype=float)
    for k in range(len(t)):
        i = cell.motion_currents(q[k], dq[k], w) + rng.normal(0.0, noise, size=cell.robot.n_joints)
        cols.run.append(run)
        cols.direction.append(direction)
        cols.load.append(load)
        cols.t.append(t[k])
        cols.q.append(q[k])
        cols.dq.append(dq[k])
        cols.currents.append(i)
        cols.wrench.append(w)


def simulate_sweeps(robot: Robot, truth: CellTruth, plan: SweepPlan, rng: np.random.Generator, *,
                    t0: float = 0.0, cols: _Columns | None = None) -> tuple[_Columns, float]:
    """Sweeps of ``plan.joint`` (``+`` then ``-``) at each value of the next joint."""
    _check_size(robot, "q_base", plan.q_base)
    swept = plan.joint - 1
    cell = SimCell(robot, truth)
    cols = _Columns.empty() if cols is None else cols
    n = int(round((plan.q2_end - plan.q2_start) / plan.step_rad)) + 1
    q2 = np.linspace(plan.q2_start, plan.q2_end, n)
    dt = (q2[1] - q2[0]) / plan.speed_rad_s
    t = t0
    load = "0" if not np.any(plan.wrench) else "payload"
    for k, q3 in enumerate(plan.q3_values, start=1):
        for direction, path in (("+", q2), ("-", q2[::-1])):
            q = np.tile(plan.q_base, (n, 1))
            q[:, swept + 1] = q3
            q[:, swept] = path
            dq = np.zeros((n, robot.n_joints))
            dq[:, swept] = plan.speed_rad_s if direction == "+" else -plan.speed_rad_s
            times = t + dt * np.arange(n)
            _record(cols, cell, rng, run=f"sweep{k}{direction}", direction=direction, load=load, t=times, q=q,
                    dq=dq, wrench=np.array(plan.wrench))
            t = times[-1] + 5.0
    return cols, t


def simulate_friction_runs(robot: Robot, truth: CellTruth, plan: FrictionPlan, rng: np.random.Generator, *,
                           t0: float = 0.0, cols: _Columns | None = None) -> tuple[_Columns, float]:
    """UV and VU runs at each speed and load of ``plan``."""
    _check_size(robot, "q_u", plan.q_u)
    cell = SimCell(robot, truth)
    cols = _Columns.empty() if cols is None else cols
    qu, qv = np.array(plan.q_u), np.array(plan.q_v)
    s = np.linspace(0.0, 1.0, plan.samples)
    span = qv - qu
    t = t0
    for load, wrench in plan.loads:
        for speed in plan.speeds_rad_s:
            duration = float(np.max(np.abs(span))) / speed
            for direction in ("UV", "VU"):
                if direction == "UV":
                    q = qu + np.outer(s, span)
                    dq = np.tile(span / duration, (plan.samples, 1))
                else:
                    q = qv - np.outer(s, span)
                    dq = np.tile(-span / duration, (plan.samples, 1))
                times = t + s * duration
                _record(cols, cell, rng, run=f"{direction}-{speed:g}-{load}", direction=direction, load=load,
                        t=times, q=q, dq=dq, wrench=np.array(wrench))
                t = times[-1] + 5.0
    return cols, t


#: the default plans of :func:`simulate_runs`, placed on the robot's joints (``for_robot``)
DEFAULT_SWEEPS = SweepPlan()
DEFAULT_FRICTION = FrictionPlan()


def simulate_runs(robot: Robot, truth: CellTruth, *, seed: int, sweeps: SweepPlan | None = DEFAULT_SWEEPS,
                  friction: FrictionPlan | None = DEFAULT_FRICTION, source: str = "<simulated runs>",
                  progress=None) -> RunTable:
    """Run table (docs/formats.md §3) of compensator-joint sweeps then UV/VU runs on the simulated
    cell; the default plans are placed on ``robot``'s joints. ``progress``: told of the sweeps and
    of the runs, ``progress(done, label, total=...)``."""
    def stage(done: int, label: str) -> None:
        if progress is not None:
            progress(done, label, total=2)

    if sweeps is DEFAULT_SWEEPS:
        sweeps = SweepPlan.for_robot(robot)
    if friction is DEFAULT_FRICTION:
        friction = FrictionPlan.for_robot(robot)
    rng = np.random.default_rng(seed)
    cols = _Columns.empty()
    t = 0.0
    if sweeps is not None:
        stage(0, "the compensator sweeps")
        cols, t = simulate_sweeps(robot, truth, sweeps, rng, t0=t, cols=cols)
    if friction is not None:
        stage(1, "the UV/VU runs")
        cols, t = simulate_friction_runs(robot, truth, friction, rng, t0=t, cols=cols)
    if not cols.run:
        raise ValueError("simulate_runs: nothing to simulate (no sweeps and no friction runs)")
    return run_table_from_arrays(run=cols.run, direction=cols.direction, load=cols.load, t=cols.t, q=cols.q,
                                 dq=cols.dq, currents=cols.currents, wrench=cols.wrench, source=source)


def write_runs_csv(path: str | pathlib.Path, table: RunTable) -> None:
    """Write a simulated run table (docs/formats.md §3)."""
    write_run_table(path, table)


def simulate_run_dataset(robot: Robot, truth: CellTruth, *, seed: int, out_dir: str | pathlib.Path) -> dict:
    """Write ``out_dir/runs.csv`` (sweeps and UV/VU runs) and return the true
    parameters it shows that ``truth.parameters(robot)`` does not hold (none:
    compensator and friction parameters are already there)."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = simulate_runs(robot, truth, seed=seed, source=str(out / "runs.csv"))
    write_runs_csv(out / "runs.csv", table)
    return {}


#: what ``elastocal sim runs --hidden`` can switch on: each friction term alone, all
#: three together ("friction", the realistic cell), the compensator (the description then
#: gives no nominal C, l_c), or none; "a,b" for several
RUN_HIDDEN = ("none", "coulomb_friction", "viscous_friction", "load_dependent_friction", "friction", "compensator")


def described_robot(robot: Robot, effect: str) -> Robot:
    """The robot description a user of the simulated cell has: with the compensator
    hidden, its geometry without the nominal parameters (the cell still has them)."""
    names = {e.strip() for e in effect.split(",")}
    if "compensator" not in names or robot.compensator is None:
        return robot
    return replace(robot, compensator=replace(robot.compensator, nominal=()))


def hide_in_runs(truth: CellTruth, effect: str) -> CellTruth:
    """``truth`` with only the named friction switched on (sizes of
    :func:`default_run_truth`); ``none`` switches friction off, ``friction``
    switches on all three terms. The compensator and the link masses are always
    in the run physics: the run torque model always holds them (docs/cli.md);
    ``compensator`` hides it from the description (:func:`described_robot`)."""
    names = {e.strip() for e in effect.split(",")}     # "a,b": several
    for name in names:
        if name not in RUN_HIDDEN:
            raise ValueError(f"the simulator cannot hide {name!r} in run data; one of {', '.join(RUN_HIDDEN)}")
    zero = np.zeros(truth.n_joints)
    full = default_run_truth(truth)
    return replace(truth,
                   coulomb=full.coulomb if names & {"coulomb_friction", "friction"} else zero,
                   viscous=full.viscous if names & {"viscous_friction", "friction"} else zero,
                   load_friction=full.load_friction if names & {"load_dependent_friction", "friction"} else zero)
