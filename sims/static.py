"""Static before/after-load experiments on the simulated cell (docs/formats.md §2)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.model.robot import LOAD_FRAME, Robot
from elastocal.formats.tables import StaticTable, static_table_from_arrays
from elastocal.sims.cell import CellTruth, SimCell

G = 9.81
#: joint ranges the random poses are drawn from: the working region in front of
#: the six-axis arm, wrist away from its singularity [rad]
WORK_LOW = np.array([-1.0, -0.35, -1.0, -1.6, 0.5, -1.6])
WORK_HIGH = np.array([1.0, 1.0, 0.35, 1.6, 1.9, 1.6])
#: joints before the six-axis arm (a track, a turntable) move over this middle part of their range
AUXILIARY_RANGE = 0.8


def work_region(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the random poses: the six-axis arm's working region on the last six joints,
    the middle :data:`AUXILIARY_RANGE` of the limits on the joints before them (a track)."""
    n_aux = max(robot.n_joints - len(WORK_LOW), 0)
    mid, half = (robot.upper + robot.lower) / 2, (robot.upper - robot.lower) / 2 * AUXILIARY_RANGE
    lo = np.r_[mid[:n_aux] - half[:n_aux], WORK_LOW[len(WORK_LOW) - (robot.n_joints - n_aux):]]
    hi = np.r_[mid[:n_aux] + half[:n_aux], WORK_HIGH[len(WORK_HIGH) - (robot.n_joints - n_aux):]]
    return np.maximum(lo, robot.lower), np.minimum(hi, robot.upper)


@dataclass(frozen=True)
class StaticPlan:
    """What a simulated static experiment does."""

    n_poses: int = 12
    n_loads: int = 3            # loaded states per pose, besides the unloaded reference
    repeats: int = 3            # readings per marker and load state
    markers: tuple[str, ...] | None = None  # default: every marker of the robot
    reading_s: float = 2.0      # time between two readings
    load_change_s: float = 45.0
    move_s: float = 30.0
    #: one drive reading per repeat, copied to the rows of all its markers
    #: (docs/formats.md §2), instead of one reading per row
    shared_currents: bool = False

    def __post_init__(self) -> None:
        if self.n_poses < 1 or self.n_loads < 1 or self.repeats < 1:
            raise ValueError("n_poses, n_loads and repeats must be >= 1")


def random_poses(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` reachable poses in the working region: load point above 0.3 m, wrist
    away from its singularity, within the joint limits."""
    lo, hi = work_region(robot)
    wrist = robot.n_joints - 2          # the wrist bend of the six-axis arm: either side
    poses = []
    while len(poses) < n:
        q = rng.uniform(lo, hi)
        if rng.random() < 0.5:
            q[wrist] = -q[wrist]
        z = robot.positions(robot.theta(q), [LOAD_FRAME])[0, 2]
        if z < 0.3:
            continue
        poses.append(q)
    return np.array(poses)


def load_wrenches(n_loads: int, rng: np.random.Generator) -> np.ndarray:
    """Wrenches (n_loads, 6) on the load point for one pose: hung weights, then
    cable pulls in a random horizontal direction."""
    out = np.zeros((n_loads, 6))
    for k in range(n_loads):
        if k == 0:
            out[k, 2] = -60.0 * G
        elif k == 1:
            out[k, 2] = -110.0 * G
        else:
            phi = rng.uniform(-np.pi, np.pi)
            horizontal = rng.uniform(500.0, 900.0)
            out[k, :3] = [horizontal * np.cos(phi), horizontal * np.sin(phi), -rng.uniform(200.0, 600.0)]
    return out


def simulate_static(robot: Robot, truth: CellTruth, *, seed: int, plan: StaticPlan = StaticPlan(),
                    poses: np.ndarray | None = None, wrenches: Sequence[np.ndarray] | None = None,
                    source: str = "<simulated static>", progress=None) -> StaticTable:
    """Run a static experiment on the simulated cell and return its table.

    Per pose: the unloaded reference, then each load state; ``repeats`` readings
    of every marker per state, each reading with its own current sample (or,
    with ``plan.shared_currents``, one current sample per repeat for all markers).
    ``poses`` (n, 6) and ``wrenches`` (one (n_loads, 6) array per pose) override
    the random ones. ``progress``: told of each pose, ``progress(done, label, total=...)``.
    """
    rng = np.random.default_rng(seed)
    cell = SimCell(robot, truth)
    markers = list(plan.markers or robot.marker_names)
    if poses is None:
        poses = random_poses(robot, plan.n_poses, rng)
    poses = np.asarray(poses, dtype=float)
    cols: dict[str, list] = {k: [] for k in ("pose", "load", "t", "q", "wrench", "currents", "marker", "xyz")}
    t = 0.0
    for p, q in enumerate(poses, start=1):
        if progress is not None:
            progress(p - 1, f"pose {p}", total=len(poses))
        w_states = load_wrenches(plan.n_loads, rng) if wrenches is None else np.asarray(wrenches[p - 1])
        t += plan.move_s
        reference = cell.equilibrium(q)
        states = [("0", np.zeros(6), reference)]     # the wrench: six components on any robot
        for k, w in enumerate(w_states, start=1):
            states.append((str(k), w, cell.equilibrium(q, w, reference=reference)))
        for index, (load, w, eq) in enumerate(states):
            if index:
                t += plan.load_change_s
            for _ in range(plan.repeats):
                shared = cell.read_currents(eq, rng) if plan.shared_currents else None
                for m in markers:
                    t += plan.reading_s
                    cols["pose"].append(str(p))
                    cols["load"].append(load)
                    cols["t"].append(t)
                    cols["q"].append(q)
                    cols["wrench"].append(w)
                    cols["currents"].append(shared if shared is not None else cell.read_currents(eq, rng))
                    cols["marker"].append(m)
                    cols["xyz"].append(cell.read_tracker(eq, [m], t, rng)[0])
    return static_table_from_arrays(pose=cols["pose"], load=cols["load"], t=cols["t"], q=cols["q"],
                                    wrench=cols["wrench"], currents=cols["currents"], marker=cols["marker"],
                                    xyz=cols["xyz"], source=source)


#: size of a simulated bad tracker reading (a beam break, a knocked reflector) [m]
OUTLIER_RANGE_M = (3e-4, 5e-4)


def add_outliers(table: StaticTable, n: int, rng: np.random.Generator) -> tuple[StaticTable, np.ndarray]:
    """``n`` tracker readings of distinct repeat groups moved 0.3-0.5 mm in a
    random direction: (the table, the 1-based file lines of the bad readings)."""
    from dataclasses import replace

    if n <= 0:
        return table, np.zeros(0, dtype=int)
    groups: dict[tuple[str, str, str], list[int]] = {}
    for i, key in enumerate(zip(table.pose, table.load, table.marker)):
        groups.setdefault(key, []).append(i)
    keys = list(groups)
    if n > len(keys):
        raise ValueError(f"cannot add {n} outliers to {len(keys)} repeat groups")
    chosen = rng.choice(len(keys), size=n, replace=False)
    rows = np.array(sorted(int(rng.choice(groups[keys[k]])) for k in chosen))
    xyz = table.xyz.copy()
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    xyz[rows] += direction * rng.uniform(*OUTLIER_RANGE_M, size=(n, 1))
    return replace(table, xyz=xyz), table.line[rows]
