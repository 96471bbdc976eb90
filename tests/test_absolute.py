"""Absolute accuracy: the kinematic error model, its identifiable set,
the registration of a tracker placed anywhere, and the joint absolute fit, on
the simulated cell with the real DH table off by 0.02-0.05 deg and 0.1-0.5 mm."""

import json

import numpy as np
import pytest

from elastocal.cli import main
from elastocal.identify import kinematics as kin
from elastocal.identify.absolute import identify_absolute
from elastocal.identify.registration import kabsch
from elastocal.formats.robot_toml import bundled_robot, parse_robot
from elastocal.identify.static import identify_static
from elastocal.sims.as_built import KINEMATIC_ERRORS
from elastocal.sims.cell import DEFAULT_TRACKER, CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot()
FULL = ("joint_stiffness", "kinematic_errors", "tracker_frame")
#: what the frame, the markers and the parallel axes 2-3 absorb on the HH-150
ABSORBED = {"dq1": "rz", "da1": "tx", "dd1": "tz", "dalpha1": "rx", "dd3": "dd2"}


def test_position_jacobian_matches_finite_differences_of_the_rebuilt_robot():
    names = kin.parameter_names(ROBOT, ROBOT.marker_names)
    rng = np.random.default_rng(4)
    values = rng.normal(0.0, 1e-3, len(names))
    robot = kin.corrected_robot(ROBOT, names, values)
    q = np.array([0.3, 0.4, -0.5, 0.7, 1.1, -0.4])
    pos, jac = kin.position_jacobian(robot, robot.theta(q), list(ROBOT.marker_names), names)
    np.testing.assert_allclose(pos, robot.positions(robot.theta(q), ROBOT.marker_names), atol=1e-12)
    h = 1e-7
    for k, name in enumerate(names):
        step = np.zeros(len(names))
        step[k] = h
        plus = kin.corrected_robot(ROBOT, names, values + step)
        minus = kin.corrected_robot(ROBOT, names, values - step)
        fd = (plus.positions(plus.theta(q), ROBOT.marker_names)
              - minus.positions(minus.theta(q), ROBOT.marker_names)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, k], fd, atol=1e-6, err_msg=name)
    # on the chain whose links 2 and 3 bend (link_compliance): the same, with the springs' angles
    bent = np.array([2e-3, -1e-3, 1.5e-3, 3e-3])
    pos, jac = kin.position_jacobian(robot, robot.theta(q), list(ROBOT.marker_names), names, link_angles=bent)

    def bent_positions(r):
        return r.positions(r.theta_links(r.theta(q), bent), ROBOT.marker_names, links=True)

    np.testing.assert_allclose(pos, bent_positions(robot), atol=1e-12)
    for k, name in enumerate(names):
        step = np.zeros(len(names))
        step[k] = h
        fd = (bent_positions(kin.corrected_robot(ROBOT, names, values + step))
              - bent_positions(kin.corrected_robot(ROBOT, names, values - step))) / (2 * h)
        np.testing.assert_allclose(jac[:, :, k], fd, atol=1e-6, err_msg=name)
    # the nominal robot is untouched (a new robot is built, never changed and reverted)
    assert ROBOT.joints[2].beta == 0.0 and robot.joints[2].beta == values[names.index("dbeta3")]


def test_hayati_beta_only_where_consecutive_axes_are_parallel():
    assert kin.parallel_joints(ROBOT) == (3,)
    names = kin.parameter_names(ROBOT, ("R1",))
    assert "dbeta3" in names and not any(n.startswith("dbeta") and n != "dbeta3" for n in names)
    # a beta written in robot.toml round-trips
    text = ROBOT.to_toml().replace("offset = 3.141592653589793", "beta = 0.001\noffset = 3.141592653589793", 1)
    again = parse_robot(text)
    assert again.joints[2].beta == 0.001
    assert parse_robot(again.to_toml()).joints[2].beta == 0.001


@pytest.fixture(scope="module")
def kinematic_data():
    truth = CellTruth().with_hidden("kinematic_errors")
    return truth, [simulate_static(ROBOT, truth, seed=seed) for seed in range(5)]


