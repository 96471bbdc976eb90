"""The simulated cell: exact nonlinear statics of a virtual-joint robot with N joints.

This is the truth model of tests, benchmarks and the demo. One spring per joint
(``k``), optional springs at the distal ends of the two longest links
(``link_compliance``), gravity of the links, the gravity compensator, an external
wrench at the load point, and switchable effects that elastocal's joint-only
model does not know about: link compliance, tracker thermal drift, static
friction that absorbs part of a load change, backlash.

It is an independent witness of the identification: its torques, compensator,
friction and equilibria are computed by sims/physics.py with Pinocchio's own
algorithms (``rnea`` at rest, frame Jacobians), never with the physics methods
or the effect and fitting code the identification uses (tests/test_layers.py).
Any robot the bottom layer describes works: N revolute or prismatic joints,
per-joint truths of length N (:meth:`CellTruth.for_robot`).

Conventions (docs/formats.md): ``xi i`` is the load torque a joint carries,
``xi_j i_j = k_j (theta_j - q_j - offset_j)`` at rest. Friction during motion
resists the motion, so the drive supplies it in the direction of motion (the
motor's torque balance, docs/physics.md): ``xi i = tau_load + f(dq)`` with
``f = fc sign(dq) + fv dq + fl |tau_load| sign(dq)``.

Every function is pure given its arguments; noise comes from a
``numpy.random.Generator`` the caller passes (seeded).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from elastocal.model.robot import LOAD_FRAME, Robot
from elastocal.sims import physics
from elastocal.sims.as_built import (HH150_PARALLEL, as_built, default_kinematic_errors, default_urdf_errors,
                                     error_unit, parallel_axes)

#: HH-150 joint stiffness, Yang Table 6 (current-based) [N·m/rad]
HH150_STIFFNESS = (0.559e6, 1.435e6, 1.829e6, 0.184e6, 0.171e6, 0.070e6)
#: a linear track's carriage: rack, pinion and gearbox seen at the carriage [N/m] (the order of
#: magnitude of catalogue tracks for 150-kg arms; the simulator's choice, not a measured value)
TRACK_STIFFNESS = 2.0e7
#: effects the simulator can hide in a dataset (``--hidden``)
HIDDEN_EFFECTS = ("none", "link_compliance", "thermal_drift", "static_friction", "backlash",
                  "kinematic_errors", "tracker_frame", "base_tilt", "nonlinear_stiffness")
#: what the demo can hide and then find: effects its current-based static model lacks that the
#: static procedure shows (the geometry is always hidden; static friction holds part of a load in the
#: gears and the currents read what the gears carry after it, so no current-based model lacks it)
DEMO_HIDDEN = ("none", "link_compliance", "thermal_drift", "backlash")
#: what the demo can hide on a URDF robot: its fit does not model bent links beside its joint origins
DEMO_HIDDEN_URDF = ("none", "thermal_drift", "backlash")


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    out = np.eye(3)
    out[i, i], out[i, j], out[j, i], out[j, j] = c, -s, s, c
    return out


def tracker_placement(base_p_tracker, yaw: float, tilt_x: float, tilt_y: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of ``p_tracker = R p_base + t`` for a tracker standing at
    ``base_p_tracker`` [m], turned by ``yaw`` about the vertical and tilted by
    ``tilt_x``, ``tilt_y`` (a tripod that is not level) [rad]."""
    rot = _rot(0, tilt_x) @ _rot(1, tilt_y) @ _rot(2, yaw)
    return rot, -rot @ np.asarray(base_p_tracker, dtype=float)


#: the default simulated tracker: on a tripod 3.7 m from the robot, turned
#: 2.4 rad about the vertical, 4 and 3 mrad off level (docs/formats.md §2: any rigid placement)
DEFAULT_TRACKER = tracker_placement((3.2, -1.8, 0.6), 2.4, 0.004, -0.003)
#: ``--hidden tracker_frame``: the tracker moved to another stand, behind and
#: above the robot, facing it from the other side
MOVED_TRACKER = tracker_placement((-2.6, 2.9, 1.9), -0.9, -0.006, 0.008)

