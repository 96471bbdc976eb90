"""Design of experiments (design/search.py, `elastocal plan`): the industry
measure K40 (Klimchik §V.C), the planned experiment against random poses on
the simulated cell, the workspace constraints, Yang's first-order map."""

import json
import math

import numpy as np
import pytest

from elastocal.formats.plan import load_plan
from elastocal.cli import main
from elastocal.errors import InputError
from elastocal.design import search as dz
from elastocal.sims import first_order_map as fom
from elastocal.design import candidates as dzc
from elastocal.model.robot import LOAD_FRAME
from elastocal.identify.static import identify_static
from elastocal.formats.tables import static_table_from_arrays
from elastocal.sims.cell import CellTruth, SimCell
from elastocal.sims.static import StaticPlan, simulate_static
from elastocal.model.kinds import KinematicForm, TorqueSource

TEST = dz.TestPose(q=(0.3, 0.5, -0.3, 0.2, 1.0, 0.1), wrench=(800.0, -300.0, -600.0, 0.0, 0.0, 0.0))
TRACKER = (3.5, 0.0, 1.2)
F_MAX = 1100.0
TRUTH = CellTruth()
#: a rough prior: the true stiffness off by up to 30 %
PRIOR = tuple(TRUTH.stiffness * np.array([1.3, 0.8, 1.2, 0.7, 1.3, 0.8]))


@pytest.fixture(scope="module")
def workspace():
    return dz.Workspace(f_max_n=F_MAX, base_p_tracker=TRACKER)


def actual_error(robot, q, wrenches, seed):
    """Actual positioning error at the test pose after identifying k on the
    simulated cell: |A0 (c_identified - c_true)|."""
    table = simulate_static(robot, TRUTH, seed=seed, plan=StaticPlan(n_poses=len(q), n_loads=wrenches.shape[1]),
                            poses=q, wrenches=list(wrenches))
    fit = identify_static(robot, table)
    c = 1.0 / fit.values([f"k{j}" for j in range(1, 7)])
    return float(np.linalg.norm(dz.a0_matrix(robot, TEST) @ (c - 1.0 / TRUTH.stiffness)))


def test_planned_experiment_beats_random_poses_over_ten_seeds(robot, workspace):
    """Acceptance: 12 planned poses identify k with a smaller predicted and
    actual error at the test pose than 12 random reachable poses under the
    same loads, over 10 seeds."""
    markers = robot.marker_names
    pred_plan, pred_rand, act_plan, act_rand = [], [], [], []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        cand = dzc.sample_candidates(robot, 300, rng, workspace, markers)
        design = dz.plan_experiment(robot, cand, TEST, n_poses=12, loads_per_pose=2, workspace=workspace,
                                    markers=markers, prior_stiffness=PRIOR)
        # the plan respects the workspace and |F| <= F_max
        assert np.all(dzc.check_poses(robot, design.q, workspace, markers) == -1)
        assert np.all(design.q >= robot.lower) and np.all(design.q <= robot.upper)
        assert np.allclose(np.linalg.norm(design.forces, axis=1), F_MAX)
        random_q = cand.q[rng.choice(len(cand.q), 12, replace=False)]
        pred_plan.append(design.quality.accuracy_m)
        pred_rand.append(dz.evaluate_design(robot, random_q, list(design.wrenches), TEST, markers,
                                            prior_stiffness=PRIOR).accuracy_m)
        act_plan.append(actual_error(robot, design.q, design.wrenches, 1000 + seed))
        act_rand.append(actual_error(robot, random_q, design.wrenches, 2000 + seed))
    pred_plan, pred_rand = np.array(pred_plan), np.array(pred_rand)
    act_plan, act_rand = np.array(act_plan), np.array(act_rand)
    assert np.all(pred_plan < 0.8 * pred_rand), (pred_plan, pred_rand)
    rms_plan, rms_rand = np.sqrt(np.mean(act_plan ** 2)), np.sqrt(np.mean(act_rand ** 2))
    assert rms_plan < 0.8 * rms_rand, (act_plan, act_rand)
    assert np.sum(act_plan < act_rand) >= 7, (act_plan, act_rand)
    # the prediction is honest: the actual rms is near the predicted one
    assert 0.6 < rms_plan / np.sqrt(np.mean(pred_plan ** 2)) < 1.6