def test_identifiable_set_on_parallel_axes_2_3(kinematic_data):
    truth, tables = kinematic_data
    fit = identify_absolute(ROBOT, tables[0], model=FULL)
    # dd3 moves along the same (parallel) axis as dd2: absorbed, never reported as identified
    assert set(fit.unidentifiable) == {"dq1", "da1", "dd1", "dalpha1", "dd3", "dq6", "dd6"}
    for dropped, by in ABSORBED.items():
        assert fit.absorbed_by[dropped][0][0] == by, (dropped, fit.absorbed_by[dropped])
    # the joint-6 zero and offset by the marker positions (dq6 turns them about z6, dd6 moves them along it)
    assert {n for n, _ in fit.absorbed_by["dd6"]} == {"dz_R1", "dz_R2", "dz_R3"}
    assert all(n.startswith(("dx_", "dy_")) for n, _ in fit.absorbed_by["dq6"])
    assert "dbeta3" in {p.name for p in fit.parameters}
    obj = fit.to_json()
    assert "dd3" in obj["unidentifiable"] and "dd3" not in obj["parameters"]
    assert "frame rotation about z (rz)" in obj["absorbed_by"]["dq1"]


def test_absolute_fit_recovers_geometry_to_the_noise_floor(kinematic_data):
    truth, tables = kinematic_data
    true_values = dict(truth.kinematic_errors)
    z_all = []
    for table in tables:
        nominal = identify_absolute(ROBOT, table)
        fit = identify_absolute(ROBOT, table, model=FULL)
        # millimetres before, the noise floor after
        assert nominal.rms > 0.2e-3 and nominal.max > 0.8e-3
        assert nominal.rms > 30 * nominal.noise_floor
        assert fit.rms < 1.25 * fit.noise_floor, (fit.rms, fit.noise_floor)
        assert fit.deflection_rms < 1.25 * fit.static.noise_floor
        expected = fit.identifiable.base_value(true_values)
        z = np.array([(p.value - expected[p.name]) / p.std for p in fit.parameters if p.name in fit.kinematic_names])
        assert len(z) == 27
        assert np.max(np.abs(z)) < 4.0
        z_all.append(z)
    z_all = np.concatenate(z_all)
    # coverage over 5 seeds x 27 parameters: the stds are honest
    assert np.mean(np.abs(z_all) < 3.0) >= 0.97
    assert 0.7 < np.sqrt(np.mean(z_all ** 2)) < 1.3


def test_rotated_tracker_gives_the_stiffness_of_an_aligned_one():
    aligned = CellTruth(tracker_rotation=np.eye(3), tracker_translation=np.zeros(3))
    placed = CellTruth()                         # the default cell: 3.7 m away, turned 2.4 rad, not level
    assert np.linalg.norm(DEFAULT_TRACKER[1]) > 3.0
    fa = identify_static(ROBOT, simulate_static(ROBOT, aligned, seed=11))
    fp = identify_static(ROBOT, simulate_static(ROBOT, placed, seed=11))
    for j in range(1, 7):
        a, p = fa.parameter(f"k{j}"), fp.parameter(f"k{j}")
        assert abs(a.value - p.value) < a.std, (j, a, p)
    assert abs(fa.rms - fp.rms) < 0.05 * fa.rms
    # the absolute fit registers the tracker where it stands
    fit = identify_absolute(ROBOT, simulate_static(ROBOT, placed, seed=11), model=FULL)
    np.testing.assert_allclose(fit.registration.base_p_tracker, [3.2, -1.8, 0.6], atol=2e-3)
    ka = identify_absolute(ROBOT, simulate_static(ROBOT, aligned, seed=11), model=FULL)
    for j in range(1, 7):
        assert abs(ka.parameter(f"k{j}").value - fit.parameter(f"k{j}").value) < ka.parameter(f"k{j}").std