def _arr(value, n: int, name: str) -> np.ndarray:
    out = np.asarray(value, dtype=float).reshape(-1)
    if out.shape != (n,):
        raise ValueError(f"{name}: expected {n} values, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name}: values must be finite")
    return out


def joint_values(prismatic: Sequence[bool], revolute: Sequence[float], prismatic_value: float) -> np.ndarray:
    """One value per joint of a chain: the six-axis arm's values in order for its revolute
    joints (the last one repeated beyond six), ``prismatic_value`` for a prismatic joint."""
    out, r = [], 0
    for p in prismatic:
        out.append(prismatic_value if p else revolute[min(r, len(revolute) - 1)])
        r += not p
    return np.array(out, dtype=float)


@dataclass(frozen=True, eq=False)
class CellTruth:
    """The true parameters of a simulated cell (SI units; a prismatic joint's in N/m, N, m).

    Per-joint arrays have one value per joint of the robot (:meth:`for_robot`); left empty,
    they are zero (inf for ``hardening_torque``)."""

    stiffness: np.ndarray = field(default_factory=lambda: np.array(HH150_STIFFNESS))
    #: compensator parameters (C, l_c) or (K_c, s0); None when the robot has none
    compensator: tuple[float, float] | None = (4771.4, 0.9112)
    #: link compliance cl2x, cl2y, cl3x, cl3y [rad/(N·m)]
    link_compliance: np.ndarray = field(default_factory=lambda: np.zeros(4))
    #: tracker drift [m/s]
    drift_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: static friction torque that can absorb a load change, per joint [N·m]
    static_friction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: backlash (total lost motion) per joint [rad]; smoothed over backlash_torque_nm
    backlash: np.ndarray = field(default_factory=lambda: np.zeros(0))
    backlash_torque_nm: float = 20.0
    #: compliance of the base about its x and y axes [rad/(N·m)]: the whole robot
    #: tilts about the base origin under the overturning moment (load and link weights)
    base_tilt: np.ndarray = field(default_factory=lambda: np.zeros(2))
    #: torque-dependent gear stiffness dtau/dtheta = k (1 + |tau| / T) per joint [N·m];
    #: inf (the default) for a linear spring
    hardening_torque: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: Coulomb, viscous and load-dependent friction during motion
    coulomb: np.ndarray = field(default_factory=lambda: np.zeros(0))
    viscous: np.ndarray = field(default_factory=lambda: np.zeros(0))
    load_friction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: measurement noise (one standard deviation per reading)
    tracker_noise_m: float = 10e-6
    current_noise_a: float = 0.02
    #: the real robot's DH (or URDF joint origins') and marker errors, (name, value) under the names
    #: of identify/kinematics.py; () for a robot built exactly to its drawing
    kinematic_errors: tuple[tuple[str, float], ...] = ()
    #: where the tracker stands: p_tracker = tracker_rotation @ p_base + tracker_translation
    tracker_rotation: np.ndarray = field(default_factory=lambda: DEFAULT_TRACKER[0].copy())
    tracker_translation: np.ndarray = field(default_factory=lambda: DEFAULT_TRACKER[1].copy())
    #: which joints are prismatic (their values in N/m, N, m); () for the six revolute joints
    prismatic: tuple[bool, ...] = ()
    #: which joints' axes are parallel to the previous joint's (``--hidden kinematic_errors`` tilts
    #: them); () for the HH-150's (:data:`HH150_PARALLEL`) on six joints, none on another number
    parallel: tuple[bool, ...] = ()
    #: the robot's geometry is a URDF's joint origins (``--hidden kinematic_errors`` moves them,
    #: :func:`default_urdf_errors`), not a DH table
    urdf: bool = False

    @classmethod
    def for_robot(cls, robot: Robot, **changes) -> "CellTruth":
        """The simulated cell of ``robot``: the HH-150's stiffness (Yang Table 6) on its revolute
        joints in order, :data:`TRACK_STIFFNESS` on a prismatic one, the robot's parallel axes
        (:func:`parallel_axes`), whether it is a URDF robot; ``changes`` as the fields."""
        prismatic = tuple(bool(p) for p in robot.prismatic)
        if "stiffness" not in changes:
            changes["stiffness"] = joint_values(prismatic, HH150_STIFFNESS, TRACK_STIFFNESS)
        changes.setdefault("parallel", parallel_axes(robot))
        changes.setdefault("urdf", robot.urdf is not None)
        return cls(prismatic=prismatic, **changes)

    @property
    def n_joints(self) -> int:
        return int(self.stiffness.size)

    def per_joint(self, revolute: Sequence[float], prismatic_value: float) -> np.ndarray:
        """One value per joint of this cell (:func:`joint_values`)."""
        return joint_values(self.prismatic, revolute, prismatic_value)

    def __post_init__(self) -> None:
        n_joints = np.asarray(self.stiffness).size
        prismatic = tuple(bool(p) for p in self.prismatic) or (False,) * n_joints
        if len(prismatic) != n_joints:
            raise ValueError(f"prismatic: expected {n_joints} flags, got {len(prismatic)}")
        object.__setattr__(self, "prismatic", prismatic)
        parallel = tuple(bool(p) for p in self.parallel) or (HH150_PARALLEL if n_joints == 6 else (False,) * n_joints)
        if len(parallel) != n_joints:
            raise ValueError(f"parallel: expected {n_joints} flags, got {len(parallel)}")
        object.__setattr__(self, "parallel", parallel)
        for name in ("static_friction", "backlash", "coulomb", "viscous", "load_friction", "hardening_torque"):
            if np.asarray(getattr(self, name)).size == 0:
                fill = np.inf if name == "hardening_torque" else 0.0
                object.__setattr__(self, name, np.full(n_joints, fill))
        for name, n in (("stiffness", n_joints), ("link_compliance", 4), ("drift_velocity", 3),
                        ("static_friction", n_joints), ("backlash", n_joints), ("coulomb", n_joints),
                        ("viscous", n_joints), ("load_friction", n_joints), ("base_tilt", 2)):
            object.__setattr__(self, name, _arr(getattr(self, name), n, name))
        object.__setattr__(self, "tracker_translation", _arr(self.tracker_translation, 3, "tracker_translation"))
        rot = np.asarray(self.tracker_rotation, dtype=float)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
            raise ValueError("tracker_rotation must be a rotation matrix")
        object.__setattr__(self, "tracker_rotation", rot)
        hard = np.asarray(self.hardening_torque, dtype=float).reshape(-1)
        if hard.shape != (n_joints,) or np.any(np.isnan(hard)) or np.any(hard <= 0):
            raise ValueError(f"hardening_torque: expected {n_joints} positive values (inf for a linear spring)")
        object.__setattr__(self, "hardening_torque", hard)
        if np.any(self.stiffness <= 0):
            raise ValueError("stiffness must be positive")

    def with_hidden(self, effect: str) -> "CellTruth":
        """The same truth with one hidden effect switched on at a typical size
        (``"a,b"``: each of several)."""
        if "," in effect:
            out = self
            for name in (e.strip() for e in effect.split(",")):
                out = out.with_hidden(name)
            return out
        if effect == "none":
            return self
        if effect == "link_compliance":
            return replace(self, link_compliance=np.array([4.0e-7, 2.5e-7, 6.0e-7, 3.0e-7]))
        if effect == "thermal_drift":
            return replace(self, drift_velocity=np.array([0.6e-7, -0.4e-7, 0.8e-7]))
        if effect == "static_friction":
            return replace(self, static_friction=self.per_joint([60.0, 250.0, 200.0, 25.0, 20.0, 12.0], 150.0))
        if effect == "backlash":
            return replace(self, backlash=self.per_joint([6e-5, 5e-5, 5e-5, 1.2e-4, 1.2e-4, 1.5e-4], 2e-5))
        if effect == "kinematic_errors":
            errors = default_urdf_errors(self.prismatic) if self.urdf else \
                default_kinematic_errors(self.prismatic, self.parallel)
            return replace(self, kinematic_errors=errors)
        if effect == "tracker_frame":
            return replace(self, tracker_rotation=MOVED_TRACKER[0].copy(),
                           tracker_translation=MOVED_TRACKER[1].copy())
        if effect == "base_tilt":
            return replace(self, base_tilt=np.array([5.0e-8, 4.0e-8]))
        if effect == "nonlinear_stiffness":
            # stiffness that doubles at these torques: hardening gears (catalogue curves)
            return replace(self, hardening_torque=self.per_joint([4000.0, 15000.0, 8000.0, 1500.0, 1200.0, 500.0],
                                                                 3000.0))
        raise ValueError(f"unknown hidden effect {effect!r}; one of {', '.join(HIDDEN_EFFECTS)}")

    def parameters(self, robot: Robot) -> dict[str, dict[str, float | str]]:
        """True parameters under the names of docs/formats.md §4 (truth.json)."""
        out: dict[str, dict[str, float | str]] = {}
        for j, (k, p) in enumerate(zip(self.stiffness, self.prismatic), start=1):
            out[f"k{j}"] = {"value": float(k), "unit": "N/m" if p else "N*m/rad"}
        if robot.compensator is not None and self.compensator is not None:
            units = robot.compensator.parameter_units
            for name, value in zip(robot.compensator.parameter_names, self.compensator):
                out[name] = {"value": float(value), "unit": units[name]}
        if np.any(self.link_compliance):
            for name, v in zip(robot.link_spring_names, self.link_compliance):
                out[name] = {"value": float(v), "unit": "rad/(N*m)"}
        if np.any(self.base_tilt):
            for name, v in zip(("cl0x", "cl0y"), self.base_tilt):
                out[name] = {"value": float(v), "unit": "rad/(N*m)"}
        if np.any(np.isfinite(self.hardening_torque)):
            for j, (v, p) in enumerate(zip(self.hardening_torque, self.prismatic), start=1):
                out[f"T{j}"] = {"value": float(v) if np.isfinite(v) else None, "unit": "N" if p else "N*m"}
        if np.any(self.drift_velocity):
            for name, v in zip(("vx", "vy", "vz"), self.drift_velocity):
                out[name] = {"value": float(v), "unit": "m/s"}
        if np.any(self.backlash):
            for j, (v, p) in enumerate(zip(self.backlash, self.prismatic), start=1):
                out[f"b{j}"] = {"value": float(v), "unit": "m" if p else "rad"}
        if np.any(self.static_friction):
            for j, (v, p) in enumerate(zip(self.static_friction, self.prismatic), start=1):
                out[f"fs{j}"] = {"value": float(v), "unit": "N" if p else "N*m"}
        for prefix, arr, units in (("fc", self.coulomb, ("N*m", "N")), ("fv", self.viscous, ("N*m*s/rad", "N*s/m")),
                                   ("fl", self.load_friction, ("1", "1"))):
            if np.any(arr):
                for j, (v, p) in enumerate(zip(arr, self.prismatic), start=1):
                    out[f"{prefix}{j}"] = {"value": float(v), "unit": units[p]}
        for name, v in self.kinematic_errors:
            out[name] = {"value": float(v), "unit": error_unit(name, self.prismatic)}
        rvec = _rotation_vector(self.tracker_rotation)
        for name, v, unit in zip(("rx", "ry", "rz", "tx", "ty", "tz"), (*rvec, *self.tracker_translation),
                                 ("rad",) * 3 + ("m",) * 3):
            out[name] = {"value": float(v), "unit": unit}
        return out


