"""Make tests/data/compensation_reference.npz: compensated paths of the per-point implementation.

The reference file was made with this script at commit 39d2c42, before the batched kernel
replaced the per-point Pinocchio calls; tests/test_compensation_batched.py checks the
current implementation against it (and imports :func:`cases` for the inputs). Running it again
would record the current implementation, so do that only for a deliberate change of results.

Run: python tests/helpers/make_compensation_reference.py tests/data/compensation_reference.npz
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

from elastocal.compensation.ik import yang_path
from elastocal.compensation.model import CompensationModel
from elastocal.compensation.trajectory import compensate_path, predicted_residual
from elastocal.identify import kinematics as kin
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path, load_robot
from elastocal.sims.cell import CellTruth
from elastocal.model.kinds import KinematicForm


def cases() -> dict:
    """name -> (model, q (n, 6), wrench (6,) or (n, 6))."""
    rng = np.random.default_rng(15)
    robot = bundled_robot()
    truth = CellTruth()
    coarse = yang_path(robot, step_m=0.02)
    s, s_new = np.linspace(0, 1, len(coarse)), np.linspace(0, 1, 120)
    q_yang = np.column_stack([np.interp(s_new, s, coarse.q[:, j]) for j in range(6)])
    n = 60
    sl = np.linspace(0.0, 1.0, n)[:, None]
    q_wide = np.array([-0.4, 0.1, -0.3, 0.3, 0.9, -0.2]) * (1 - sl) + np.array([0.5, 0.6, 0.1, -0.4, 1.4, 0.5]) * sl
    w_var = rng.normal(size=(n, 6)) * np.array([600, 600, 1200, 60, 60, 60])
    w_var[::7] = 0.0                                   # unloaded samples among loaded ones
    w_yang = np.array([0.0, 0.0, 1500.0, 0.0, 0.0, 0.0])
    bare = replace(robot, joints=tuple(replace(j, mass=0.0) for j in robot.joints))
    urdf_robot = load_robot(bundled_robot_path("hh150_urdf"))
    names = kin.parameter_names(robot, robot.marker_names)
    geo = kin.corrected_robot(robot, names, rng.normal(size=len(names)) * 2e-4)
    marker = robot.marker_names[0]
    full = CompensationModel(robot, truth.stiffness, truth.compensator)
    return {
        "yang": (full, q_yang, w_yang),
        "wide": (full, q_wide, w_var),
        "nocomp": (CompensationModel(robot, truth.stiffness * 0.7, None), q_wide, w_var),
        "bare": (CompensationModel(bare, truth.stiffness, (4771.4, 0.9112)), q_wide, w_var),
        "urdf": (CompensationModel(urdf_robot, truth.stiffness, truth.compensator), q_wide, w_var),
        "marker": (full.with_tool(marker), q_wide, w_var),
        "geometry": (CompensationModel(geo, truth.stiffness, truth.compensator, nominal=robot).with_tool(marker),
                     q_wide, w_var),
    }


def main(out_path: str) -> None:
    out = {}
    for name, (model, q, w) in cases().items():
        out[f"{name}/q"] = q
        out[f"{name}/wrench"] = np.broadcast_to(w, q.shape).copy()
        refs = ("unloaded", "rigid") + (("nominal",) if model.nominal is not None else ())
        for form in KinematicForm:
            for ref in refs:
                r = compensate_path(model, q, w, form=form, reference=ref)
                key = f"{name}/{form}/{ref}"
                out[key + "/q_command"] = r.q_command
                out[key + "/theta_target"] = r.theta_target
                out[key + "/tcp_deflection"] = r.tcp_deflection
                out[key + "/residual"] = predicted_residual(model, r)
    np.savez_compressed(out_path, **out)


if __name__ == "__main__":
    main(sys.argv[1])