def test_kabsch_is_exact_and_refuses_collinear_points():
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(20, 3))
    rot, t = DEFAULT_TRACKER
    reg = kabsch(pts, pts @ rot.T + t)
    np.testing.assert_allclose(reg.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(reg.translation, t, atol=1e-12)
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    assert kabsch(line, line) is None


def test_cli_sim_kinematic_errors_and_identify_json(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "3", "--out", str(out)]) == 0
    capsys.readouterr()
    truth = json.loads((out / "truth.json").read_text())
    for name, value in KINEMATIC_ERRORS:
        assert truth["parameters"][name]["value"] == pytest.approx(value)
    assert {"rx", "ry", "rz", "tx", "ty", "tz"} <= set(truth["parameters"])
    base = ["identify", "--robot", str(out / "robot.toml"), "--static", str(out / "static.csv"), "--json"]
    assert main(base) == 0
    plain = json.loads(capsys.readouterr().out)
    assert plain["absolute_residual"]["rms"] > 0.2e-3
    assert main([*base, "--model", ",".join(FULL), "--out", str(tmp_path / "cal.json")]) == 0
    full = json.loads(capsys.readouterr().out)
    assert full["absolute_residual"]["rms"] < 1.25 * full["absolute_noise_floor"]
    assert full["absolute_residual"]["unit"] == "m" and full["absolute_residual"]["n"] == 432
    assert "dd3" in full["unidentifiable"] and "dq2" in full["parameters"]
    cal = json.loads((tmp_path / "cal.json").read_text())
    assert cal["model"] == list(FULL)
    assert {"dq2", "dbeta3", "rz", "dx_R1"} <= set(cal["parameters"])
    assert cal["absolute_residual"]["rms"] == full["absolute_residual"]["rms"]


def test_diagnose_names_kinematic_errors_and_adding_them_reaches_the_floor(kinematic_data):
    from elastocal.diagnose.static import diagnose_static

    truth, tables = kinematic_data
    for table in tables[:3]:
        diag = diagnose_static(ROBOT, table)
        assert diag.verdict == "kinematic_errors"
        assert diag.steps == ()                       # the deflections fit: nothing elastic is missing
        a = diag.absolute
        assert a.base.rms > 30 * a.base.noise_floor
        assert [s.effect for s in a.steps] == ["kinematic_errors"]
        assert a.final.rms < 1.25 * a.final.noise_floor
        obj = diag.to_json()
        assert obj["verdict"] == "kinematic_errors"
        assert obj["absolute_residual"]["rms"] == a.base.rms and obj["absolute_noise_floor"] == a.base.noise_floor
        assert obj["absolute_candidates"][0]["effect"] == "kinematic_errors"
        assert obj["absolute_candidates"][0]["significant"]
        assert len(obj["absolute_per_pose"]) == 12
    # the null on complete data in >= 19 of 20 seeds is tests/test_diagnose.py's (it covers the absolute part)


def test_a_tracker_on_another_stand_is_not_a_missing_effect(tmp_path, capsys):
    from elastocal.diagnose.static import diagnose_static

    moved = CellTruth().with_hidden("tracker_frame")
    diag = diagnose_static(ROBOT, simulate_static(ROBOT, moved, seed=21))
    assert diag.verdict is None
    assert diag.absolute.base.rms < 1.25 * diag.absolute.base.noise_floor
    np.testing.assert_allclose(diag.absolute.base.registration.base_p_tracker, [-2.6, 2.9, 1.9], atol=2e-3)
    assert "tracker_frame" in {n.effect for n in diag.not_testable}
    out = tmp_path / "ds"
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "5", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["diagnose", "--robot", str(out / "robot.toml"), "--static", str(out / "static.csv")]) == 0
    text = capsys.readouterr().out
    assert "absolute positions (after the best rigid registration)" in text
    assert "kinematic_errors" in text and "--model joint_stiffness,kinematic_errors,tracker_frame" in text


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory, kinematic_data):
    from elastocal.formats.calibration import calibration_from_fit, write_calibration

    truth, tables = kinematic_data
    fit = identify_absolute(ROBOT, tables[0], model=FULL)
    path = tmp_path_factory.mktemp("cal") / "cal.json"
    write_calibration(path, calibration_from_fit(ROBOT.name, fit.to_json(), robot_description=ROBOT.to_toml()))
    return path


