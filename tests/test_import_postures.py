"""`elastocal import` of posture-per-row files (docs/import.md): joint-named columns, several
points per row, mm/deg, FIGAROH's calibration CSV layout; every bad input one line, exit 2,
nothing written."""

from __future__ import annotations

import csv
import json
import math
import re

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path

URDF_ROBOT = bundled_robot_path("hh150_urdf")
DH_ROBOT = bundled_robot_path("hh150")
ROBOT = bundled_robot("hh150_urdf")


def _postures(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 6) controller angles and (n, 3, 3) marker positions R1..R3 in a measuring frame
    (rotated and shifted from the base, as a tracker or a camera system stands)."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(ROBOT.lower, ROBOT.upper, size=(n, 6))
    c, s = math.cos(0.4), math.sin(0.4)
    rotation, shift = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([3.0, -1.0, 0.2])
    p = np.array([ROBOT.positions(ROBOT.theta(row), ["R1", "R2", "R3"]) for row in q]) @ rotation.T + shift
    return q, p


def _figaroh_csv(path, q, p, *, blank=None) -> None:
    """FIGAROH's calibration CSV (figaroh.calibration.data_loader.load_data): x1,y1,z1,phix1..phiz1 per
    point, then one column per joint named as the URDF joint, metres and radians; a pandas index first."""
    header = [""] + [f"{a}{k}" for k in (1, 2) for a in ("x", "y", "z", "phix", "phiy", "phiz")]
    header += [j.name for j in ROBOT.joints]
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for i, (qr, pr) in enumerate(zip(q, p)):
            points = [[repr(float(v)) for v in pr[k]] + ["0.1", "0.2", "0.3"] for k in (0, 1)]
            if blank is not None and blank[0] == i:
                points[blank[1]][:3] = ["", "", ""]
            writer.writerow([str(i), *points[0], *points[1], *(repr(float(v)) for v in qr)])


