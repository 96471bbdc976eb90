"""Convert the CTU Motoman Leica set (LGPL-3.0-or-later) into elastocal's tables, once.

Source: GitHub ctu-vras/multirobot-calibration (Multisensorial robot calibration toolbox, Rozlivek, Rustler
et al., Czech Technical University in Prague), ``UserData/Robots/Motoman/Dataset/leica_dataset/
updated_leica_dataset.mat`` and the nominal kinematics of ``UserData/Robots/Motoman/loadMotomanLeica.m``.

Rows are selected as the toolbox's own loader ``loadNewLeicaDataset.m`` does: the first record of every
pose id, only poses the Leica logged, and the 13th of those removed (586 right-arm poses). The external
(torso) axis is ~0 (|E| < 2e-4 rad) and stays fixed at 0: the right arm is a 6R chain.

Columns of the .mat (leica_dataset_description.txt): pose id, face, arm, camera, u, v, E, S, L, U, R, B, T
(right arm), six left-arm joints, Leica X, Y, Z [m], total uncertainty [m], uncertainty X, Y, Z [m]. The
per-axis uncertainties are the tracker's standard deviations (the total is their root sum of squares),
stored rounded to 1 um; the rounding's own 1 um / sqrt(12) is added in quadrature, so none is zero.

Writes static.csv (all 586 poses, source order), train.csv and validate.csv (the alternate split: poses
1st, 3rd, 5th, ... of the source order for training, the others for validation, 293/293).

Run: python convert.py updated_leica_dataset.mat   (needs scipy; not part of the test suite)
"""

from __future__ import annotations

import csv
import math
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).parent
ROUNDING_STD_M = 1e-6 / math.sqrt(12.0)

#: loadMotomanLeica.m, structure.kinematics.rightArm: rows TT1, S1, L1, U1, R1, B1, T1, LR1;
#: columns a [m], d [m], alpha [rad], offset [rad]; standard DH (dhpars2tfmat.m: Rz(th) Tz(d) Tx(a) Rx(al))
STANDARD_DH = np.array([
    [0.000, -0.263, 15 * math.pi / 180, -math.pi / 2],
    [0.150, 1.4159, -math.pi / 2, 0.000],
    [0.614, 0.000, math.pi, -math.pi / 2],
    [0.200, 0.000, -math.pi / 2, 0.000],
    [0.000, -0.640, math.pi / 2, 0.000],
    [0.030, 0.000, math.pi / 2, -math.pi / 2],
    [0.000, 0.200, 0.000, 0.000],
    [0.045, 0.245, 0.000, -0.38],
])


def standard_dh_point(q6: np.ndarray) -> np.ndarray:
    """The toolbox's LR1 origin in its base frame (torso axis 0), as dhpars2tfmat.m computes it."""
    T = np.eye(4)
    for row, q in zip(STANDARD_DH, np.concatenate([[0.0], q6, [0.0]])):
        a, d, al, off = row
        th = q + off
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                          [0, sa, ca, d], [0, 0, 0, 1]])
    return T[:3, 3]


def modified_dh() -> tuple[list[tuple[float, float, float, float]], np.ndarray, np.ndarray]:
    """The same chain in modified DH (Craig): joint i takes (a, alpha) of the standard row before it.

    Returns ((a, alpha, d, offset) per joint), the fixed base transform (the torso row's Rz Tz) and the
    marker in flange coordinates (the LR1 row's Rz(offset) Tz(d) Tx(a) after joint 6's trailing Tx Rx,
    which is the identity here)."""
    joints = []
    for i in range(1, 7):
        a_prev, _, al_prev, _ = STANDARD_DH[i - 1]
        _, d, _, off = STANDARD_DH[i]
        joints.append((float(a_prev), float(al_prev), float(d), float(off)))
    _, d0, _, off0 = STANDARD_DH[0]
    base = np.array([[math.cos(off0), -math.sin(off0), 0, 0], [math.sin(off0), math.cos(off0), 0, 0],
                     [0, 0, 1, d0], [0, 0, 0, 1]])
    a7, d7, _, off7 = STANDARD_DH[7]
    marker = np.array([a7 * math.cos(off7), a7 * math.sin(off7), d7])
    return joints, base, marker


def modified_dh_point(q6: np.ndarray) -> np.ndarray:
    joints, base, marker = modified_dh()
    T = base.copy()
    for (a, al, d, off), q in zip(joints, q6):
        ca, sa, ct, st = math.cos(al), math.sin(al), math.cos(q + off), math.sin(q + off)
        T = T @ np.array([[1, 0, 0, a], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1]]) @ np.array(
            [[ct, -st, 0, 0], [st, ct, 0, 0], [0, 0, 1, d], [0, 0, 0, 1]])
    return (T @ np.append(marker, 1.0))[:3]


def select_rows(data: np.ndarray) -> np.ndarray:
    """loadNewLeicaDataset.m: first record per pose id, Leica-logged poses only, the 13th removed."""
    _, first = np.unique(data[:, 0], return_index=True)
    rows = data[first]
    rows = rows[~np.isnan(rows[:, -1])]
    return np.delete(rows, 12, axis=0)


def write(path: pathlib.Path, rows: np.ndarray) -> None:
    header = ["pose", "load", "q1", "q2", "q3", "q4", "q5", "q6", "marker", "x", "y", "z", "sx", "sy", "sz"]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        for r in rows:
            s = np.sqrt(r[23:26] ** 2 + ROUNDING_STD_M ** 2)
            w.writerow([int(r[0]), 0, *(f"{v:.9g}" for v in r[7:13]), "LR1",
                        *(f"{v:.9g}" for v in r[19:22]), *(f"{v:.3e}" for v in s)])


def main(mat_path: str) -> None:
    import scipy.io

    rows = select_rows(scipy.io.loadmat(mat_path)["dataset"])
    assert len(rows) == 586, len(rows)
    for q in rows[:20, 7:13]:                      # the conversion to modified DH changes no point
        assert np.allclose(standard_dh_point(q), modified_dh_point(q), atol=1e-12)
    write(HERE / "static.csv", rows)
    write(HERE / "train.csv", rows[0::2])
    write(HERE / "validate.csv", rows[1::2])


if __name__ == "__main__":
    main(sys.argv[1])