def test_validate_on_other_poses_and_another_tracker_stand(calibration_file, tmp_path, capsys):
    from elastocal.identify.accuracy import validate
    from elastocal.formats.calibration import read_calibration
    from elastocal.formats.tables import write_static_table

    cal = read_calibration(calibration_file)
    truth = CellTruth().with_hidden("kinematic_errors")
    for seed in (31, 32):                         # 12 other poses each
        other = simulate_static(ROBOT, truth, seed=seed)
        v = validate(ROBOT, cal, other)
        assert v.absolute_nominal.rms > 0.2e-3 and v.absolute_nominal.max > 0.8e-3
        assert v.absolute_calibrated.rms < 2.0 * v.noise_floor, (v.absolute_calibrated, v.noise_floor)
        assert v.deflection_calibrated.rms < 2.0 * v.noise_floor * np.sqrt(2)
        assert v.deflection_nominal.rms > 10 * v.deflection_calibrated.rms
        kept = validate(ROBOT, cal, other, keep_frame=True)
        assert kept.absolute_calibrated.rms < 2.0 * kept.noise_floor
    # the tracker moved to another stand: registered afresh it still holds; kept, it does not
    moved = simulate_static(ROBOT, replace_tracker(truth), seed=33)
    assert validate(ROBOT, cal, moved).absolute_calibrated.rms < 2.0 * v.noise_floor
    assert validate(ROBOT, cal, moved, keep_frame=True).absolute_calibrated.rms > 1e-2
    # the command and its --json object (docs/cli.md)
    write_static_table(tmp_path / "other.csv", other)
    (tmp_path / "robot.toml").write_text(ROBOT.to_toml())
    args = ["validate", "--robot", str(tmp_path / "robot.toml"), "--calibration", str(calibration_file),
            "--static", str(tmp_path / "other.csv")]
    assert main([*args, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["poses"] == 12 and obj["calibration"] == str(calibration_file)
    for part in ("absolute", "deflection"):
        for which in ("nominal", "calibrated"):
            assert set(obj[part][which]) == {"rms", "mean", "max", "p95", "n", "unit"}
    assert obj["absolute"]["calibrated"]["n"] == 432 and obj["deflection"]["calibrated"]["n"] == 324
    assert obj["absolute"]["calibrated"]["rms"] < 2.0 * obj["absolute"]["noise_floor"]
    assert main(args) == 0
    assert "absolute error on 12 poses not used in the fit: nominal" in capsys.readouterr().out
    # --keep-frame needs a registration in the calibration
    plain = tmp_path / "plain.json"
    doc = json.loads(calibration_file.read_text())
    doc["model"] = ["joint_stiffness", "kinematic_errors"]
    for name in ("rx", "ry", "rz", "tx", "ty", "tz"):
        del doc["parameters"][name]
    plain.write_text(json.dumps(doc))
    assert main(["validate", "--robot", str(tmp_path / "robot.toml"), "--calibration", str(plain), "--static",
                 str(tmp_path / "other.csv"), "--keep-frame"]) == 2
    assert "--keep-frame needs a calibration with tracker_frame" in capsys.readouterr().err


def replace_tracker(truth):
    import dataclasses

    from elastocal.sims.cell import MOVED_TRACKER

    return dataclasses.replace(truth, tracker_rotation=MOVED_TRACKER[0], tracker_translation=MOVED_TRACKER[1])


def test_robot_command_round_trip_and_urdf(calibration_file, tmp_path, capsys):
    import pinocchio as pin

    from elastocal.identify.accuracy import calibrated_robot
    from elastocal.formats.calibration import read_calibration
    from elastocal.formats.robot_toml import load_robot

    out, urdf = tmp_path / "calibrated.toml", tmp_path / "calibrated.urdf"
    assert main(["robot", "--calibration", str(calibration_file), "--out", str(out), "--urdf", str(urdf)]) == 0
    capsys.readouterr()
    expected = calibrated_robot(ROBOT, read_calibration(calibration_file))
    again = load_robot(out)
    model = pin.buildModelFromXML(urdf.read_text())
    data = model.createData()
    rng = np.random.default_rng(8)
    for _ in range(20):
        q = rng.uniform(ROBOT.lower, ROBOT.upper)
        want = expected.positions(expected.theta(q), ROBOT.marker_names)
        np.testing.assert_allclose(again.positions(again.theta(q), ROBOT.marker_names), want, rtol=0, atol=1e-9)
        pin.framesForwardKinematics(model, data, q)          # the URDF's joint variable is the controller's q
        flange = data.oMf[model.getFrameId("flange")]
        np.testing.assert_allclose(flange.translation, expected.positions(expected.theta(q), ["flange"])[0],
                                   rtol=0, atol=1e-9)
    # the corrections are in the file, and differ from the drawing
    assert again.joints[2].beta != 0.0 and again.joints[1].offset != ROBOT.joints[1].offset
    assert dict(again.tool.flange_p_markers)["R1"] != dict(ROBOT.tool.flange_p_markers)["R1"]
    assert main(["robot", "--calibration", str(calibration_file), "--out", str(out)]) == 2   # no --force
    assert "--force" in capsys.readouterr().err


def test_check_compares_absolute_accuracy_when_the_calibration_holds_the_geometry(calibration_file):
    from elastocal.formats.calibration import read_calibration
    from elastocal.diagnose.check import check_calibration

    cal = read_calibration(calibration_file)
    truth = CellTruth().with_hidden("kinematic_errors")
    holds = check_calibration(ROBOT, cal, static=simulate_static(ROBOT, truth, seed=41))
    assert holds.absolute is not None and holds.absolute.passed
    assert holds.to_json()["absolute"]["absolute"]["calibrated"]["rms"] < 2 * holds.absolute.validation.noise_floor
    # the real robot changed: joint 2's zero moved by 0.02 deg
    changed = dict(truth.kinematic_errors)
    changed["dq2"] += np.radians(0.02)
    import dataclasses

    bumped = dataclasses.replace(truth, kinematic_errors=tuple(changed.items()))
    lost = check_calibration(ROBOT, cal, static=simulate_static(ROBOT, bumped, seed=42))
    assert not lost.absolute.passed and lost.verdict == "recalibrate"
    assert any(r.startswith("absolute accuracy lost") for r in lost.reasons)


def test_compensated_path_through_the_cell_with_geometric_errors(calibration_file):
    """The real robot (calibrated geometry, springs, load) puts the
    tool where the drawing's path meant it, as the tracker sees it."""
    from elastocal.compensation.model import CompensationModel
    from drawing_path import drawing_path, tracker_error
    from elastocal.identify.accuracy import calibration_frame
    from elastocal.formats.calibration import read_calibration
    from elastocal.sims.cell import SimCell

    cal = read_calibration(calibration_file)
    model = CompensationModel.from_calibration(ROBOT, cal).with_tool("R1")
    truth = CellTruth().with_hidden("kinematic_errors")
    cell = SimCell(ROBOT, truth)
    frame = calibration_frame(cal)                     # the cell frame the calibration defines
    q, wrench, path = drawing_path(model)
    assert path.reference == "nominal"
    before, after = (tracker_error(ROBOT, cell, frame, q, c, wrench) for c in (q, path.q_command))
    assert before.max() > 1e-3                       # millimetres: geometry, sag and load
    assert after.max() <= 2 * truth.tracker_noise_m, after.max()
    # the model predicted the error it removed
    np.testing.assert_allclose(np.linalg.norm(path.tcp_deflection, axis=1), before, atol=2 * truth.tracker_noise_m)


def test_plan_makes_the_kinematic_set_observable_and_beats_random_poses():
    from elastocal.design import search as dz
    from elastocal.design import candidates as dzc
    from elastocal.design.kinematic import plan_for_geometry

    test = dzc.TestPose(q=(0.3, 0.5, -0.3, 0.2, 1.0, 0.1), wrench=(800.0, -300.0, -600.0, 0.0, 0.0, 0.0))
    workspace = dzc.Workspace(f_max_n=1100.0, base_p_tracker=(3.5, 0.0, 1.2))
    rng = np.random.default_rng(2)
    candidates = dzc.sample_candidates(ROBOT, 150, rng, workspace, ROBOT.marker_names)
    design = dz.plan_experiment(ROBOT, candidates, test, n_poses=12, loads_per_pose=3, workspace=workspace,
                                markers=ROBOT.marker_names)
    geo = plan_for_geometry(ROBOT, candidates, design, test, workspace=workspace, markers=ROBOT.marker_names,
                            rng=np.random.default_rng(3))
    obj = geo.to_json()
    assert obj["unidentifiable"] == ["dq1", "da1", "dd1", "dalpha1", "dd3", "dq6", "dd6"]
    assert obj["o1"] > obj["o1_random_median"] and obj["o1"] > obj["o1_stiffness_only"]
    assert obj["a_optimal"]["value"] < obj["a_optimal_random_median"]["value"]
    assert obj["a_optimal"]["value"] < obj["a_optimal_stiffness_only"]["value"]
    # the stiffness keeps most of what its own plan gave it
    assert geo.design.quality.k40 < 1.5 * design.quality.k40


def test_report_shows_absolute_errors_per_pose_and_their_vectors(kinematic_data):
    from elastocal.diagnose.static import diagnose_static
    from elastocal.report.html import render_report

    truth, tables = kinematic_data
    diag = diagnose_static(ROBOT, tables[1])
    page = render_report(ROBOT, diag)
    assert "Missing effect: <b>kinematic_errors</b>" in page
    section = page[page.index("<h2>Absolute positions</h2>"):]
    assert "Absolute error per pose" in section and "Error vectors (top view" in section
    assert section.count("<svg") == 2
    table = section[section.index("<table>"):section.index("</table>")]
    assert table.count("<tr>") == 1 + 12                  # header and one row per pose
    before = [p["rms"] for p in diag.absolute.base.per_pose()]
    after = [p["rms"] for p in diag.absolute.final.per_pose()]
    assert min(before) > 20 * max(after)                  # every pose: millimetres to the floor


def test_one_marker_on_the_tool_axis():
    """A single reflector on the axis of joint 6: neither the joint-6 zero nor its
    twist moves it, so k6, dq6 (and what the flange's tilt trades with the wrist)
    are reported unidentifiable, and the rest still reaches the floor."""
    truth = CellTruth().with_hidden("kinematic_errors")
    table = simulate_static(ROBOT, truth, seed=4, plan=StaticPlan(markers=("R1",)))
    fit = identify_absolute(ROBOT, table, model=FULL)
    assert {"k6", "dq6", "dd6"} <= set(fit.unidentifiable)
    assert fit.absorbed_by["dq6"] == ()                  # moves nothing at all
    assert fit.rms < 1.25 * fit.noise_floor
    assert all(abs(p.value) < 0.01 for p in fit.parameters if p.name in fit.kinematic_names)


def test_tracker_position_prior_from_the_cell(kinematic_data):
    truth, tables = kinematic_data
    free = identify_absolute(ROBOT, tables[2], model=FULL)
    placed = identify_absolute(ROBOT, tables[2], model=FULL, tracker_prior=(3.1, -1.7, 0.6))
    prior = placed.json_fields()["registration"]["prior"]
    assert prior["std"] == 0.1 and prior["offset"] == pytest.approx(np.linalg.norm(
        placed.registration.base_p_tracker - np.array([3.1, -1.7, 0.6])))
    # a tape-measure prior does not move a registration the data fix to micrometres
    np.testing.assert_allclose(placed.registration.base_p_tracker, free.registration.base_p_tracker, atol=1e-6)
    assert placed.rms == pytest.approx(free.rms, rel=1e-3)
