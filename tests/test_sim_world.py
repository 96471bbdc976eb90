"""The simulated world: motion at finite speed, loads, and readings consistent with SimCell."""

from __future__ import annotations

import numpy as np
import pytest

from elastocal.sims.config import SimConfig
from elastocal.errors import InputError
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.world import SimWorld

START = (0.0, 0.2, -0.4, 0.0, 0.5, 0.0)


class Clock:
    """A hand-driven monotonic clock [ns]."""

    def __init__(self) -> None:
        self.t = 10**12

    def __call__(self) -> int:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += int(round(seconds * 1e9))


@pytest.fixture(scope="module")
def robot():
    return bundled_robot()


def make(robot, noise_a=0.0, noise_m=0.0, **sim):
    clock = Clock()
    cfg = SimConfig(current_noise_a=noise_a, tracker_noise_m=noise_m, start_q=START, **sim)
    world = SimWorld.from_config(robot, cfg)
    world._clock_ns = clock            # drive time by hand in these tests
    world._t0_ns = clock()
    world._reading_starts = [clock()]
    return world, clock


def test_moves_are_straight_lines_at_the_speed(robot):
    world, clock = make(robot, move_speed_rad_s=0.5)
    target = np.array([0.5, 0.4, -0.2, 0.3, -0.6, 0.2])
    duration = world.move_to(target)
    assert duration == pytest.approx(1.1 / 0.5)                      # joint 5 moves 1.1 rad
    with pytest.raises(InputError, match="moving"):
        world.move_to(START)
    with pytest.raises(InputError, match="while the robot moves"):
        world.set_load([0, 0, -100, 0, 0, 0])
    clock.advance(duration / 4)
    s = world.sample()
    np.testing.assert_allclose(s.q, np.array(START) + 0.25 * (target - START), atol=1e-12)
    np.testing.assert_allclose(s.dq, (target - START) / duration)
    assert s.moving and world.is_moving()
    clock.advance(duration)
    assert not world.is_moving() and world.wait_idle(0.0)
    np.testing.assert_allclose(world.sample().q, target)
    with pytest.raises(InputError, match="outside the joint limits"):
        world.move_to([0, 3.0, 0, 0, 0, 0])


def test_currents_at_rest_and_under_load_match_simcell(robot):
    world, clock = make(robot)
    cell = world.cell
    np.testing.assert_allclose(world.sample().currents_a, cell.currents(cell.equilibrium(START)), atol=1e-12)
    w = [0.0, 0.0, -1500.0, 0.0, 0.0, 0.0]
    world.set_load(w)
    eq = cell.equilibrium(START, w)
    np.testing.assert_allclose(world.sample().currents_a, cell.currents(eq), atol=1e-12)
    p = world.read_tracker("R2")
    np.testing.assert_allclose(p, cell.tracker_positions(eq, ["R2"])[0], atol=1e-12)
    world.remove_load()
    np.testing.assert_allclose(world.sample().currents_a, cell.currents(cell.equilibrium(START)), atol=1e-12)


def test_static_friction_absorbs_part_of_a_load_change(robot):
    world, clock = make(robot, hidden="static_friction")
    w = [0.0, 0.0, -1500.0, 0.0, 0.0, 0.0]
    world.set_load(w)
    cell = world.cell
    reference = cell.equilibrium(START)
    expected = cell.equilibrium(START, w, reference=reference)
    np.testing.assert_allclose(world.sample().currents_a, cell.currents(expected), atol=1e-12)
    # friction takes up to its limit of each joint's load change; the gear (and the current) sees the rest
    limit = cell.truth.static_friction
    delta_gear = expected.gear_torque - reference.gear_torque
    full_change = delta_gear + expected.friction_torque
    # (the absorbed part is fixed from the load change before friction acts: 1e-3 N·m of the
    # hundreds the load changes by)
    np.testing.assert_allclose(np.abs(expected.friction_torque), np.minimum(np.abs(full_change), limit),
                               rtol=1e-9, atol=1e-3)
    moved = np.abs(full_change) > 1e-6
    assert np.all(np.sign(expected.friction_torque[moved]) == np.sign(full_change[moved]))
    big = np.abs(full_change) > limit
    assert big[1] and big[2], "1500 N must overcome joint 2 and 3 friction"
    np.testing.assert_allclose(np.abs(delta_gear[big]), np.abs(full_change[big]) - limit[big], rtol=1e-9)
    np.testing.assert_allclose(delta_gear[~big], 0.0, atol=1e-3)
    # the change of the joints' load torque is that of the rigid statics at the loaded pose
    th10 = robot.theta_links(expected.theta, expected.link_angles)
    q2 = expected.theta[1] - robot.joints[1].offset
    load = robot.load_torque(th10, np.array(w), cell.truth.compensator, links=True, q_compensator=q2)
    np.testing.assert_allclose(expected.gear_torque + expected.friction_torque, load[[0, 1, 4, 7, 8, 9]],
                               rtol=1e-9, atol=1e-6)


