"""The guided procedure on a simulated cell's own clock (acquisition/lockstep.py): the procedure
and the simulated devices share one simulated clock, so one seed gives one log, times included."""

from dataclasses import replace

import numpy as np
import pytest

from elastocal.acquisition.export import load_log
from elastocal.acquisition.lockstep import AIM_TICK_NS, LockstepCellIO, run_lockstep_calibration
from elastocal.commands._cell import lockstep_world
from two_pose_plan import two_pose_plan
from elastocal.formats.plan import LoadSpec, parse_plan, plan_toml
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.config import sim_config
from elastocal.sims.serve import example_cell_config
from elastocal.sims.world import SimClock, SimWorld


def _config(seed=7, hidden="kinematic_errors"):
    config = example_cell_config(move_speed_rad_s=2.0, seed=seed, hidden=hidden)
    return replace(config, drives=tuple(replace(d, rate_hz=200.0) for d in config.drives))


def _io(config):
    world, clock = lockstep_world(config)
    return LockstepCellIO(config.load_robot(), config, world, clock), clock, world


def test_the_clock_moves_only_when_the_procedure_waits_and_devices_sample_on_their_grids():
    config = _config()
    io, clock, world = _io(config)
    io.start()
    t0 = clock.now_ns()
    assert io.clock() == world.now_ns() == t0
    samples = io.poll(["R1"], 0.1)
    assert clock.now_ns() == world.now_ns() == t0 + 100_000_000
    # 200 Hz drives: 20 instants in (t0, t0 + 0.1 s], each with all six joints; 100 Hz tracker: 10
    times = sorted({d.t_ns for d in samples.drives})
    assert times == [t0 + 5_000_000 * k for k in range(1, 21)]
    assert len(samples.drives) == 6 * 20
    assert [s.t_ns for s in samples.tracker] == [t0 + 10_000_000 * k for k in range(1, 11)]
    assert {s.marker for s in samples.tracker} == {"R1"}
    # nothing happens between polls: the clock stands still however long this computer takes
    assert clock.now_ns() == t0 + 100_000_000
    # an aim opens a new reading a tick later: samples of the window after it are of that reading only
    io.begin_reading("R2")
    assert clock.now_ns() == t0 + 100_000_000 + AIM_TICK_NS
    reading = io.poll(["R2"], 0.03)
    first = reading.drives[0]
    assert all(d.current_a == next(e.current_a for e in reading.drives if e.joint == d.joint)
               for d in reading.drives)          # at rest, one noise draw per reading
    assert first.current_a != next(d.current_a for d in samples.drives if d.joint == first.joint)
    # a move takes the simulated time its length at the controller's speed asks for
    q = np.array(world.q_now()) + 0.2
    io.start_move(q, 1.0)
    assert not io.move_done() and io.motion_reported()
    io.poll([], 0.2 / 2.0 + 0.005)
    assert io.move_done() and io.motion_reported() is None


def test_the_world_must_run_on_the_lockstep_clock():
    config = _config()
    robot = config.load_robot()
    world = SimWorld.from_config(robot, sim_config(config), config.tracker.markers)       # this computer's clock
    with pytest.raises(ValueError, match="lockstep clock"):
        LockstepCellIO(robot, config, world, SimClock())


def test_two_procedures_with_one_seed_write_one_table_times_included(tmp_path):
    """With the devices on the wall clock (calibrate --sim) the readings' times, and whatever is
    fitted against them, differed between runs; in lockstep every reading has the same window."""
    robot = bundled_robot()
    plan = two_pose_plan(robot)
    tables = []
    for k in range(2):
        log = tmp_path / f"run{k}.mcap"
        config = _config(hidden="kinematic_errors,thermal_drift")
        world, clock = lockstep_world(config)
        outcome = run_lockstep_calibration(config, plan, log, world=world, clock=clock)
        assert outcome.status == "completed" and outcome.steps_done == 2
        robot_log, table, _ = load_log(log)
        tables.append(table)
    a, b = tables
    assert len(a.pose) == 2 * 2 * 2 * 2
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.currents, b.currents)
    assert np.all(np.diff(a.t) > 0)
    # noisy all the same: repeats of one marker differ by the tracker's noise, not by nothing
    first = (a.marker == "R1") & (a.pose == a.pose[0]) & (a.load == a.load[0])
    assert first.sum() == 2 and 1e-6 < np.linalg.norm(np.diff(a.xyz[first], axis=0)) < 1e-4
    # the hidden drift moves the markers with the simulated time, the same in both runs
    assert a.t[-1] - a.t[0] > 1.0


def test_a_real_cell_is_refused(tmp_path):
    from elastocal.errors import InputError

    config = replace(_config(), sim={})
    plan = parse_plan(plan_toml(poses=[(0.1, 0.3, -0.4, 0.2, 1.0, 0.1)], loads=(LoadSpec("L1", mass_kg=50.0),), markers=("R1",), repeats=1,
                                reading_s=0.03))
    with pytest.raises(InputError, match="simulated cell only"):
        run_lockstep_calibration(config, plan, tmp_path / "x.mcap", world=None, clock=None)
    assert not (tmp_path / "x.mcap").exists()
