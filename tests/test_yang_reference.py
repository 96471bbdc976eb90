"""Yang et al. Table 5 (HH-150 static loading): current-to-torque handling and
load-current linearity. The joint configurations were published only as
pictures, so the table checks torques, not the full identification."""

import csv
import pathlib

import numpy as np
import pytest

from elastocal.formats.robot_toml import bundled_robot

DATA = pathlib.Path(__file__).parent / "data" / "yang_hh150_static.csv"
ROBOT = bundled_robot()


def load():
    with open(DATA) as fh:
        rows = list(csv.DictReader(fh))
    out = {}
    for r in rows:
        out.setdefault(r["config"], []).append(r)
    return out


def test_torque_constants_are_yang_table_2():
    np.testing.assert_allclose(ROBOT.torque_constants,
                               [169.6355, 220.8436, 220.8436, 127.0724, 138.3101, 139.4627])


@pytest.mark.parametrize("config", ["1", "2", "3", "4"])
def test_joint_torque_differences_grow_linearly_with_hung_load(config):
    rows = load()[config]
    fz = np.array([float(r["fz_N"]) for r in rows])
    i = np.array([[float(r[f"i{j}_A"]) for j in range(1, 7)] for r in rows])
    gamma = ROBOT.torque_constants * (i - i[0])     # Γ = ξ ⊙ (i(load) − i(0))
    dz = np.array([float(r["dz_mm"]) for r in rows[1:]]) * 1e-3
    for j in (1, 2):  # joints 2 and 3 carry the weight
        slope, intercept = np.polyfit(fz, gamma[:, j], 1)
        fit = slope * fz + intercept
        r2 = 1 - np.sum((gamma[:, j] - fit) ** 2) / np.sum((gamma[:, j] - gamma[:, j].mean()) ** 2)
        assert r2 > 0.95, (config, j, r2)
        # a 1 kN weight at 1.5–2.5 m from the axes: 1–3 kN·m on the shoulder and elbow
        assert 0.2 < abs(slope) < 3.5, slope
    # the deflection follows the load too: downwards, proportional to fz
    slope, intercept = np.polyfit(fz[1:], dz, 1)
    assert slope < 0 and abs(intercept) < 0.2e-3
    # and the implied compliance lies between the joint stiffness values of Table 6
    assert 1e-6 < abs(slope) < 5e-6


def test_lateral_loads_reach_joint_1():
    rows = load()
    for config in ("5", "6"):
        r0, r1 = rows[config]
        di1 = (float(r1["i1_A"]) - float(r0["i1_A"])) * ROBOT.torque_constants[0]
        assert abs(di1) > 500.0   # N·m from the horizontal force
