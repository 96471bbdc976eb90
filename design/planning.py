"""The planning pipeline of ``elastocal plan``: candidate poses, the search, the baselinesit is compared with, the check subset, and the plan.toml text the procedures read(docs/plan.md). The command parses its flags and prints; everything else is here.It sits in acquisition because it writes the procedures' plan format(:mod:`elastocal.formats.plan`); the design itself is :mod:`elastocal.design.search`."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.formats.plan import CheckSpec, FrictionSpec, LoadSpec, Plan, parse_plan, plan_toml
from elastocal.design.search import CheckChoice, ExperimentDesign, choose_check, plan_experiment, random_design_k40
from elastocal.design.candidates import Candidates, TestPose, Workspace, sample_candidates
from elastocal.design.measures import DesignQuality, NoiseModel, evaluate_design
from elastocal.model.robot import Robot


def load_specs(forces: np.ndarray, gravity: np.ndarray):
    g = float(np.linalg.norm(gravity))
    down = gravity / g
    specs = []
    for k, f in enumerate(forces, start=1):
        size = float(np.linalg.norm(f))
        if np.allclose(f / size, down, atol=1e-9):
            specs.append(LoadSpec(f"L{k}", mass_kg=size / g, description=f"hung weight of {size / g:.1f} kg"))
        else:
            u = f / size + 0.0        # + 0.0: no negative zeros in the file
            specs.append(LoadSpec(f"L{k}", force_n=tuple(float(x) + 0.0 for x in f),
                                  description=f"pull of {size:.0f} N toward ({u[0]:+.2f}, {u[1]:+.2f}, {u[2]:+.2f}) "
                                              "in base axes, through a force gauge"))
    return tuple(specs)


@dataclass(frozen=True, eq=False)
class PlannedExperiment:
    """A planned calibration experiment and what it is compared with."""

    design: ExperimentDesign
    candidates: Candidates
    baseline_k40: np.ndarray            # K40 of random designs from the same candidates, same loads
    random_quality: DesignQuality       # one random design with the full noise model
    check: CheckChoice
    loads: tuple[LoadSpec, ...]
    pose_ids: tuple[str, ...]
    check_spec: CheckSpec
    text: str                           # plan.toml
    plan: Plan
    planning_s: float                   # time of the search alone
    #: the exchange that makes the kinematic set observable too (design/kinematic.py); None: stiffness only
    geometry: object | None = None


#: the stages :func:`plan_calibration` reports (sampling, choosing, geometry, baseline, check)
PLAN_STAGES = 5


def plan_calibration(robot: Robot, test: TestPose, workspace: Workspace, noise: NoiseModel, *,
                     markers: Sequence[str], n_poses: int, loads_per_pose: int, n_candidates: int, n_check: int,
                     prior_stiffness: Sequence[float], friction: Sequence[FrictionSpec] = (), name: str | None = None,
                     repeats: int = 3, seed: int = 0, source: str = "<plan.toml>",
                     geometry: bool = True, progress=None) -> PlannedExperiment:
    """Plan a calibration (K §V.C): ``n_poses`` of ``n_candidates`` sampled poses and the
    load forces, a random baseline, the check subset, and the plan.toml text (parsed back
    and validated for ``robot``; an error names ``source``). ``progress``: told of each stage,
    ``progress(done, label, total=...)`` (elastocal/progress.py)."""
    def stage(done: int, label: str) -> None:
        if progress is not None:
            progress(done, label, total=PLAN_STAGES)

    rng = np.random.default_rng(seed)
    stage(0, f"sampling {n_candidates} candidate poses")
    candidates = sample_candidates(robot, n_candidates, rng, workspace, markers)
    stage(1, f"choosing {n_poses} poses and their loads")
    t_plan = time.monotonic()
    design = plan_experiment(robot, candidates, test, n_poses=n_poses, loads_per_pose=loads_per_pose,
                             workspace=workspace, markers=markers, prior_stiffness=prior_stiffness, noise=noise)
    geo = None
    if geometry and robot.urdf is None:     # poses that observe the kinematic set too (docs/absolute.md)
        from elastocal.design.kinematic import plan_for_geometry

        stage(2, "poses that observe the geometry too")
        geo = plan_for_geometry(robot, candidates, design, test, workspace=workspace, markers=markers,
                                prior_stiffness=prior_stiffness, noise=noise, rng=np.random.default_rng(seed + 1))
        design = geo.design
    planning_s = time.monotonic() - t_plan
    stage(3, "a random design to compare with")
    baseline = random_design_k40(robot, candidates, design.forces, test, n_poses=n_poses, markers=markers, rng=rng)
    random_quality = evaluate_design(robot, candidates.q[rng.choice(len(candidates.q), n_poses, replace=False)],
                                     list(design.wrenches), test, markers, prior_stiffness=prior_stiffness,
                                     noise=noise)
    stage(4, "the check poses")
    check = choose_check(robot, design, test, n_check=min(n_check, n_poses), markers=markers,
                         prior_stiffness=prior_stiffness, noise=noise)
    loads = load_specs(design.forces, np.array(robot.gravity))
    pose_ids = tuple(f"P{k}" for k in range(1, len(design.q) + 1))
    friction = tuple(friction)
    check_spec = CheckSpec(poses=tuple(pose_ids[i] for i in check.poses), load=loads[check.load].id,
                           friction=friction[0].id if friction else None)
    text = plan_toml(poses=dict(zip(pose_ids, (tuple(float(v) for v in q) for q in design.q))), loads=loads,
                     markers=markers, name=name, repeats=repeats, friction=friction, check=check_spec,
                     procedures=("static", "friction") if friction else ("static",))
    plan = parse_plan(text, source=source)
    plan.validate_for(robot)
    return PlannedExperiment(design=design, candidates=candidates, baseline_k40=baseline,
                             random_quality=random_quality, check=check, loads=loads, pose_ids=pose_ids,
                             check_spec=check_spec, text=text, plan=plan, planning_s=planning_s, geometry=geo)
