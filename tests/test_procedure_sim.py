"""The guided procedure against the simulated devices (CANopen drives on a
virtual CAN bus, the tracker over TCP, the Modbus cell controller), through
the real drivers: interrupted by the operator, resumed from the command line
with --sim --yes, and identified from the log within the core tolerances."""

import json

import numpy as np
import pytest

from elastocal.acquisition.export import load_log
from elastocal.acquisition.logreader import read_log
from two_pose_plan import two_pose_plan
from elastocal.formats.plan import LoadSpec, SettleSpec, parse_plan, plan_toml
from elastocal.acquisition.procedures import run_calibration
from elastocal.acquisition.ui import Aborted, AutoUI
from elastocal.cli import main
from elastocal.formats.robot_toml import bundled_robot
from elastocal.identify.static import identify_static
from elastocal.sims.cell import CellTruth
from elastocal.sims.serve import SimulatedCell, example_cell_config
from elastocal.sims.static import random_poses
from elastocal.model.kinds import KinematicForm, TorqueSource

#: these tests run simulated devices in wall-clock time (tests/conftest.py)
pytestmark = pytest.mark.slow


class AbortAt(AutoUI):
    def __init__(self, n):
        super().__init__(quiet=True)
        self.n = n

    def confirm(self, text):
        super().confirm(text)
        if len(self.prompts) == self.n:
            raise Aborted(f"aborted by the operator at: {text}")
        return "yes"


