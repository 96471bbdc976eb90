"""The geometry's Jacobian against central differences of the corrected robot (tests of kinematic_errors)."""

from __future__ import annotations

import numpy as np

from elastocal.identify import kinematics as kin


def assert_jacobian_is_the_differences(robot, theta, markers, names, links=None) -> np.ndarray:
    """Each column of ``kin.position_jacobian`` at ``theta`` (link angles ``links`` or none) equals the
    central difference of the positions of the robot corrected by +-1e-6 of that parameter; returns the
    Jacobian."""
    _, jac = kin.position_jacobian(robot, theta, markers, names, link_angles=links)
    h = 1e-6
    for c, name in enumerate(names):
        moved = []
        for step in (h, -h):
            r = kin.corrected_robot(robot, [name], [step])
            moved.append(kin.position_jacobian(r, theta + r.offsets - robot.offsets, markers, [name],
                                               link_angles=links)[0])
        # central differences of a smooth map at h = 1e-6: exact to ~1e-10 of a unit column
        np.testing.assert_allclose(jac[..., c], (moved[0] - moved[1]) / (2 * h), atol=1e-7, err_msg=name)
    return jac