def test_run_currents_include_friction_from_motion_currents(robot):
    world, clock = make(robot, run_speed_rad_s=0.05, move_speed_rad_s=1.0)
    u = np.array([0.0, -0.3, -0.5, 0.0, 0.5, 0.0])
    v = np.array([0.0, 0.9, -0.5, 0.0, 0.5, 0.0])
    w = np.array([0.0, 0.0, -800.0, 0.0, 0.0, 0.0])
    world.move_to(u)
    clock.advance(5.0)
    world.set_load(w)
    duration = world.run(u, v)
    assert duration == pytest.approx(1.2 / 0.05)
    for frac in (0.1, 0.37, 0.8):
        clock.t = world._segments[-1].t0_ns + int(frac * duration * 1e9)
        s = world.sample()
        np.testing.assert_allclose(s.dq, (v - u) / duration)
        exact = world.cell.motion_currents(s.q, s.dq, w)
        np.testing.assert_allclose(s.currents_a, exact, atol=2e-3)      # interpolated between grid points
        np.testing.assert_allclose(world.read_tracker("R1"),
                                   world.cell.tracker_positions(world.cell.equilibrium(s.q, w), ["R1"])[0],
                                   atol=2e-6)
    # forward and backward runs: friction flips sign, the load part does not
    clock.advance(duration)
    back = world.run(v, u)
    clock.t = world._segments[-1].t0_ns + int(0.5 * back * 1e9)
    i_vu = world.sample().currents_a
    q_mid = (u + v) / 2
    i_uv = world.cell.motion_currents(q_mid, (v - u) / duration, w)
    static = world.cell.currents(world.cell.equilibrium(q_mid, w))
    np.testing.assert_allclose((i_uv + i_vu) / 2, static, atol=2e-3)
    assert abs((i_uv - i_vu)[1] / 2) > 0.3                            # joint 2 friction current [A]


def test_noise_is_seeded(robot):
    a, _ = make(robot, noise_a=0.02, seed=11)
    b, _ = make(robot, noise_a=0.02, seed=11)
    c, clock = make(robot, noise_a=0.02, seed=12)
    before = c.sample().currents_a                  # no reading under way yet: a draw per sample
    clock.advance(0.001)
    assert not np.array_equal(before, c.sample().currents_a)
    for w in (a, b, c):
        w.select_marker(w.markers[0])
    first = a.sample().currents_a
    np.testing.assert_array_equal(first, b.sample().currents_a)
    assert not np.array_equal(first, c.sample().currents_a)
    np.testing.assert_array_equal(first, a.sample().currents_a)       # one draw for the whole reading
    a.select_marker(a.markers[0])
    assert not np.array_equal(first, a.sample().currents_a)           # fresh noise per reading
    exact = a.cell.currents(a.cell.equilibrium(START))

    def next_reading():
        a.select_marker(a.markers[0])
        return a.sample().currents_a - exact
    spread = np.std([next_reading() for _ in range(400)])
    assert spread == pytest.approx(0.02, rel=0.1)


def test_noise_follows_the_readings_not_the_order_of_the_devices(robot):
    """Each device's noise is its own function of the seed and the reading: how often and in which
    order the other devices read (the wall clock's doing in a served cell) changes nothing."""
    a, _ = make(robot, noise_a=0.02, noise_m=1e-5, seed=5)
    b, _ = make(robot, noise_a=0.02, noise_m=1e-5, seed=5)
    marker = a.markers[0]
    rows_a, rows_b = [], []
    for k in range(5):
        a.select_marker(marker)
        b.select_marker(marker)
        for _ in range(k + 1):               # a reads its tracker and drives more often than b
            a.read_tracker(marker)
            a.sample()
        rows_a.append((a.sample().currents_a, a.read_tracker(marker)))
        rows_b.append((b.sample().currents_a, b.read_tracker(marker)))
    for (ia, pa), (ib, pb) in zip(rows_a, rows_b):
        np.testing.assert_array_equal(ia, ib)
        np.testing.assert_array_equal(pa, pb)
    assert len({tuple(p) for _, p in rows_a}) == 5         # each reading its own draw
    # a reading taken again (a drive lost samples on a busy host) changes its own draw, not the next rest's
    a.select_marker(marker)
    for w in (a, b):
        w.set_load((0.0, 0.0, -500.0, 0.0, 0.0, 0.0))
        w.select_marker(marker)
    np.testing.assert_array_equal(a.read_tracker(marker), b.read_tracker(marker))
    np.testing.assert_array_equal(a.sample().currents_a, b.sample().currents_a)
