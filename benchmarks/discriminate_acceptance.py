"""The next experiment over seeds (docs/plan.md, "The next experiment"): on simulated cells whose
first round leaves a hidden effect open, one planned round of at most 6 poses, then `diagnose` on
both rounds; the same with a random round of the same count (poses from the same candidates, load
forces of the same size in random rig directions); and complete cells (no hidden effect).

    python benchmarks/discriminate_acceptance.py [--seeds 20] [--poses 6] [--scale 1] [--effects link_compliance,...]

Prints one table row per case: how often diagnose names the hidden effect (or, for "none", stays
null) after the first round alone, after the planned round, after the random round, and the
median delta BIC of the hidden effect's test on both rounds together (planned | random).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

from elastocal.design.candidates import Workspace, load_directions, sample_candidates
from elastocal.design.discriminate import given_from_diagnosis, plan_discrimination
from elastocal.diagnose.static import diagnose_static
from elastocal.formats.robot_toml import load_robot
from elastocal.formats.tables import concat_static_tables
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = pathlib.Path(__file__).resolve().parents[1] / "elastocal" / "robots" / "hh150.toml"
#: the first round of each case: what leaves the effect open (too few poses; hung weights only)
FIRST = {"link_compliance": StaticPlan(n_poses=3, n_loads=2),
         "backlash": StaticPlan(n_poses=4, n_loads=2),
         "nonlinear_stiffness": StaticPlan(n_poses=4, n_loads=1),
         "none": StaticPlan(n_poses=4, n_loads=2)}
TARGETS = ("link_compliance", "backlash", "nonlinear_stiffness")
F_MAX_N = 110.0 * 9.81          # the rig's largest force: the simulated cell's heaviest weight
N_POSES, LOADS_PER_POSE = 6, 2


def _wrenches(forces: np.ndarray, pose_loads) -> list[np.ndarray]:
    return [np.array([np.concatenate([forces[f], np.zeros(3)]) for f in fl]) for fl in pose_loads]


def _dbic(diag, effect: str) -> float:
    """The delta BIC of ``effect``'s test against the model (nan when it was not tested)."""
    return next((c.delta_bic for c in diag.candidates if c.effect == effect), float("nan"))


def _scaled(truth: CellTruth, hidden: str, scale: float) -> CellTruth:
    """The hidden effect at ``scale`` times the simulator's typical size (smaller: harder to find)."""
    from dataclasses import replace

    if scale == 1.0 or hidden == "none":
        return truth
    if hidden == "link_compliance":
        return replace(truth, link_compliance=truth.link_compliance * scale)
    if hidden == "backlash":
        return replace(truth, backlash=truth.backlash * scale)
    if hidden == "nonlinear_stiffness":
        return replace(truth, hardening_torque=truth.hardening_torque / scale)
    raise ValueError(f"no scaling for {hidden}")


def one_seed(robot, hidden: str, seed: int, n_poses: int = N_POSES, scale: float = 1.0) -> dict:
    truth = _scaled(CellTruth().with_hidden(hidden), hidden, scale)
    first = simulate_static(robot, truth, seed=seed, plan=FIRST[hidden])
    d1 = diagnose_static(robot, first)
    targets = TARGETS if hidden == "none" else (hidden,)
    workspace = Workspace(f_max_n=F_MAX_N)
    design = plan_discrimination(robot, given_from_diagnosis(d1), targets, workspace, markers=robot.marker_names,
                                 n_poses=n_poses, loads_per_pose=LOADS_PER_POSE, seed=seed, n_random=0)
    planned = simulate_static(robot, truth, seed=seed + 10_000, poses=design.q,
                              wrenches=_wrenches(design.forces, design.pose_loads))
    d2 = diagnose_static(robot, concat_static_tables([first, planned]))
    rng = np.random.default_rng(seed + 20_000)
    cands = sample_candidates(robot, len(design.q), rng, workspace, robot.marker_names)
    dirs = F_MAX_N * load_directions(workspace.directions, robot.gravity)
    pick = [rng.choice(len(dirs), LOADS_PER_POSE, replace=False) for _ in cands.q]
    random_round = simulate_static(robot, truth, seed=seed + 10_000, poses=cands.q, wrenches=_wrenches(dirs, pick))
    d3 = diagnose_static(robot, concat_static_tables([first, random_round]))
    want = None if hidden == "none" else hidden
    return {"first": d1.verdict == want, "planned": d2.verdict == want, "random": d3.verdict == want,
            "poses": len(design.q), "time_s": design.time_s,
            "dbic_planned": _dbic(d2, hidden), "dbic_random": _dbic(d3, hidden)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--poses", type=int, default=N_POSES, help="poses of the planned and random rounds")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="the hidden effect at this times the simulator's typical size (default 1)")
    parser.add_argument("--effects", default="link_compliance,backlash,nonlinear_stiffness,none")
    args = parser.parse_args(argv)
    robot = load_robot(ROBOT)
    print(f"| hidden effect | first round | + planned round (≤ {args.poses} poses) | + random round (same count) "
          "| median ΔBIC, planned / random | seeds |")
    print("| --- | --- | --- | --- | --- | --- |")
    for hidden in args.effects.split(","):
        started = time.monotonic()
        rows = [one_seed(robot, hidden, s, args.poses, args.scale) for s in range(args.seeds)]
        n = len(rows)
        med = "-" if hidden == "none" else (f"{np.nanmedian([r['dbic_planned'] for r in rows]):.0f} / "
                                             f"{np.nanmedian([r['dbic_random'] for r in rows]):.0f}")
        print(f"| {hidden} | {sum(r['first'] for r in rows)}/{n} | {sum(r['planned'] for r in rows)}/{n} | "
              f"{sum(r['random'] for r in rows)}/{n} | {med} | {n} ({time.monotonic() - started:.0f} s) |")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