def test_static_procedure_on_simulated_devices_interrupted_resumed_and_identified(tmp_path, capsys):
    robot = bundled_robot()
    poses = random_poses(robot, 4, np.random.default_rng(3))
    loads = (LoadSpec("L1", mass_kg=110.0), LoadSpec("L2", force_n=(650.0, -300.0, -400.0)))
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(plan_toml(poses=poses, loads=loads, markers=("R1", "R2", "R3"), repeats=2, reading_s=0.05,
                                   settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=10.0)))
    plan = parse_plan(plan_path.read_text(), source=str(plan_path))
    config = example_cell_config(can_channel="issue4-proc-a", move_speed_rad_s=2.0)

    # the operator aborts while hanging the first load at pose P3
    first = tmp_path / "first.mcap"
    with SimulatedCell(config) as sim:
        out = run_calibration(sim.config, plan, first, yes=True, ui=AbortAt(1 + 3 * 2 + 2), world=sim.world)
    assert out.status == "aborted" and out.steps_done == 2
    contents = read_log(first)
    assert contents.complete and contents.completed_steps == ("static/P1", "static/P2")
    assert contents.cell.text == sim.config.to_toml()      # the served cell, its ports resolved
    assert sum(len(d.t_ns) for d in contents.drives) > 1000 and set(contents.markers) == {"R1", "R2", "R3"}
    # drive samples carry the SYNC time they were latched at: one monotonic clock with the events
    t_events = [e["t_ns"] for e in contents.events]
    assert min(t_events) < contents.drives[0].t_ns[len(contents.drives[0].t_ns) // 2] < max(t_events)

    # resumed from the command line on a fresh simulated cell, prompts answered by --yes
    cell_path = tmp_path / "cell.toml"
    cell_path.write_text(example_cell_config(can_channel="issue4-proc-b", move_speed_rad_s=2.0).to_toml())
    second = tmp_path / "second.mcap"
    rc = main(["calibrate", "--cell", str(cell_path), "--out", str(second),      # the plan: the log's
               "--resume", str(first), "--sim", "--yes", "--json"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    obj = json.loads(captured.out)
    assert obj == {"log": str(second), "status": "completed", "steps": 4, "steps_done": 4, "steps_resumed": 2,
                   "duration_s": obj["duration_s"]}

    log_robot, static, runs = load_log(second)
    assert runs is None and sorted(set(static.pose)) == ["P1", "P2", "P3", "P4"]
    fit = identify_static(log_robot, static, torque=TorqueSource.CURRENT, form=KinematicForm.EXACT)
    truth = np.array(CellTruth().stiffness)
    err = np.abs(fit.values([f"k{j}" for j in range(1, 7)]) - truth) / truth
    assert np.all(err[:3] < 0.02), err
    assert np.all(err[3:] < 0.05), err
    # 4 poses and 2 repeats estimate the floor itself to about 15 %: the core design's 1.15x is checked on
    # the virtual cell (test_procedure.py); here the residual must still be noise, not a model error
    assert fit.noise_floor is not None and fit.rms <= 1.5 * fit.noise_floor, (fit.rms, fit.noise_floor)


def test_calibrate_cli_refuses_yes_on_a_real_cell_and_bad_inputs(tmp_path, capsys):
    cell = tmp_path / "cell.toml"
    cell.write_text(example_cell_config(can_channel="issue4-proc-c").to_toml())
    plan = tmp_path / "plan.toml"
    plan.write_text(plan_toml(poses=[(0.1, 0.3, -0.4, 0.2, 1.0, 0.1)], loads=(LoadSpec("L1", mass_kg=50.0),),
                              markers=("R1",)))
    cases = [
        (["--yes"], "--yes: --yes answers the prompts of simulated devices only"),
        (["--sim", "--yes", "--procedure", "static,spin"], "unknown procedure 'spin'"),
        (["--sim", "--yes", "--procedure", "sweep"], "procedure 'sweep' is not in the plan"),
        (["--sim", "--yes", "--resume", str(tmp_path / "none.mcap")], "cannot read"),
    ]
    for extra, message in cases:
        rc = main(["calibrate", "--cell", str(cell), "--plan", str(plan), "--out", str(tmp_path / "x.mcap"),
                   *extra])
        err = capsys.readouterr().err
        assert rc == 2 and message in err and err.count("\n") == 1, err
    # no --plan: the cell config names none
    rc = main(["calibrate", "--cell", str(cell), "--out", str(tmp_path / "x.mcap"), "--sim", "--yes"])
    err = capsys.readouterr().err
    assert rc == 2 and "--plan: no plan: give --plan plan.toml or name one in [cell]" in err, err
    # ... or names one, next to it
    from elastocal.commands.calibrate import resolve_plan
    from elastocal.drivers.config import load_cell_config

    cell.write_text(cell.read_text().replace("[cell]\n", '[cell]\nplan = "plan.toml"\n', 1))
    resolved = resolve_plan(None, load_cell_config(cell), None)
    assert resolved.sha256 == parse_plan(plan.read_text(), source="x").sha256
    (tmp_path / "exists.mcap").write_bytes(b"")
    rc = main(["calibrate", "--cell", str(cell), "--plan", str(plan), "--out", str(tmp_path / "exists.mcap"),
               "--sim", "--yes"])
    assert rc == 2 and "already exists" in capsys.readouterr().err


def test_friction_pair_and_sweep_run_as_taught_paths_on_simulated_devices(tmp_path):
    from dataclasses import replace

    from elastocal.formats.plan import FrictionSpec, SweepSpec
    from elastocal.drivers.config import PathSpec

    u, v = (0.1, 0.3, -0.4, 0.0, 0.6, 0.0), (0.25, 0.4, -0.35, 0.05, 0.65, 0.05)
    w0 = (0.0, 0.2, -0.5, 0.0, 0.5, 0.0)
    w1 = (0.0, 0.45, -0.5, 0.0, 0.5, 0.0)
    config = example_cell_config(can_channel="issue4-proc-d", move_speed_rad_s=2.0)
    config = replace(config, controller=replace(config.controller, paths=(PathSpec(1, u, v, 0.1),
                                                                          PathSpec(2, w0, w1, 0.1))))
    plan = parse_plan(plan_toml(poses=[], loads=(LoadSpec("L1", mass_kg=80.0),), markers=(),
                                friction=(FrictionSpec("F1", start=u, end=v, speeds_rad_s=(0.1,), loads=("L1",),
                                                       marker="R1"),),
                                sweep=SweepSpec(q=w0, q2_from=0.2, q2_to=0.45, speed_rad_s=0.25),
                                settle=SettleSpec(spread_m=20e-6, window_s=0.15, timeout_s=10.0)))
    log = tmp_path / "runs.mcap"
    with SimulatedCell(config) as sim:
        assert run_calibration(sim.config, plan, log, yes=True, world=sim.world).status == "completed"
    robot, static, runs = load_log(log)
    assert static is None
    assert list(dict.fromkeys(runs.run)) == ["F1-1-UV", "F1-1-VU", "sweep-1+", "sweep-1-"]
    uv, vu = runs.run == "F1-1-UV", runs.run == "F1-1-VU"
    assert runs.q[uv][0, 0] == pytest.approx(0.1, abs=2e-3) and runs.q[uv][-1, 0] == pytest.approx(0.25, abs=2e-3)
    assert runs.q[vu][0, 0] == pytest.approx(0.25, abs=2e-3) and runs.q[vu][-1, 0] == pytest.approx(0.1, abs=2e-3)
    assert np.all(runs.load[uv | vu] == "L1") and np.allclose(runs.wrench[uv][:, 2], -80.0 * 9.81)
    assert (runs.marker[uv] == "R1").mean() > 0.02      # the tracker (100 Hz) follows R1 during the runs
    # the drive supplies friction in the direction of motion: joint 1 turns positive on UV, so
    # its current is larger forward than backward at mid-path (docs/physics.md)
    xi1 = robot.torque_constants[0]
    mid = lambda rows: np.abs(runs.q[rows][:, 0] - 0.175) < 0.03  # noqa: E731
    f1 = xi1 * (runs.currents[uv][mid(uv), 0].mean() - runs.currents[vu][mid(vu), 0].mean()) / 2
    assert 40.0 < f1 < 200.0   # Coulomb 40 N·m plus viscous and load-dependent parts (sim defaults)
    plus, minus = runs.run == "sweep-1+", runs.run == "sweep-1-"
    assert np.ptp(runs.q[plus][:, 1]) == pytest.approx(0.25, abs=3e-3) and np.ptp(runs.q[plus][:, 0]) < 1e-6
    assert set(runs.direction[plus | minus]) == {"+", "-"}


def test_static_procedure_reads_the_same_numbers_twice_with_one_seed(tmp_path):
    """The simulated devices draw each reading's noise once, from the seed and the reading's index
    (sims/world.py), and every reading starts with the tracker's aim (DriverCellIO.begin_reading):
    however many samples the wall clock lets into a window, and however busy the machine, two runs
    of one plan on one seed give one static table. (With noise drawn per sample, the means differ by
    the noise over a few samples: micrometres, not the last bit.)"""
    from dataclasses import replace

    robot = bundled_robot()
    plan = two_pose_plan(robot)
    tables = []
    for k in range(2):
        config = example_cell_config(can_channel=f"repeat-{k}", move_speed_rad_s=2.0, seed=7)
        config = replace(config, drives=tuple(replace(d, rate_hz=200.0) for d in config.drives))
        log = tmp_path / f"run{k}.mcap"
        with SimulatedCell(config) as sim:
            assert run_calibration(sim.config, plan, log, yes=True, world=sim.world).status == "completed"
        tables.append(load_log(log)[1])
    a, b = tables
    assert len(a.pose) == len(b.pose) == 2 * 2 * 2 * 2
    assert list(a.pose) == list(b.pose) and list(a.marker) == list(b.marker)
    # means of identical samples: equal to the last bits (a count of 2 or 3 may round differently)
    np.testing.assert_allclose(a.xyz, b.xyz, rtol=1e-13, atol=0)
    np.testing.assert_allclose(a.currents, b.currents, rtol=1e-12, atol=1e-15)
    # and yet noisy: repeats of one marker differ by the tracker's noise (10 µm), not by nothing
    first = (a.marker == "R1") & (a.pose == a.pose[0]) & (a.load == a.load[0])
    assert first.sum() == 2 and 1e-6 < np.linalg.norm(np.diff(a.xyz[first], axis=0)) < 1e-4