def _read(path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_figaroh_calibration_csv_becomes_an_absolute_only_table(tmp_path, capsys):
    q, p = _postures(7, seed=1)
    _figaroh_csv(tmp_path / "figaroh.csv", q, p, blank=(3, 1))          # posture 4 did not see its second point
    out = tmp_path / "static.csv"
    assert main(["import", str(tmp_path / "figaroh.csv"), "--robot", str(URDF_ROBOT),
                 "--points", "R1=x1,y1,z1;R2=x2,y2,z2", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["rows"], summary["postures"], summary["markers"]) == (13, 7, ["R1", "R2"])
    rows = _read(out)
    assert len(rows) == 13
    assert {r["load"] for r in rows} == {"0"} and not any(r["fx"] or r["i1"] or r["t"] for r in rows)
    seen = [(r["pose"], r["marker"]) for r in rows]
    assert ("4", "R2") not in seen and ("4", "R1") in seen
    for r in rows:
        k = int(r["pose"]) - 1
        np.testing.assert_array_equal([float(r[f"q{j}"]) for j in range(1, 7)], q[k])
        np.testing.assert_array_equal([float(r[a]) for a in "xyz"], p[k, int(r["marker"][1]) - 1])


@pytest.mark.parametrize("flag, columns", [("--u95", ("u95",)), ("--std", ("sx", "sy", "sz"))])
def test_mm_and_degrees_named_columns_three_points_two_files_and_uncertainty(tmp_path, capsys, flag, columns):
    """A motion-capture export: joints in degrees under their own names, three bodies in mm,
    an uncertainty column in mm; two sessions' files numbered on."""
    names = ["J1 [deg]", "J2 [deg]", "J3 [deg]", "J4 [deg]", "J5 [deg]", "J6 [deg]"]
    files = []
    for part, seed in enumerate((2, 3)):
        q, p = _postures(4, seed)
        path = tmp_path / f"session{part}.csv"
        with open(path, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(["frame", *names, *(f"{b}_{a}" for b in ("tool", "side", "top") for a in "XYZ"), "U95"])
            for i, (qr, pr) in enumerate(zip(q, p)):
                writer.writerow([str(i), *(repr(float(np.degrees(v))) for v in qr),
                                 *(repr(float(v * 1e3)) for v in pr.ravel()), "0.05"])
        files.append((path, q, p))
    out = tmp_path / "static.csv"
    assert main(["import", str(files[0][0]), str(files[1][0]), "--robot", str(DH_ROBOT), "--joints", ",".join(names),
                 "--points", "R1=tool_X,tool_Y,tool_Z;R2=side_X,side_Y,side_Z;R3=top_X,top_Y,top_Z",
                 "--unit", "mm", "--angles", "deg", flag, "U95", "--out", str(out)]) == 0
    assert "24 rows, 8 postures" in capsys.readouterr().out
    rows = _read(out)
    assert [r["pose"] for r in rows] == [str(k) for k in range(1, 9) for _ in range(3)]
    for r in rows:
        k = int(r["pose"]) - 1
        _, q, p = files[k // 4]
        np.testing.assert_allclose([float(r[f"q{j}"]) for j in range(1, 7)], q[k % 4], rtol=0, atol=1e-12)
        np.testing.assert_allclose([float(r[a]) for a in "xyz"], p[k % 4, int(r["marker"][1]) - 1], rtol=0,
                                   atol=1e-12)
        assert [float(r[c]) for c in columns] == pytest.approx([5e-5] * len(columns), rel=1e-12)
        assert not ({"u95", "sx"} - set(columns)) & set(r)       # only the uncertainty asked for
    from elastocal.formats.tables import read_static_table

    table = read_static_table(out, bundled_robot("hh150"))     # an absolute-only table elastocal reads
    assert len(table) == 24 and set(table.load) == {"0"}


def test_a_figaroh_file_with_unknown_tool_points_calibrates(tmp_path, capsys):
    """FIGAROH's layout from a robot whose two markers sit 15-25 cm from robot.toml's, read
    with 20 µm of noise: imported, then identified (the tool-point pre-fit finds the markers)."""
    rng = np.random.default_rng(7)
    q = rng.uniform(ROBOT.lower, ROBOT.upper, size=(40, 6))
    moved = {"R1": np.array([0.12, -0.1, 0.08]), "R2": np.array([-0.15, 0.05, 0.17])}
    from dataclasses import replace

    true = replace(ROBOT, tool=replace(ROBOT.tool, flange_p_markers=tuple(
        (m, tuple(np.array(p) + moved.get(m, 0.0))) for m, p in ROBOT.tool.flange_p_markers)))
    p = np.array([true.positions(true.theta(row), ["R1", "R2"]) for row in q]) + np.array([2.0, 1.0, -0.5])
    p += rng.normal(0.0, 20e-6, size=p.shape)
    _figaroh_csv(tmp_path / "figaroh.csv", q, p)
    out = tmp_path / "static.csv"
    assert main(["import", str(tmp_path / "figaroh.csv"), "--robot", str(DH_ROBOT),
                 "--points", "R1=x1,y1,z1;R2=x2,y2,z2", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["identify", "--robot", str(DH_ROBOT), "--static", str(out), "--json"]) == 0
    fit = json.loads(capsys.readouterr().out)
    found = fit["tool_prefit"]["flange_p_markers"]
    for m, p0 in ROBOT.tool.flange_p_markers:
        if m in moved:
            assert np.linalg.norm(np.array(found[m]) - (np.array(p0) + moved[m])) < 1e-3
    assert fit["absolute_residual"]["rms"] < 3 * 20e-6


def _write(tmp_path, header, rows) -> str:
    path = tmp_path / "postures.csv"
    path.write_text("\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n", encoding="utf-8")
    return str(path)


GOOD_Q = ["0.1", "0.2", "-0.3", "0.4", "0.5", "0.6"]
HEADER = ["A1", "A2", "A3", "A4", "A5", "A6", "x1", "y1", "z1", "x2", "y2", "z2"]
GOOD = GOOD_Q + ["1.5", "0.2", "1.1", "1.6", "0.1", "1.2"]


@pytest.mark.parametrize("header, rows, extra, match", [
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1;R2=x2,y2,w2"], r"line 1: no column 'w2' \(named by --points\)"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1"], r"--points: expected NAME=X,Y,Z"),
    (HEADER, [GOOD], ["--points", "R7=x1,y1,z1"], r"--points: 'R7' is not a marker of robot HH-150"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1;R1=x2,y2,z2"], r"--points: marker R1 is given twice"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1", "--joints", "A1,A2,A3"], r"--joints: names 3 columns; robot "
                                                                             r"HH-150 has 6 joints"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1", "--joints", "A1,A2,A3,A4,A5,J6"], r"no column 'J6' \(named by "
                                                                                    r"--joints\)"),
    (HEADER, [GOOD_Q[:2] + ["abc"] + GOOD[3:]], ["--points", "R1=x1,y1,z1"], r"line 2, column A3: 'abc' is not a "
                                                                             r"number"),
    (HEADER, [GOOD[:6] + ["1.5", "", "1.1"] + GOOD[9:]], ["--points", "R1=x1,y1,z1"],
     r"line 2, column y1: point R1 has an empty y1"),
    (HEADER, [GOOD[:6] + [""] * 6], ["--points", "R1=x1,y1,z1;R2=x2,y2,z2"], r"line 2: no point measured"),
    (HEADER, [["10", "20", "-30", "40", "50", "60"] + GOOD[6:]], ["--points", "R1=x1,y1,z1"],
     r"line 2, column A1: joint 1 \(A1\) at 10 rad is outside its limits.*give --angles deg"),
    (HEADER, [GOOD_Q + ["1500", "200", "1100"] + GOOD[9:]], ["--points", "R1=x1,y1,z1"],
     r"look like millimetres; give --unit mm"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1", "--unit", "mm"], r"look like metres read as millimetres; give "
                                                                  r"--unit m"),
    (HEADER, [], ["--points", "R1=x1,y1,z1"], r"no postures"),
    (HEADER, [GOOD[:8]], ["--points", "R1=x1,y1,z1"], r"line 2: 8 fields; the header has 12"),
    (HEADER + ["u"], [GOOD + ["20"]], ["--points", "R1=x1,y1,z1", "--u95", "u"], r"column u: an uncertainty of "
                                                                                 r"20000 mm"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1", "--names", "P{pose}_{marker}"], r"--names: is for tracker exports"),
    (HEADER, [GOOD], ["--points", "R1=x1,y1,z1", "--robot", "missing.toml"], r"missing\.toml"),
])
def test_bad_posture_files_are_one_line_errors_and_nothing_is_written(tmp_path, capsys, header, rows, extra, match):
    path = _write(tmp_path, header, rows)
    out = tmp_path / "static.csv"
    args = ["import", path, "--out", str(out), *extra]
    if "--robot" not in extra:
        args += ["--robot", str(URDF_ROBOT)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("elastocal import: ")
    assert re.search(match, err), err
    assert not out.exists()


def test_the_robot_is_needed_and_the_uncertainty_flags_only_with_points(tmp_path, capsys):
    path = _write(tmp_path, HEADER, [GOOD])
    assert main(["import", path, "--points", "R1=x1,y1,z1", "--out", str(tmp_path / "s.csv")]) == 2
    assert "--robot: posture-per-row files need the robot" in capsys.readouterr().err
    assert main(["import", path, "--joints", path, "--u95", "u", "--out", str(tmp_path / "s.csv")]) == 2
    assert "--u95: is for posture-per-row files" in capsys.readouterr().err
    assert not (tmp_path / "s.csv").exists()



def test_seven_joints_with_a_prismatic_one_in_millimetres(tmp_path, capsys):
    """The HH-150 on its track (7 joints, the first prismatic): the track's column in mm with
    --unit mm, the arm's in degrees; the table has q1..q7 with the track in metres."""
    robot = bundled_robot("hh150_track")
    rng = np.random.default_rng(4)
    q = rng.uniform(robot.lower, robot.upper, size=(5, 7))
    names = ["track [mm]"] + [f"A{i} [deg]" for i in range(1, 7)]
    path = tmp_path / "track.csv"
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow([*names, "x", "y", "z"])
        for row in q:
            p = robot.positions(robot.theta(row), ["R1"])[0]
            writer.writerow([repr(float(row[0] * 1e3)), *(repr(float(v)) for v in np.degrees(row[1:])),
                             *(repr(float(v)) for v in p * 1e3)])
    out = tmp_path / "static.csv"
    assert main(["import", str(path), "--robot", str(bundled_robot_path("hh150_track")), "--joints", ",".join(names),
                 "--points", "R1=x,y,z", "--unit", "mm", "--angles", "deg", "--out", str(out)]) == 0
    capsys.readouterr()
    from elastocal.formats.tables import read_static_table

    table = read_static_table(out, robot)
    np.testing.assert_allclose(table.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(table.xyz, [robot.positions(robot.theta(row), ["R1"])[0] for row in q], rtol=0,
                               atol=1e-12)
    # the track's column in metres read as mm: a carriage beyond its 6 m
    assert main(["import", str(path), "--robot", str(bundled_robot_path("hh150_track")), "--joints", ",".join(names),
                 "--points", "R1=x,y,z", "--angles", "deg", "--out", str(tmp_path / "bad.csv")]) == 2
    assert "joint 1 (T1)" in capsys.readouterr().err