def _rotation_vector(rot: np.ndarray) -> np.ndarray:
    import pinocchio as pin

    return np.asarray(pin.log3(np.asarray(rot, dtype=float)))


@dataclass(frozen=True)
class Equilibrium:
    """A static equilibrium of the simulated robot (noise-free)."""

    q: np.ndarray                  # commanded joint coordinates [rad, m]
    theta: np.ndarray              # link-side coordinates of the N joints [rad, m]
    link_angles: np.ndarray        # rotations of the 4 link springs [rad]
    gear_torque: np.ndarray        # torque each gear (and motor) carries [N·m]; xi i = gear_torque
    wrench: np.ndarray             # external wrench on the load point, base axes
    friction_torque: np.ndarray    # part of the load absorbed by static friction [N·m]
    base_rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # tilt of the base [rad]


def spring_angle(torque: np.ndarray, stiffness: np.ndarray, hardening_torque: np.ndarray) -> np.ndarray:
    """Twist of the joint springs under ``torque``: ``tau / k`` for a linear
    spring, ``(T / k) sign(tau) ln(1 + |tau| / T)`` for one whose stiffness
    ``dtau/dtheta = k (1 + |tau| / T)`` grows with the torque."""
    torque = np.asarray(torque, dtype=float)
    linear = torque / stiffness
    finite = np.isfinite(hardening_torque)
    if not np.any(finite):
        return linear
    t = np.where(finite, hardening_torque, 1.0)
    hard = t / stiffness * np.sign(torque) * np.log1p(np.abs(torque) / t)
    return np.where(finite, hard, linear)


