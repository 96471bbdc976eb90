"""The simulated robot under external guidance, and the process force that deflects it.

The simulated EGM and RSI controllers (:mod:`elastocal.sims.egm_controller`,
:mod:`elastocal.sims.rsi_controller`) hand every cycle's joint targets to a
:class:`GuidedRobot`; it takes them as the motor-side joint coordinates (the servos follow
within the cycle: the statics do not depend on the speed of a path at 10 mm/s) and solves
the deflected equilibrium under the process force of that instant with the simulated cell's
own physics. The simulated Net F/T (:mod:`elastocal.sims.netft_sensor`) reads the same
process force.

The physics enters through one function, :func:`statics`: the simulated cell's public
equilibrium for a configuration and a wrench. Nothing here knows how it is computed.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import pinocchio as pin

from elastocal.model.robot import LOAD_FRAME


@dataclass(frozen=True)
class Statics:
    """The simulated robot at rest under a wrench: what the guided controllers need of it."""

    theta: np.ndarray          # link-side joint angles [rad]
    gear_torque: np.ndarray    # torque each gear and motor carries [N·m] (xi i = gear torque)
    load_point: np.ndarray     # base-frame position of the load point [m]


def statics(cell, q: Sequence[float], wrench: Sequence[float] | None) -> Statics:
    """The deflected equilibrium of the simulated ``cell`` at commanded ``q`` under ``wrench``
    (on the load point, base axes): the one place the guided simulation calls the cell's physics."""
    eq = cell.equilibrium(np.asarray(q, dtype=float), None if wrench is None else np.asarray(wrench, dtype=float))
    return Statics(theta=np.asarray(eq.theta, dtype=float), gear_torque=np.asarray(eq.gear_torque, dtype=float),
                   load_point=np.asarray(cell.load_point(eq), dtype=float))


@dataclass(frozen=True, eq=False)
class ProcessLoad:
    """The process wrench on the load point (base axes [N, N·m]): from the first guided cycle it
    builds up from zero to ``start`` over ``engage_s`` (the tool entering the workpiece, a smooth
    step), and changes linearly from ``start`` to ``end`` over ``duration_s``, then is held.
    Before guidance starts the tool is off the workpiece (no wrench)."""

    start: np.ndarray
    end: np.ndarray
    duration_s: float
    engage_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("start", "end"):
            v = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if v.shape != (6,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name}: expected 6 finite values")
            object.__setattr__(self, name, v)
        if not self.duration_s > 0:
            raise ValueError("duration_s must be > 0")
        if not self.engage_s >= 0:
            raise ValueError("engage_s must be >= 0")

    def at(self, t_s: float | None) -> np.ndarray:
        if t_s is None:
            return np.zeros(6)
        s = min(max(t_s / self.duration_s, 0.0), 1.0)
        w = self.start + s * (self.end - self.start)
        if t_s < self.engage_s:
            x = max(t_s, 0.0) / self.engage_s
            w = w * (x * x * (3.0 - 2.0 * x))
        return w


@dataclass(frozen=True)
class GuidedStep:
    """What the simulated robot did in one cycle (the witness's record)."""

    t_s: float                 # process time (0 at the first guided cycle)
    q: np.ndarray              # motor-side joint coordinates it ran [rad]
    wrench: np.ndarray         # the true process wrench then
    load_point: np.ndarray     # where the load point truly was [m]


@dataclass(frozen=True)
class SensorPlacement:
    """How a force sensor sits on the tool: its axes are the load point frame's (turned with the tool)."""

    frame: str = LOAD_FRAME


class GuidedRobot:
    """The simulated robot the guided controllers move (see the module docstring). Thread-safe."""

    def __init__(self, cell, *, start_q: Sequence[float], load: ProcessLoad | None = None, seed: int = 0) -> None:
        self.cell = cell
        self.robot = cell.robot
        self.n_joints = len(self.robot.joints)
        q0 = np.asarray(start_q, dtype=float)
        if q0.shape != (self.n_joints,):
            raise ValueError(f"start_q: expected {self.n_joints} values")
        self.load = load
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._q = q0
        self._t_s: float | None = None
        self._statics = statics(cell, q0, None)
        self._steps: list[GuidedStep] = []
        self._rotation_key: tuple | None = None
        self._rotation = np.eye(3)

    # ----------------------------------------------------------- the process
    def process_time(self) -> float | None:
        """The process time of the robot's last cycle [s] (None before the first guided cycle)."""
        with self._lock:
            return self._t_s

    def process_wrench(self) -> np.ndarray:
        """The true process wrench now (base axes): the one of the robot's last cycle."""
        t_s = self.process_time()
        if self.load is None or t_s is None:
            return np.zeros(6)
        return self.load.at(t_s)

    def sensor_wrench(self, placement: SensorPlacement) -> np.ndarray:
        """The process wrench in a tool-mounted sensor's axes (turned with the deflected tool)."""
        w = self.process_wrench()
        with self._lock:
            rot = self._tool_rotation(placement.frame)
        return np.concatenate((rot.T @ w[:3], rot.T @ w[3:]))

    def _tool_rotation(self, frame: str) -> np.ndarray:
        """Base <- ``frame`` at the current deflected pose (the lock is held; cached per pose)."""
        key = (frame, id(self._statics))
        if self._rotation_key != key:
            model = self.robot.model
            data = model.createData()         # this computation owns its Data (Pinocchio's rule)
            pin.framesForwardKinematics(model, data, self._statics.theta)   # link-side angles, offsets included
            self._rotation = data.oMf[self.robot.frame_id(frame)].rotation.copy()
            self._rotation_key = key
        return self._rotation

    # ---------------------------------------------------------------- motion
    @property
    def q(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    @property
    def has_currents(self) -> bool:
        """Whether the robot description gives the torque constants that turn torques into currents."""
        return self.robot.has_torque_constants

    def currents(self) -> np.ndarray:
        """Motor currents [A] with the simulated cell's current noise (xi i = gear torque)."""
        with self._lock:
            tau = self._statics.gear_torque.copy()
        noise = getattr(self.cell.truth, "current_noise_a", 0.0)
        return tau / self.robot.torque_constants + self._rng.normal(0.0, noise, size=tau.shape)

    def step(self, q_target: Sequence[float], t_s: float) -> GuidedStep:
        """Run one guided cycle at process time ``t_s`` (the controller's clock since guidance
        started: the process advances with the robot, not with this computer's clock): the motors
        go to ``q_target``; the robot settles under the process wrench of that instant."""
        q = np.asarray(q_target, dtype=float)
        w = self.load.at(t_s) if self.load is not None else np.zeros(6)
        st = statics(self.cell, q, w)
        record = GuidedStep(t_s=float(t_s), q=q.copy(), wrench=w, load_point=st.load_point)
        with self._lock:
            self._q = q.copy()
            self._t_s = float(t_s)
            self._statics = st
            self._steps.append(record)
        return record

    def hold(self, t_s: float) -> None:
        """A cycle without a new target: the robot stays where it is (the process force may change)."""
        self.step(self.q, t_s)

    def history(self) -> list[GuidedStep]:
        with self._lock:
            return list(self._steps)


@dataclass(frozen=True)
class Faults:
    """Faults a simulated guidance peer injects (for tests and rehearsals)."""

    #: cycles (0-based) whose state message the controller does not send (a lost packet)
    lost_cycles: frozenset[int] = field(default_factory=frozenset)
    #: from this cycle on the controller sends nothing (a cable pulled, the program stopped)
    silent_from_cycle: int | None = None
