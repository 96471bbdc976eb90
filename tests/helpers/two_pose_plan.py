"""The short plan two tests run twice on one seed to show that a procedure's table repeats: two
random poses (seed 4), an 80 kg load, two markers, two readings of 0.03 s each."""

import numpy as np

from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.sims.static import random_poses


def two_pose_plan(robot):
    poses = random_poses(robot, 2, np.random.default_rng(4))
    return parse_plan(plan_toml(poses=poses, loads=(LoadSpec("L1", mass_kg=80.0),), markers=("R1", "R2"),
                                repeats=2, reading_s=0.03,
                                settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=10.0)))