def test_k40_is_klimchiks_trace_and_ignores_units(robot):
    """K40 = trace(A0 (sum A_i^T A_i)^-1 A0^T) with A_i = J_p diag(J_f^T F_i) (K31, K40),
    built here from Pinocchio Jacobians of the load point, independent of
    the compliance scaling the search uses."""
    rng = np.random.default_rng(4)
    q = rng.uniform([-1, 0, -1, -1, 0.5, -1], [1, 1, 0, 1, 1.5, 1], size=(8, 6))
    forces = rng.normal(size=(8, 3)) * 500.0
    info = np.zeros((6, 6))
    for qi, f in zip(q, forces):
        jac = robot.jacobians(robot.theta(qi), [LOAD_FRAME])[0]
        a_i = jac[:3] @ np.diag(jac.T @ np.concatenate([f, np.zeros(3)]))
        info += a_i.T @ a_i
    jac0 = robot.jacobians(robot.theta(np.array(TEST.q)), [LOAD_FRAME])[0]
    a0 = jac0[:3] @ np.diag(jac0.T @ np.array(TEST.wrench))
    direct = np.trace(a0 @ np.linalg.inv(info) @ a0.T)
    assert dz.industry_measure(info, a0) == pytest.approx(direct, rel=1e-9)
    assert np.allclose(dz.a0_matrix(robot, TEST), a0)
    s = np.diag([2.0, 0.5, 3.0, 10.0, 0.1, 7.0])      # compliances in other units
    assert dz.industry_measure(s @ info @ s, a0 @ s) == pytest.approx(direct, rel=1e-9)


def test_predicted_accuracy_matches_monte_carlo(robot, workspace):
    """evaluate_design's accuracy (tracker and current noise, shared references)
    against 40 simulated calibrations of the same experiment."""
    cand = dzc.sample_candidates(robot, 200, np.random.default_rng(7), workspace, robot.marker_names)
    design = dz.plan_experiment(robot, cand, TEST, n_poses=8, loads_per_pose=2, workspace=workspace,
                                markers=robot.marker_names, prior_stiffness=TRUTH.stiffness)
    errors = [actual_error(robot, design.q, design.wrenches, 300 + s) for s in range(40)]
    mc = float(np.sqrt(np.mean(np.square(errors))))
    assert mc == pytest.approx(design.quality.accuracy_m, rel=0.3)


def test_hung_weights_cannot_serve_a_sideways_process_load(robot):
    """Vertical loads never load joint 1 (Y §3): K40 is infinite when the
    test load needs k1, finite when it is vertical too; k1 is unidentifiable."""
    ws = dz.Workspace(f_max_n=F_MAX, directions="down")
    cand = dzc.sample_candidates(robot, 150, np.random.default_rng(2), ws, robot.marker_names)
    sideways = dz.plan_experiment(robot, cand, TEST, n_poses=6, loads_per_pose=1, workspace=ws,
                                  markers=robot.marker_names)
    assert math.isinf(sideways.quality.k40) and math.isinf(sideways.quality.accuracy_m)
    assert math.isinf(sideways.quality.stiffness_rel_std[0])
    assert np.allclose(sideways.forces, [[0.0, 0.0, -F_MAX]])
    vertical = dz.TestPose(q=TEST.q, wrench=(0.0, 0.0, -900.0, 0.0, 0.0, 0.0))
    down = dz.plan_experiment(robot, cand, vertical, n_poses=6, loads_per_pose=1, workspace=ws,
                              markers=robot.marker_names)
    assert math.isfinite(down.quality.k40) and down.quality.accuracy_m < 20e-6


def test_load_directions_pull_down_or_sideways_once_each(robot):
    dirs = dz.load_directions("any", robot.gravity)
    assert dirs.shape == (13, 3)
    assert np.allclose(dirs[0], [0.0, 0.0, -1.0])
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert np.all(dirs[:, 2] <= 1e-12)                       # nothing pulls upwards
    cos = np.abs(dirs @ dirs.T) - np.eye(13)
    assert np.max(cos) < 1.0 - 1e-9                          # no two parallel (F and -F inform alike)
    assert dz.load_directions("down", robot.gravity).shape == (1, 3)


