"""Planning time: 12 poses out of 2,000 candidate poses (design/search.py).

    python benchmarks/bench_plan.py [--candidates 2000] [--poses 12] [--loads-per-pose 2] [--repeat 3]

Prints the time to sample the candidates (joint limits, heights, reach,
markers' line of sight from the tracker), the time of the search itself
(greedy start, Fedorov exchange, load directions), and the quality reached
against random poses.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from elastocal.design import search as dz
from elastocal.design import candidates as dzc
from elastocal.formats.robot_toml import bundled_robot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--candidates", type=int, default=2000)
    parser.add_argument("--poses", type=int, default=12)
    parser.add_argument("--loads-per-pose", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    robot = bundled_robot()
    markers = robot.marker_names
    test = dz.TestPose(q=(0.3, 0.5, -0.3, 0.2, 1.0, 0.1), wrench=(800.0, -300.0, -600.0, 0.0, 0.0, 0.0))
    workspace = dz.Workspace(f_max_n=1100.0, base_p_tracker=(3.5, 0.0, 1.2))
    sample_s, plan_s = [], []
    for r in range(args.repeat):
        t0 = time.perf_counter()
        cand = dzc.sample_candidates(robot, args.candidates, np.random.default_rng(r), workspace, markers)
        t1 = time.perf_counter()
        design = dz.plan_experiment(robot, cand, test, n_poses=args.poses, loads_per_pose=args.loads_per_pose,
                                    workspace=workspace, markers=markers)
        t2 = time.perf_counter()
        sample_s.append(t1 - t0)
        plan_s.append(t2 - t1)
    baseline = dz.random_design_k40(robot, cand, design.forces, test, n_poses=args.poses, markers=markers,
                                    rng=np.random.default_rng(99))
    print(f"elastocal plan benchmark: {args.poses} poses x {args.loads_per_pose} loads out of {args.candidates} "
          f"candidates, HH-150, 3 markers, {args.repeat} runs")
    print(f"  sampling candidates: {np.median(sample_s):.3f} s median ({cand.sampled} poses drawn, "
          f"{cand.accepted} respected the workspace)")
    print(f"  planning:            {np.median(plan_s):.3f} s median (min {min(plan_s):.3f} s; "
          f"{design.rounds} round(s), {design.exchanges} exchanges in the last run)")
    print(f"  K40 {design.quality.k40:.4g} (random poses, same loads: median {np.median(baseline):.4g}); "
          f"predicted accuracy at the test pose {design.quality.accuracy_m * 1e6:.2f} µm rms")


if __name__ == "__main__":
    main()
