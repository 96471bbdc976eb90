"""The simulated seven-joint cell: the HH-150 on a floor track (elastocal/robots/hh150_track.toml,
a prismatic joint and the six-axis arm) through the README's workflows, and six no longer
special anywhere on the way: tables with q1..q7, the MCAP log, identify, diagnose, validate,
compensate (CSV, KRL, RAPID) and the report.

Each check is against the simulator's truth or first principles (Pinocchio's kinematics),
within the uncertainty the fit reports; the statistics over 100 seeds are the heavy test.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from elastocal.compensation.chain import Angles, BatchedChain
from elastocal.errors import InputError
from elastocal.formats.calibration import read_calibration
from elastocal.formats.robot_toml import bundled_robot
from elastocal.formats.tables import parse_static_table, read_static_table
from elastocal.identify.absolute import identify_absolute
from elastocal.identify.static import build_dataset
from elastocal.model.robot import LOAD_FRAME
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static

ROBOT = bundled_robot("hh150_track")
K_NAMES = [f"k{j}" for j in range(1, 8)]
FRAME_NAMES = ["rx", "ry", "rz", "tx", "ty", "tz"]


def _cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "elastocal", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=600)


@pytest.fixture(scope="module")
def sim_static(tmp_path_factory):
    """``elastocal sim static --robot <the bundled track robot>``: robot.toml, static.csv, log.mcap, truth.json."""
    out = tmp_path_factory.mktemp("track")
    robot_path = out / "track.toml"
    robot_path.write_text(ROBOT.to_toml(), encoding="utf-8")
    done = _cli("sim", "static", "--robot", str(robot_path), "--out", str(out / "sim"), "--seed", "3")
    assert done.returncode == 0, done.stderr
    return out / "sim"


def test_the_bundled_track_robot_has_seven_joints_the_first_prismatic():
    assert ROBOT.n_joints == 7 and bool(ROBOT.prismatic[0]) and not np.any(ROBOT.prismatic[1:])
    assert ROBOT.compensator.joint == 3               # the arm's joint 2, behind the carriage
    truth = CellTruth.for_robot(ROBOT)
    assert truth.parameters(ROBOT)["k1"]["unit"] == "N/m"
    assert truth.parameters(ROBOT)["k2"]["value"] == CellTruth().stiffness[0]


def test_the_static_table_has_columns_for_seven_joints(sim_static):
    header = (sim_static / "static.csv").read_text(encoding="utf-8").splitlines()[0].split(",")
    assert [c for c in header if c.startswith("q")] == [f"q{j}" for j in range(1, 8)]
    assert [c for c in header if c.startswith("i")] == [f"i{j}" for j in range(1, 8)]
    table = read_static_table(sim_static / "static.csv", ROBOT)
    assert table.q.shape[1] == 7 and table.currents.shape[1] == 7
    # the carriage moves over the track: poses spread over metres of it
    assert np.ptp(table.q[:, 0]) > 1.0


def test_a_table_of_another_n_is_refused_in_one_line_naming_both(sim_static):
    text = (sim_static / "static.csv").read_text(encoding="utf-8")
    six = bundled_robot()
    with pytest.raises(InputError, match=r"q1\.\.q7.*'HH-150' has 6 joints") as err:
        parse_static_table(text, six, source="static.csv")
    assert "\n" not in str(err.value)


def test_identify_recovers_the_stiffness_of_every_joint_within_its_std(sim_static):
    done = _cli("identify", "--robot", str(sim_static / "robot.toml"), "--static", str(sim_static / "static.csv"),
                "--model", "joint_stiffness,tracker_frame", "--json")
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout)["parameters"]
    truth = json.loads((sim_static / "truth.json").read_text())["parameters"]
    for name in K_NAMES + FRAME_NAMES:
        assert got[name]["unit"] == truth[name]["unit"]
        z = (got[name]["value"] - truth[name]["value"]) / got[name]["std"]
        assert abs(z) < 4.0, (name, got[name], truth[name])


def test_the_log_holds_seven_drives_and_identifies_as_the_table(sim_static):
    from elastocal.acquisition.logreader import read_log

    contents = read_log(sim_static / "log.mcap")
    assert len(contents.drives) == 7 and all(len(d.t_ns) for d in contents.drives)
    from_log = _cli("identify", str(sim_static / "log.mcap"), "--json")
    from_csv = _cli("identify", "--robot", str(sim_static / "robot.toml"), "--static", str(sim_static / "static.csv"),
                    "--json")
    assert from_log.returncode == 0 and from_csv.returncode == 0, from_log.stderr + from_csv.stderr
    a, b = json.loads(from_log.stdout)["parameters"], json.loads(from_csv.stdout)["parameters"]
    for name in K_NAMES:
        assert abs(a[name]["value"] - b[name]["value"]) <= 0.01 * a[name]["std"]


def test_diagnose_names_the_hidden_link_compliance_on_the_track_cell(tmp_path):
    out = tmp_path / "lc"
    robot_path = tmp_path / "track.toml"
    robot_path.write_text(ROBOT.to_toml(), encoding="utf-8")
    done = _cli("sim", "static", "--robot", str(robot_path), "--hidden", "link_compliance", "--out", str(out),
                "--seed", "4", "--poses", "16")
    assert done.returncode == 0, done.stderr
    diag = _cli("diagnose", "--robot", str(out / "robot.toml"), "--static", str(out / "static.csv"), "--json")
    assert diag.returncode == 0, diag.stderr
    obj = json.loads(diag.stdout)
    assert obj["verdict"] == "link_compliance", obj["verdict"]


def test_validate_on_unseen_poses_is_within_a_quarter_above_the_floor(sim_static, tmp_path):
    cal = tmp_path / "cal.json"
    done = _cli("identify", "--robot", str(sim_static / "robot.toml"), "--static", str(sim_static / "static.csv"),
                "--model", "joint_stiffness,tracker_frame", "--out", str(cal))
    assert done.returncode == 0, done.stderr
    assert read_calibration(cal).find("k1").unit == "N/m"
    other = tmp_path / "other"
    assert _cli("sim", "static", "--robot", str(sim_static / "robot.toml"), "--out", str(other),
                "--seed", "11").returncode == 0
    done = _cli("validate", "--robot", str(sim_static / "robot.toml"), "--calibration", str(cal), "--static",
                str(other / "static.csv"), "--keep-frame", "--json")
    assert done.returncode == 0, done.stderr
    obj = json.loads(done.stdout)
    calibrated = obj["absolute"]["calibrated"]
    assert calibrated["rms"] <= 1.25 * obj["absolute"]["noise_floor"], obj["absolute"]


def test_the_default_as_built_errors_are_sized_by_each_joints_kind():
    """``--hidden kinematic_errors`` on the track cell: every joint's zero of its own kind (the carriage's
    a length of a tenth of a millimetre's order, the arm's an angle of hundredths of a degree; the carriage's fixed
    theta too, an angle), a tilt only on
    the axis parallel to the one before (the fit's own set says which), nothing the fit cannot hold; the
    six-axis HH-150 keeps its table exactly."""
    from elastocal.identify import kinematics as kin
    from elastocal.sims.as_built import KINEMATIC_ERRORS

    truth = CellTruth.for_robot(ROBOT).with_hidden("kinematic_errors")
    errors, units = dict(truth.kinematic_errors), truth.parameters(ROBOT)
    for j in range(1, 8):
        unit = kin.unit_of(f"dq{j}", ROBOT)
        assert units[f"dq{j}"]["unit"] == unit == ("m" if ROBOT.prismatic[j - 1] else "rad")
        low, high = (5e-5, 1e-3) if unit == "m" else (np.radians(0.01), np.radians(0.1))
        for kind in ("dq", "da", "dalpha") + (("dd",) if unit == "rad" else ("dtheta",)):
            size = abs(errors[f"{kind}{j}"])
            lo, hi = (5e-5, 1e-3) if kin.unit_of(f"{kind}{j}", ROBOT) == "m" else (low, high)
            assert lo <= size <= hi, (kind, j, size)
    assert [n for n in errors if n.startswith("dbeta")] == [f"dbeta{j}" for j in kin.parallel_joints(ROBOT)] \
        == ["dbeta4"]
    assert set(errors) <= set(kin.parameter_names(ROBOT, ROBOT.marker_names)) and "dd1" not in errors
    for six in (CellTruth(), CellTruth.for_robot(bundled_robot())):
        assert six.with_hidden("kinematic_errors").kinematic_errors == KINEMATIC_ERRORS


def test_identify_recovers_the_default_as_built_errors_of_the_track_cell(tmp_path):
    """One seed of ``sim static --hidden kinematic_errors`` on the track cell: the joint fit of springs,
    geometry and registration finds each kinematic parameter within 4 std of what it estimates (its own
    error plus what it absorbs) and reaches the floor."""
    truth = CellTruth.for_robot(ROBOT).with_hidden("kinematic_errors")
    ds = build_dataset(simulate_static(ROBOT, truth, seed=5, plan=StaticPlan()))
    fit = identify_absolute(ROBOT, ds, model=("joint_stiffness", "kinematic_errors", "tracker_frame"))
    assert fit.rms <= 1.25 * fit.noise_floor, (fit.rms, fit.noise_floor)
    values = dict(truth.kinematic_errors) | {f"c{j}": 1.0 / k for j, k in enumerate(truth.stiffness, start=1)}
    expected = fit.identifiable.base_value(values)
    z = {p.name: (p.value - expected[p.name]) / p.std for p in fit.parameters if p.name in fit.kinematic_names}
    assert len(z) > 25 and max(abs(v) for v in z.values()) < 4.0, z
    # the errors are there to find: most of what the fit keeps is many std from the drawing
    assert np.median([abs(expected[n]) / p.std for n in z for p in fit.parameters if p.name == n]) > 5.0


def test_the_batched_chain_is_pinocchio_on_a_prismatic_joint():
    """Compensation's batched kinematics and statics against Pinocchio's on the track robot."""
    rng = np.random.default_rng(7)
    q = np.column_stack([rng.uniform(ROBOT.lower * 0.5, ROBOT.upper * 0.5) for _ in range(6)])
    chain = BatchedChain(ROBOT.model)
    state = chain.state(Angles.of(q), masses=True)
    fid = ROBOT.frame_id(LOAD_FRAME)
    force, moment = rng.normal(size=(3, 6)) * 500.0, rng.normal(size=(3, 6)) * 50.0
    tau = chain.torque(state, force=force, moment=moment, frame_id=fid)
    jac = chain.jacobian(state, fid)
    for k in range(q.shape[1]):
        wrench = np.r_[force[:, k], moment[:, k]]
        np.testing.assert_allclose(tau[:, k], ROBOT.load_torque(q[:, k], wrench), rtol=0, atol=1e-9)
        np.testing.assert_allclose(chain.position(state, fid)[:, k], ROBOT.positions(q[:, k], [LOAD_FRAME])[0],
                                   rtol=0, atol=1e-12)
        np.testing.assert_allclose(jac[:, :, k], ROBOT.jacobians(q[:, k], [LOAD_FRAME])[0], rtol=0, atol=1e-12)


def test_compensate_writes_seven_joints_and_the_track_as_an_external_axis_in_mm(sim_static, tmp_path):
    cal = tmp_path / "cal.json"
    assert _cli("identify", "--robot", str(sim_static / "robot.toml"), "--static", str(sim_static / "static.csv"),
                "--out", str(cal)).returncode == 0
    q0 = np.array([2.0, 0.1, 0.3, -0.3, 0.2, 0.9, 0.1])
    lines = ["t," + ",".join(f"q{j}" for j in range(1, 8)) + ",fx,fy,fz,mx,my,mz"]
    for i in range(40):
        q = q0 + np.r_[0.01 * i, 0.002 * i, np.zeros(5)]
        lines.append(",".join(repr(float(v)) for v in [0.1 * i, *q, 0.0, 800.0, -1500.0, 0.0, 0.0, 0.0]))
    path = tmp_path / "path.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    done = _cli("compensate", "--robot", str(sim_static / "robot.toml"), "--calibration", str(cal), "--path",
                str(path), "--out", str(tmp_path / "out.csv"), "--krl", str(tmp_path / "p.src"), "--rapid",
                str(tmp_path / "p.mod"), "--validate", "--json")
    assert done.returncode == 0, done.stderr
    obj = json.loads(done.stdout)
    header = (tmp_path / "out.csv").read_text(encoding="utf-8").splitlines()[0].split(",")
    assert header[-10:-3] == [f"qc{j}" for j in range(1, 8)]
    out = np.loadtxt(tmp_path / "out.csv", delimiter=",", skiprows=1)
    qc1 = out[:, header.index("qc1")]
    krl = (tmp_path / "p.src").read_text(encoding="utf-8")
    move = next(line for line in krl.splitlines() if "PTP {E6AXIS" in line)
    assert f"E1 {qc1[0] * 1e3:.6f}" in move and "A6" in move and "A7" not in move
    rapid = (tmp_path / "p.mod").read_text(encoding="utf-8")
    assert f"],[{qc1[0] * 1e3:.6f},9E9" in rapid
    # the simulated cell (the same robot, the simulator's truth): compensation removes the deflection
    check = obj["validation"]
    assert check["uncompensated"]["max"] > 1e-3
    assert check["exact"]["max"] < 0.05 * check["uncompensated"]["max"]


def test_report_and_plan_of_the_track_robot(sim_static, tmp_path):
    done = _cli("report", "--robot", str(sim_static / "robot.toml"), "--static", str(sim_static / "static.csv"),
                "--out", str(tmp_path / "r.html"))
    assert done.returncode == 0, done.stderr
    html = (tmp_path / "r.html").read_text(encoding="utf-8")
    assert "k7" in html and "N/m" in html


# ------------------------------------------------------------------ statistics over seeds
N_SEEDS = 100


@pytest.mark.heavy
@pytest.mark.acceptance
def test_stiffness_and_registration_intervals_cover_the_truth_over_seeds():
    """100 seeds of the default experiment on the track cell: the 95 % intervals of k1..k7 and of
    the registration rx..tz cover the truth 95 +- 4 % of the time (pooled over the 13
    parameters; each parameter alone within 3 binomial sigma of 95 % at 100 seeds)."""
    truth = CellTruth.for_robot(ROBOT)
    tp = truth.parameters(ROBOT)
    names = K_NAMES + FRAME_NAMES
    z = []
    for seed in range(N_SEEDS):
        ds = build_dataset(simulate_static(ROBOT, truth, seed=20_000 + seed, plan=StaticPlan()))
        fit = identify_absolute(ROBOT, ds, model=("joint_stiffness", "tracker_frame"))
        got = {p.name: p for p in fit.parameters}
        z.append([(got[n].value - tp[n]["value"]) / got[n].std for n in names])
    covered = np.abs(np.array(z)) < 1.959964
    pooled, each = covered.mean(), covered.mean(axis=0)
    assert abs(pooled - 0.95) <= 0.04, (pooled, dict(zip(names, each)))
    assert np.all(each >= 0.95 - 3 * np.sqrt(0.95 * 0.05 / N_SEEDS)), dict(zip(names, each))


@pytest.mark.heavy
@pytest.mark.acceptance
def test_geometry_registration_and_stiffness_intervals_cover_the_truth_over_seeds():
    """100 seeds of the default experiment on the track cell built with errors in every DH parameter
    the fit knows (0.3 mm, 0.5 mrad; the carriage's dd1 moves nothing and has none, its dtheta1 is the
    frame's): the joint fit of
    springs, geometry and registration, each kinematic parameter against what it estimates (its own
    error plus what it absorbs, IdentifiableSet.base_value), k1..k7 against the truth. The 95 %
    intervals cover 95 +- 4 % of each group (measured: geometry 95.7 % of 2900, springs 95.6 % of 700;
    before the carriage's dtheta1 was drawn, geometry 95.7 %, mean z 0.02, sd 0.99, springs 95.4 %)."""
    import dataclasses

    from elastocal.identify import kinematics as kin

    base = CellTruth.for_robot(ROBOT)
    tp = base.parameters(ROBOT)
    names = [n for n in kin.parameter_names(ROBOT, ROBOT.marker_names) if n != "dd1"]
    geo, springs = [], []
    for seed in range(N_SEEDS):
        rng = np.random.default_rng(30_000 + seed)
        errors = tuple((n, float(rng.normal(0.0, 3e-4 if kin.unit_of(n, ROBOT) == "m" else 5e-4))) for n in names)
        truth = dataclasses.replace(base, kinematic_errors=errors)
        ds = build_dataset(simulate_static(ROBOT, truth, seed=30_000 + seed, plan=StaticPlan()))
        fit = identify_absolute(ROBOT, ds, model=("joint_stiffness", "kinematic_errors", "tracker_frame"))
        assert fit.rms <= 1.25 * fit.noise_floor, (seed, fit.rms, fit.noise_floor)
        values = dict(errors) | {f"c{j}": 1.0 / k for j, k in enumerate(truth.stiffness, start=1)}
        expected = fit.identifiable.base_value(values)
        geo += [abs(p.value - expected[p.name]) < 1.959964 * p.std for p in fit.parameters
                if p.name in fit.kinematic_names]
        springs += [abs(p.value - tp[p.name]["value"]) < 1.959964 * p.std for p in fit.parameters
                    if p.name in K_NAMES]
    assert 0.91 <= np.mean(geo) <= 0.99 and len(geo) > 20 * N_SEEDS, (np.mean(geo), len(geo))
    assert 0.91 <= np.mean(springs) <= 0.99, np.mean(springs)


#: the demo's loads on every pose (elastocal/commands/demo.py): two hung weights and one cable pull
DEMO_WRENCHES = np.array([[0.0, 0.0, -60.0 * 9.80665, 0, 0, 0], [0.0, 0.0, -110.0 * 9.80665, 0, 0, 0],
                          [650.0, -300.0, -400.0, 0, 0, 0]])
FULL_MODEL = ("joint_stiffness", "link_compliance", "kinematic_errors", "tracker_frame")


def _demo_like_fit(seed: int):
    """The seven-joint demo's absolute fit on the simulator's table of the demo's experiment (12 random
    poses, its three loads, link compliance and the as-built geometry hidden), without the CAN bus."""
    from elastocal.sims.static import random_poses

    truth = CellTruth.for_robot(ROBOT).with_hidden("link_compliance,kinematic_errors")
    poses = random_poses(ROBOT, 12, np.random.default_rng(seed))
    table = simulate_static(ROBOT, truth, seed=seed, poses=poses, wrenches=[DEMO_WRENCHES] * len(poses))
    return truth, identify_absolute(ROBOT, build_dataset(table), model=FULL_MODEL)


def _converged(seeds) -> list[str]:
    """The seeds whose joint fit of geometry, registration and link compliance did not reach the floor."""
    bad = []
    for seed in seeds:
        _, fit = _demo_like_fit(seed)
        # at the floor: the noise alone leaves fit.noise_floor; 1.3x is the demo's own criterion
        if not fit.rms <= 1.3 * fit.noise_floor:
            bad.append(f"seed {seed}: {fit.rms * 1e6:.1f} um rms, floor {fit.noise_floor * 1e6:.1f} um")
    return bad


def test_the_absolute_fit_with_link_compliance_reaches_the_floor_on_the_demos_experiment():
    """Seeds 3-5 ended at 0.3-0.8 mm (the floor 6 um) while the joint zero of the carriage, a length,
    was differentiated as a turn about its axis (the Gauss-Newton steps then went astray)."""
    assert _converged(range(3, 6)) == []


@pytest.mark.heavy
def test_the_absolute_fit_with_link_compliance_reaches_the_floor_over_20_seeds():
    assert _converged(range(20)) == []


@pytest.mark.heavy
def test_the_carriage_stiffness_of_the_joint_fit_is_unbiased_over_20_seeds():
    """k1 from the joint fit of springs and geometry (what the calibration and the demo hold): its z over
    20 seeds of the demo's experiment averages 0 within 3 / sqrt(20) and none is beyond 4 std. The
    deflection fit alone, on the drawing's geometry, gives it 2.3 std low on average (the arm's
    0.02-0.05 deg errors against the carriage's 15 um under the pull), so the demo reports this one."""
    truth = CellTruth.for_robot(ROBOT).with_hidden("link_compliance,kinematic_errors")
    k1 = truth.parameters(ROBOT)["k1"]["value"]
    z = []
    for seed in range(20):
        _, fit = _demo_like_fit(seed)
        p = fit.parameter("k1")
        z.append((p.value - k1) / p.std)
    assert abs(np.mean(z)) < 3 / np.sqrt(len(z)) and np.max(np.abs(z)) < 4.0, np.round(z, 1)


def _wrong_confident_stiffnesses(robot, seeds, fit_of) -> tuple[list[str], list[str]]:
    """(stiffnesses beyond 3.5 std of the truth and not marked, the marks) over ``seeds``."""
    wrong, marks = [], []
    for seed in seeds:
        truth, fit = fit_of(seed)
        tp = truth.parameters(robot)
        undetermined = fit.undetermined
        marked = fit.to_json()["parameters"]
        for name, why in undetermined.items():
            assert marked[name]["determined"] is False and why in marked[name]["note"]
            marks.append(f"seed {seed} {name}: {why}")
        for p in fit.parameters:
            if p.name.startswith("k") and p.name not in undetermined:
                z = (p.value - tp[p.name]["value"]) / p.std
                if abs(z) > 3.5:            # 3.5 std: beyond chance over 20 seeds x 7 stiffnesses
                    wrong.append(f"seed {seed} {p.name} {z:+.1f} std")
    return wrong, marks


@pytest.mark.heavy
def test_the_absolute_fit_gives_no_wrong_confident_stiffness_over_20_seeds():
    """With the demo's loads the data cannot tell the forearm's cl4y from the hand's cl5x or cl6x: the
    selection keeps one and the wrist's k6 follows the choice (9-14 std off in 4 of 12 seeds). Such a
    stiffness is marked not determined, naming the two components; every other one lies within 3.5 std
    of the truth over 20 seeds. Where the forearm's cl4y is no twin but is left out for its sign (below zero
    within noise, seed 6), k6 follows the values the data still allow it and is marked too."""
    wrong, marks = _wrong_confident_stiffnesses(ROBOT, range(20), _demo_like_fit)
    assert wrong == [], (wrong, marks)
    # the mark is there, and names the twins (k6 between the forearm and the hand in some seeds)
    assert any(" k6: " in m and "cl4" in m and ("cl5x" in m or "cl6x" in m) for m in marks), marks


def _six_joint_demo_like_fit(seed: int):
    """The six-joint demo's absolute fit on the simulator's table of the demo's experiment."""
    from elastocal.sims.static import random_poses

    robot = bundled_robot()
    truth = CellTruth.for_robot(robot).with_hidden("link_compliance,kinematic_errors")
    poses = random_poses(robot, 12, np.random.default_rng(seed))
    table = simulate_static(robot, truth, seed=seed, poses=poses, wrenches=[DEMO_WRENCHES] * len(poses))
    return truth, identify_absolute(robot, build_dataset(table), model=FULL_MODEL)


def test_no_twin_mark_where_the_data_determine_the_stiffnesses():
    """On the six-joint cell with the demo's loads every stiffness is within 3.5 std and none is marked:
    the mark is for a spring that follows an undecidable choice, not for every fit with link compliance."""
    wrong, marks = _wrong_confident_stiffnesses(bundled_robot(), range(4), _six_joint_demo_like_fit)
    assert wrong == [] and marks == [], (wrong, marks)


def test_a_spring_next_to_a_compliance_left_out_for_its_sign_is_marked_where_the_data_leave_it_open():
    """Seed 6 of the track cell: the forearm's cl4y comes out below zero within noise beside the kept components
    and the controls and is left out, and k6 (9 std from the truth) moves with it: its honest interval reaches
    about 26 times as far as the printed one, so k6 is marked and the note names both."""
    from elastocal.identify.selection import BOUND_REACH

    _, fit = _demo_like_fit(6)
    found = {a.spring: a for sel in fit.static.selections for a in sel.at_bound}
    assert "k6" in found and found["k6"].component == "cl4y" and found["k6"].reach > BOUND_REACH, found
    marked = fit.to_json()["parameters"]["k6"]
    assert marked["determined"] is False and "cl4y" in marked["note"] and "k6" in marked["note"], marked


def test_a_spring_whose_honest_interval_is_a_few_times_its_printed_one_is_not_marked():
    """Seed 1 of the six-joint cell with the demo's loads: the shoulder's cl1y (zero in the truth) comes out just
    below zero and k1's honest interval reaches about 7 times as far as its printed one: measured, and below
    BOUND_REACH, so k1 (0.3 std from its truth) is not marked."""
    from elastocal.identify.selection import BOUND_REACH, honest_reach

    _, fit = _six_joint_demo_like_fit(1)
    assert "k1" not in fit.undetermined and not any(a.spring == "k1" for sel in fit.static.selections
                                                    for a in sel.at_bound), fit.undetermined
    assert 1.0 < honest_reach(-0.09, 7.5, 0.991) < BOUND_REACH


@pytest.mark.heavy
@pytest.mark.acceptance
@pytest.mark.slow
def test_the_demo_chain_runs_on_the_track_cell(tmp_path):
    """`elastocal demo --robot hh150_track`: seven simulated drives on the CAN bus, the guided procedure
    through the real drivers, identification from the log, diagnosis, the absolute calibration and the
    compensated path on the simulated cell."""
    out = tmp_path / "demo"
    done = _cli("demo", "--robot", "hh150_track", "--seed", "2", "--out", str(out))
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((out / "demo.json").read_text())
    assert summary["procedure"]["status"] == "completed" and summary["procedure"]["steps"] == 12
    assert len(summary["stiffness_error_percent"]) == 7
    assert summary["verdict"] == "link_compliance"
    assert summary["rms_after"] <= 1.3 * summary["noise_floor"]
    krl = (out / "compensated.src").read_text(encoding="utf-8")
    assert "E6AXIS" in krl and " E1 " in krl
    comp = summary["compensation"]
    assert comp["exact"]["max"] < 0.2 * comp["uncompensated"]["max"]
    absolute = summary["absolute"]
    # the joint fit of geometry, registration and link compliance reaches the floor (it ended at 0.8 mm in
    # half the runs while the carriage's zero was differentiated as a turn), and with the geometry found
    # compensation removes the process-load error as on the six-axis cell
    assert absolute["rms_after"] <= 1.3 * absolute["noise_floor"], absolute
    assert comp["exact"]["max"] < 0.05 * comp["uncompensated"]["max"]


def test_plan_for_the_track_robot_gives_seven_joint_poses_and_every_stiffness(tmp_path):
    out = tmp_path / "plan.toml"
    done = _cli("plan", "--robot", str(bundled_robot_path_of("hh150_track")), "--test-pose", "3,0,0.5,-0.5,0,-1.2,0",
                "--wrench", "0,0,-1500", "--poses", "8", "--candidates", "300", "--out", str(out), "--json")
    assert done.returncode == 0, done.stderr
    obj = json.loads(done.stdout)
    assert all(len(q) == 7 for q in obj["poses"].values())
    from elastocal.formats.plan import load_plan

    plan = load_plan(out)
    plan.validate_for(ROBOT)
    assert len(plan.static.poses[0].q) == 7
    # wrong N on the command line: one line naming the flag
    bad = _cli("plan", "--robot", str(bundled_robot_path_of("hh150_track")), "--test-pose", "0,0.5,-0.5,0,-1.2,0",
               "--wrench", "0,0,-1500", "--out", str(tmp_path / "bad.toml"))
    assert bad.returncode == 2 and "--test-pose" in bad.stderr and "expected 7" in bad.stderr


def bundled_robot_path_of(name: str):
    from elastocal.formats.robot_toml import bundled_robot_path

    return bundled_robot_path(name)