def _point_segment(x, a, b):
    t = np.clip(((x - a) @ (b - a)) / max(float((b - a) @ (b - a)), 1e-300), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[:, None] * (b - a)), axis=1)


def _clearance(p, a, b):
    """Distance from segment p0-p1 to segment a-b: a grid along p0-p1, refined
    around its best point (independent of the library's closed form)."""
    s = np.linspace(0.0, 1.0, 201)
    d = _point_segment(p[0] + s[:, None] * (p[1] - p[0]), a, b)
    k = int(np.argmin(d))
    fine = np.linspace(s[max(k - 1, 0)], s[min(k + 1, 200)], 401)
    return float(np.min(_point_segment(p[0] + fine[:, None] * (p[1] - p[0]), a, b)))


def test_candidates_keep_the_markers_in_sight(robot, workspace):
    import pinocchio as pin

    cand = dzc.sample_candidates(robot, 20, np.random.default_rng(3), workspace, robot.marker_names)
    assert len(cand.q) == 20 and cand.accepted >= 20
    assert sum(n for _, n in cand.rejected) + cand.accepted == cand.sampled
    tracker = np.array(TRACKER)
    data = robot.model.createData()
    for q in cand.q:
        pin.forwardKinematics(robot.model, data, robot.theta(q))
        pts = [np.zeros(3)] + [data.oMi[j].translation.copy() for j in range(1, 7)]
        markers = robot.positions(robot.theta(q), robot.marker_names)
        load = robot.positions(robot.theta(q), [LOAD_FRAME])[0]
        assert load[2] >= workspace.min_height_m and math.hypot(load[0], load[1]) >= workspace.min_radius_m
        for m in markers:
            for a, b in zip(pts[:-1], pts[1:]):
                if _point_segment(m[None, :], a, b)[0] < workspace.link_radius_m + 0.05:
                    continue          # the marker's own link
                assert _clearance((tracker, m), a, b) >= workspace.link_radius_m - 1e-4
    # behind the robot's base column the tracker sees nothing: everything rejected as hidden
    blind = dz.Workspace(f_max_n=F_MAX, base_p_tracker=(0.0, 0.0, 0.3), link_radius_m=0.4)
    code = dzc.check_poses(robot, cand.q, blind, robot.marker_names)
    assert np.all(code == dzc.REJECTIONS.index("markers hidden"))
    with pytest.raises(InputError, match="^candidates: "):
        dzc.sample_candidates(robot, 5, np.random.default_rng(0), blind, robot.marker_names, max_sampled=200)


def test_first_order_map_agrees_with_identify_static(robot):
    """A map cell is the first-order identification of noise-free exact
    deflections: identify_static(form=first-order) on the same simulated
    readings gives the same stiffness. A singular wrist is never good."""
    w = F_MAX / math.sqrt(3.0) * np.array([1.0, 1.0, -1.0, 0.0, 0.0, 0.0])
    k = np.array(dz.DEFAULT_PRIOR_STIFFNESS)
    fmap = fom.first_order_map(robot, q_base=TEST.q, wrench=w, stiffness=k, n_grid=4)
    assert fmap.stiffness_error.shape == (4, 4, 6) and fmap.good.shape == (4, 4)
    a, b = 1, 2
    q = np.array(TEST.q)
    q[1], q[2] = fmap.q2[b], fmap.q3[a]
    cell = SimCell(robot, CellTruth(stiffness=k, compensator=(4771.4, 0.9112), tracker_noise_m=0.0,
                                    current_noise_a=0.0))
    eq0 = cell.equilibrium(q)
    eq1 = cell.equilibrium(q, w, reference=eq0)
    rows = {k_: [] for k_ in ("pose", "load", "q", "wrench", "currents", "marker", "xyz")}
    for load, eq, wr in (("0", eq0, np.zeros(6)), ("1", eq1, w)):
        for m in robot.marker_names:
            for _ in range(2):
                rows["pose"].append("1")
                rows["load"].append(load)
                rows["q"].append(q)
                rows["wrench"].append(wr)
                rows["currents"].append(cell.currents(eq))
                rows["marker"].append(m)
                rows["xyz"].append(cell.marker_positions(eq, [m])[0])
    table = static_table_from_arrays(**rows)
    fit = identify_static(robot, table, form=KinematicForm.FIRST_ORDER, torque=TorqueSource.CURRENT)
    k_id = fit.values([f"k{j}" for j in range(1, 7)])
    assert np.allclose(np.abs(k_id - k) / k, fmap.stiffness_error[a, b], rtol=1e-4, atol=1e-7)
    assert fmap.good_fraction > 0.5
    # with the wrist stretched (q5 = 0) joints 4 and 6 turn about one axis: nowhere good
    stretched = fom.first_order_map(robot, q_base=(0.3, 0.5, -0.3, 0.2, 0.0, 0.1), wrench=w, stiffness=k, n_grid=4)
    assert stretched.good_fraction == 0.0