class SimCell:
    """Statics of the simulated robot; immutable, thread-safe (each computation makes its own
    Pinocchio Data). The physics is sims/physics.py's (module docstring)."""

    def __init__(self, robot: Robot, truth: CellTruth | None = None) -> None:
        self.robot = robot
        self.truth = truth if truth is not None else CellTruth.for_robot(robot) if robot.n_joints != 6 \
            else CellTruth()
        if self.truth.n_joints != robot.n_joints:
            raise ValueError(f"the cell's truth holds {self.truth.n_joints} joints, the robot "
                             f"{robot.name!r} {robot.n_joints} (CellTruth.for_robot sizes one)")
        if robot.compensator is None:
            self.truth = replace(self.truth, compensator=None)
        #: the robot as built: the drawing's table with the truth's kinematic errors
        #: (the physics runs on it; ``robot`` is the description users have)
        self.physical = as_built(robot, self.truth.kinematic_errors)

    # --------------------------------------------------------------- statics
    def _springs(self) -> physics.Springs:
        t = self.truth

        def twist(gear: np.ndarray) -> np.ndarray:
            out = spring_angle(gear, t.stiffness, t.hardening_torque)
            if np.any(t.backlash):
                out = out + 0.5 * t.backlash * np.tanh(gear / t.backlash_torque_nm)
            return out

        return physics.Springs(twist=twist, link_compliance=t.link_compliance)

    def equilibrium(self, q: Sequence[float], wrench: Sequence[float] | None = None, *,
                    reference: Equilibrium | None = None, tol_rad: float = 1e-13,
                    max_iter: int = 200) -> Equilibrium:
        """Solve ``spring twist(gear torque) = theta - theta_rigid`` at commanded ``q``
        (physics.solve_equilibrium).

        ``reference``: the unloaded equilibrium at the same ``q``; when given and
        the truth has static friction, friction absorbs up to ``static_friction``
        of the change of each joint's load torque (the gears, motors and springs
        see only the rest).
        """
        r = self.physical
        t = self.truth
        q = np.asarray(q, dtype=float)
        w = np.zeros(6) if wrench is None else np.asarray(wrench, dtype=float)
        loads = physics.Loads(wrench=w, compensator=t.compensator)
        springs = self._springs()
        data = r.link_model.createData()
        theta0 = r.theta(q)
        absorbed = np.zeros(r.n_joints)
        sol = physics.solve_equilibrium(r, theta0, loads, springs, data=data, tol_rad=tol_rad, max_iter=max_iter)
        if reference is not None and np.any(t.static_friction):
            delta = sol.gear_torque - reference.gear_torque
            absorbed = np.sign(delta) * np.minimum(np.abs(delta), t.static_friction)
            sol = physics.solve_equilibrium(r, theta0, loads, springs, absorbed=absorbed, data=data,
                                            tol_rad=tol_rad, max_iter=max_iter)
        tilt = np.zeros(3)
        if np.any(t.base_tilt):
            tilt[:2] = t.base_tilt * self.base_moment(sol.theta_links, w)[:2]
        return Equilibrium(q=q, theta=sol.theta, link_angles=sol.link_angles, gear_torque=sol.gear_torque,
                           wrench=w, friction_torque=absorbed, base_rotation=tilt)

    def base_moment(self, theta_links: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        """Moment the robot puts on its base about the base origin [N·m]: the link
        weights and the external wrench (the compensator's forces are internal)."""
        import pinocchio as pin

        r = self.physical
        model = r.link_model
        data = model.createData()
        com = pin.centerOfMass(model, data, theta_links)
        mass = pin.computeTotalMass(model)
        moment = mass * np.cross(com, np.array(r.gravity))
        p_load = physics.frame_positions(r, data, theta_links, [LOAD_FRAME])[0]
        return moment + wrench[3:] + np.cross(p_load, wrench[:3])

    def _theta_links(self, eq: Equilibrium) -> np.ndarray:
        return self.physical.theta_links(eq.theta, eq.link_angles)

    def marker_positions(self, eq: Equilibrium, markers: Sequence[str]) -> np.ndarray:
        """Noise-free base-frame positions (len(markers), 3) at an equilibrium."""
        r = self.physical
        p = physics.frame_positions(r, r.link_model.createData(), self._theta_links(eq), list(markers))
        if np.any(eq.base_rotation):
            import pinocchio as pin

            p = p @ pin.exp3(eq.base_rotation).T      # the base tilts about its origin
        return p

    def tracker_positions(self, eq: Equilibrium, markers: Sequence[str]) -> np.ndarray:
        """Noise-free positions (len(markers), 3) in the tracker's frame, without drift."""
        return self.to_tracker(self.marker_positions(eq, markers))

    def to_tracker(self, base_p: np.ndarray) -> np.ndarray:
        """Base-frame positions (M, 3) in the tracker's measurement frame."""
        return np.asarray(base_p) @ self.truth.tracker_rotation.T + self.truth.tracker_translation

    @property
    def tracker_drift(self) -> np.ndarray:
        """The drift velocity in the tracker's frame [m/s] (the truth gives it in base axes)."""
        return self.truth.tracker_rotation @ self.truth.drift_velocity

    def currents(self, eq: Equilibrium) -> np.ndarray:
        """Noise-free motor currents [A] (signed: xi i = gear torque)."""
        return eq.gear_torque / self.robot.torque_constants

    # ----------------------------------------------------------- measuring
    def read_tracker(self, eq: Equilibrium, markers: Sequence[str], t_s: float,
                     rng: np.random.Generator) -> np.ndarray:
        """Tracker readings of the markers at time ``t_s``, in the tracker's frame: drift and noise added.

        The noise is isotropic; it is drawn in base axes and turned with the
        reading, so that the same seed gives the same data, rigidly moved, from
        wherever the tracker stands."""
        p = self.marker_positions(eq, markers) + self.truth.drift_velocity * t_s
        return self.to_tracker(p + rng.normal(0.0, self.truth.tracker_noise_m, size=p.shape))

    def read_currents(self, eq: Equilibrium, rng: np.random.Generator) -> np.ndarray:
        return self.currents(eq) + rng.normal(0.0, self.truth.current_noise_a, size=self.robot.n_joints)

    # -------------------------------------------------------------- motion
    def motion_currents(self, q: np.ndarray, dq: np.ndarray, wrench: np.ndarray | None = None) -> np.ndarray:
        """Noise-free currents during a slow motion (quasi-static, friction on).

        ``xi i = tau_load + (fc sign(dq) + fv dq + fl |tau_load| sign(dq))``: the motor
        turns the load and overcomes the friction that resists the motion.
        """
        eq = self.equilibrium(q, wrench)
        return (eq.gear_torque + self.friction_torque(dq, eq.gear_torque)) / self.robot.torque_constants

    def friction_torque(self, dq: np.ndarray, load_torque: np.ndarray) -> np.ndarray:
        """Friction the drive supplies on top of the load torque during a motion at ``dq``
        (physics.friction_effort: in the direction of motion)."""
        t = self.truth
        return physics.friction_effort(dq, load_torque, t.coulomb, t.viscous, t.load_friction)

    def load_point(self, eq: Equilibrium) -> np.ndarray:
        r = self.physical
        return physics.frame_positions(r, r.link_model.createData(), self._theta_links(eq), [LOAD_FRAME])[0]