def test_map_plot_is_png_or_svg(robot, tmp_path):
    fmap = fom.first_order_map(robot, q_base=TEST.q, wrench=(500.0, 500.0, -500.0, 0, 0, 0), n_grid=3)
    fom.plot_first_order_map(fmap, tmp_path / "m.png", test_q=TEST.q, poses=np.array([TEST.q]))
    fom.plot_first_order_map(fmap, tmp_path / "m.svg", test_q=TEST.q)
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<svg" in (tmp_path / "m.svg").read_text()
    with pytest.raises(InputError, match=r"\.png or \.svg"):
        fom.plot_first_order_map(fmap, tmp_path / "m.pdf")


def test_plan_command_writes_a_plan_the_procedures_read(robot, tmp_path, capsys):
    out = tmp_path / "plan.toml"
    args = ["plan", "--robot", str(tmp_path / "robot.toml"), "--test-pose", ",".join(map(str, TEST.q)),
            "--load", "800,-300,-600", "--f-max", str(F_MAX), "--tracker-position", "3.5,0,1.2",
            "--candidates", "250", "--check-poses", "3", "--map", str(tmp_path / "map.svg"), "--map-grid", "3",
            "--friction-path=-0.3,0.2,-0.5,-0.3,0.6,-0.2;0.3,0.5,-0.2,0.3,0.9,0.3", "--out", str(out), "--json"]
    (tmp_path / "robot.toml").write_text(robot.to_toml())
    assert main(args) == 0
    obj = json.loads(capsys.readouterr().out)
    plan = load_plan(out)
    plan.validate_for(robot)
    assert len(plan.static.poses) == 12 and plan.static.markers == robot.marker_names
    for spec in plan.loads:
        assert np.linalg.norm(spec.wrench(robot.gravity)[:3]) == pytest.approx(F_MAX)
    assert len(plan.check.poses) == 3 and plan.check.load in [s.id for s in plan.loads]
    assert plan.check.friction == "F1" and plan.procedures == ("static", "friction")
    assert obj["k40"] < obj["k40_random_median"]
    assert obj["accuracy"]["value"] < obj["accuracy_random"]["value"]
    assert obj["visibility_checked"] and obj["map"]["path"].endswith("map.svg")
    assert (tmp_path / "map.svg").exists()
    # the same plan file again: refused without --force
    assert main(args) == 2
    assert "already exists" in capsys.readouterr().err


def test_plan_command_rejects_bad_input_in_one_line(tmp_path, capsys):
    base = ["plan", "--robot", "hh150-does-not-exist.toml", "--load", "800,0,0", "--out", str(tmp_path / "p.toml")]
    assert main(base + ["--test-pose", "0.3,0.5,-0.3,0.2,1.0,0.1"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    from elastocal.formats.robot_toml import bundled_robot_path

    good = ["plan", "--robot", str(bundled_robot_path()), "--out", str(tmp_path / "p.toml")]
    assert main(good + ["--test-pose", "0.3,2.5,-0.3,0.2,1.0,0.1", "--load", "800,0,0"]) == 2
    err = capsys.readouterr().err
    assert "--test-pose" in err and "q2" in err and err.count("\n") == 1
    assert main(good + ["--test-pose", "0.3,0.5,-0.3", "--load", "800,0,0"]) == 2
    assert "expected 6" in capsys.readouterr().err
    assert main(good + ["--test-pose", "0.3,0.5,-0.3,0.2,1.0,0.1", "--load", "0,0,0"]) == 2
    assert "zero" in capsys.readouterr().err
