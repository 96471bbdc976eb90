"""The robot model of the bottom layer: an immutable serial chain and its Pinocchio models.

A :class:`Robot` is any serial chain of N >= 1 actuated joints, revolute or
prismatic, described by a modified-DH table or by a URDF chain
(:mod:`elastocal.model.urdf`); robot.toml is read and written by
:mod:`elastocal.formats.robot_toml`. It holds two immutable Pinocchio models:

* ``model``: the rigid chain, configuration ``theta`` (the link-side joint
  variable, ``theta = q + offset + dtheta``: radians for a revolute joint, metres
  for a prismatic one), with the frames ``flange``, ``load_point`` and
  ``marker:<name>`` on the last joint;
* ``link_model``: the same chain with two passive revolute joints (about two axes
  normal to the next joint's axis, x and y of a DH frame) at the distal ends of
  the links in :attr:`Robot.spring_links` (the two longest links: links 2 and 3 of
  a six-axis arm), used by the ``link_compliance`` effect. Its configuration is
  ``theta_links``, ordered as :attr:`Robot.link_joint_order`.

Pinocchio's rule holds: the models never change, and every computation owns its
``Data``. The methods below make a Data per call, or take the
:class:`RobotData` a caller made once with :meth:`Robot.create_data` and passes
to every call of one computation (a fit's loop), never shared between threads.
Kinematics, Jacobians and gravity all come from Pinocchio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError
from elastocal.model.compensator import CompensatorSpec
from elastocal.model.kinds import JointKind
from elastocal.model.tracker_noise import TrackerNoise
from elastocal.model.urdf import UrdfSource, urdf_chain

LOAD_FRAME = "load_point"
FLANGE_FRAME = "flange"
MARKER_PREFIX = "marker:"
#: radius of the solid sphere whose inertia a link gets about its centre of mass (statics use only
#: the mass and the centre of mass)
LINK_SPHERE_RADIUS_M = 0.05
#: how many links carry the link model's exact passive springs (the longest ones)
N_SPRING_LINKS = 2
#: prior joint stiffness when nothing better is known: Yang Table 3, the
#: "arbitrary values" of his analysis (the good zone barely depends on them) [N·m/rad]
DEFAULT_PRIOR_STIFFNESS = (1.0e6, 1.5e6, 2.0e6, 0.5e6, 0.5e6, 0.5e6)
#: a prismatic joint's prior stiffness when nothing better is known [N/m] (a linear track's
#: carriage and rack, order of magnitude)
DEFAULT_PRIOR_PRISMATIC_STIFFNESS = 5.0e7


@dataclass(frozen=True)
class JointSpec:
    """One actuated joint: its kind, its modified-DH parameters (Craig) and what the
    description says of it; ``a``, ``alpha``, ``d``, ``theta`` are nan for a URDF
    robot, whose URDF holds the geometry.

    A revolute joint turns about its z axis (``theta_i = q_i + offset``, ``d`` fixed);
    a prismatic joint slides along it (``d_i = q_i + offset``, ``theta`` fixed). ``q``,
    ``offset``, ``lower``, ``upper`` are in the joint's unit (:attr:`unit`)."""

    a: float
    alpha: float
    d: float
    offset: float
    lower: float
    upper: float
    #: xi [N·m/A, N/A for a prismatic joint]: joint-side effort per motor ampere; None when
    #: the description gives none (only a robot whose currents are read needs it)
    torque_constant: float | None
    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = ""
    #: Hayati's rotation about y [rad] (elastocal extension of docs/formats.md §1, for
    #: calibrated robots whose axes i-1 and i are parallel): Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)
    beta: float = 0.0
    #: the joint's nominal stiffness [N·m/rad, N/m] (an elastocal extension of docs/formats.md §1,
    #: e.g. the gear maker's catalogue value); None when not given
    stiffness: float | None = None
    kind: JointKind = JointKind.REVOLUTE
    #: a prismatic DH joint's fixed theta_i [rad]
    theta: float = 0.0
    #: the joint's speed limit [rad/s, m/s] and effort limit [N·m, N] (a URDF's ``<limit>``);
    #: None when the description gives none
    velocity: float | None = None
    effort: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", JointKind(self.kind))
        if not self.lower < self.upper:
            raise InputError(f"joint {self.name}: lower limit {self.lower} is not below upper {self.upper}")
        if self.torque_constant is not None and (self.torque_constant == 0.0
                                                 or not math.isfinite(self.torque_constant)):
            raise InputError(f"joint {self.name}: torque_constant must be a non-zero number")
        if self.mass < 0.0:
            raise InputError(f"joint {self.name}: mass must be >= 0")
        if self.stiffness is not None and not self.stiffness > 0.0:
            raise InputError(f"joint {self.name}: stiffness must be positive")
        for key in ("velocity", "effort"):
            value = getattr(self, key)
            if value is not None and not (value > 0.0 and math.isfinite(value)):
                raise InputError(f"joint {self.name}: {key} limit must be a positive number")

    @property
    def unit(self) -> str:
        return self.kind.unit


@dataclass(frozen=True)
class ToolSpec:
    """Load point and tracker markers, in flange (tip) coordinates [m]."""

    flange_p_load: tuple[float, float, float]
    flange_p_markers: tuple[tuple[str, tuple[float, float, float]], ...]

    @property
    def marker_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.flange_p_markers)


@dataclass(frozen=True, eq=False)
class RobotData:
    """Pinocchio work buffers of one computation on one robot (:meth:`Robot.create_data`):
    ``rigid`` for ``Robot.model``, ``links`` for ``Robot.link_model``. Made by the caller,
    passed to every call of that computation, never shared between threads."""

    rigid: pin.Data
    links: pin.Data
    #: the rigid model the buffers belong to (a Data serves its own model only)
    model: pin.Model | None = None
    _reused: dict = field(default_factory=dict, repr=False)

    def of(self, links: bool) -> pin.Data:
        return self.links if links else self.rigid

    def belongs_to(self, robot: "Robot") -> bool:
        return self.model is robot.model

    def reuse(self, key: tuple, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per ``key`` within this computation: what its fits ask again at the
        same configuration (a diagnosis fits many models at the same poses). The key names the
        function and its arguments (e.g. ``(location_frames, theta.tobytes())``); the value is
        not to be written to."""
        try:
            return self._reused[key]
        except KeyError:
            value = self._reused[key] = compute()
            return value


def _joint_model(kind: JointKind, axis: np.ndarray) -> pin.JointModel:
    """A revolute or prismatic joint along ``axis`` (unit, in the joint's frame): the
    X/Y/Z variants when it is one of the frame's axes."""
    axis = np.asarray(axis, dtype=float)
    aligned = ((pin.JointModelRX, pin.JointModelRY, pin.JointModelRZ) if kind is JointKind.REVOLUTE
               else (pin.JointModelPX, pin.JointModelPY, pin.JointModelPZ))
    for k, jm in enumerate(aligned):
        if abs(axis[k] - 1.0) < 1e-12 and np.linalg.norm(np.delete(axis, k)) < 1e-12:
            return jm()
    if kind is JointKind.REVOLUTE:
        return pin.JointModelRevoluteUnaligned(*axis)
    return pin.JointModelPrismaticUnaligned(*axis)


def normal_axes(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes normal to ``axis`` and to each other, right-handed with it
    (x and y for a z axis): the bending axes of a link spring."""
    axis = np.asarray(axis, dtype=float)
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ axis) * axis
    u /= np.linalg.norm(u)
    # axis x u written out: np.cross's own formula, without its array set-up (this runs per
    # location and pose in link_compliance's bases)
    return u, np.array([axis[1] * u[2] - axis[2] * u[1], axis[2] * u[0] - axis[0] * u[2],
                        axis[0] * u[1] - axis[1] * u[0]])


def _rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def dh_placement(joint: JointSpec) -> pin.SE3:
    """The part of the modified-DH transform that does not move with the joint:
    Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta) Tz(d_i) for a revolute joint (Rz(theta)
    and Tz(d) commute), Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta) Rz(theta_i) for a
    prismatic one; beta is Hayati's rotation for parallel consecutive axes (0 in a
    drawing's table)."""
    ca, sa = math.cos(joint.alpha), math.sin(joint.alpha)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    if joint.beta:
        cb, sb = math.cos(joint.beta), math.sin(joint.beta)
        rot = rot @ np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    if joint.kind is JointKind.PRISMATIC:
        return pin.SE3(rot @ _rz(joint.theta), np.array([joint.a, 0.0, 0.0]))
    trans = np.array([joint.a, 0.0, 0.0]) + rot @ np.array([0.0, 0.0, joint.d])
    return pin.SE3(rot, trans)


def _spring_links(placements: Sequence[pin.SE3], n: int) -> tuple[int, ...]:
    """The links (1..n-1) whose distal ends get the link model's passive springs: the
    N_SPRING_LINKS longest, link l's length being the distance from joint l's frame to
    joint l+1's at q = 0 (links 2 and 3 of a six-axis arm; ties to the lower link)."""
    lengths = [(float(np.linalg.norm(placements[l].translation)), -l) for l in range(1, n)]
    chosen = sorted(lengths, reverse=True)[:N_SPRING_LINKS]
    return tuple(sorted(-neg for _, neg in chosen))


@dataclass(frozen=True, eq=False)
class Robot:
    """An immutable robot: its description and the Pinocchio models built from it."""

    name: str
    joints: tuple[JointSpec, ...]
    gravity: tuple[float, float, float]
    tool: ToolSpec
    compensator: CompensatorSpec | None = None
    source: str = "<robot>"
    urdf: UrdfSource | None = None           # the URDF the geometry comes from (None: the DH table)
    #: the tracker noise law robot.toml's ``[tracker] noise`` states (a dataset shipped with its
    #: description alone); a cell.toml's law comes before it (docs/formats.md §1)
    tracker_noise: TrackerNoise | None = None
    model: pin.Model = field(init=False, repr=False)
    link_model: pin.Model = field(init=False, repr=False)
    #: links whose distal ends carry link_model's passive springs (module docstring)
    spring_links: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        if len(self.joints) < 1:
            raise InputError("a robot needs at least one [[joint]] table", source=self.source, column="joint")
        if self.urdf is None:
            placements = tuple(dh_placement(j) for j in self.joints)
            axes = np.tile([0.0, 0.0, 1.0], (len(self.joints), 1))
            flange = pin.SE3.Identity()
        else:
            chain = urdf_chain(self.urdf, [j.name for j in self.joints], source=self.source)
            placements, axes, flange = chain.placements, chain.axes, chain.flange_placement
            for j, kind in zip(self.joints, chain.kinds):
                if j.kind is not kind:
                    raise InputError(f"joint {j.name!r} is {kind.value} in the URDF but {j.kind.value} in the "
                                     "[[joint]] table", source=self.source, column="joint.type")
        if self.compensator is not None:
            c = self.compensator
            if c.joint > len(self.joints) or self.joints[c.index].kind is not JointKind.REVOLUTE:
                raise InputError(f"the compensator's joint {c.joint} is not a revolute joint of this robot",
                                 source=self.source, column="compensator.joint")
        object.__setattr__(self, "spring_links", _spring_links(placements, len(self.joints)))
        object.__setattr__(self, "model", self._build(placements, axes, flange, with_link_springs=False))
        object.__setattr__(self, "link_model", self._build(placements, axes, flange, with_link_springs=True))

    # ----------------------------------------------------------------- build
    def _build(self, placements: Sequence[pin.SE3], axes: np.ndarray, flange: pin.SE3, *,
               with_link_springs: bool) -> pin.Model:
        """The chain from each joint's placement in the previous joint's frame and
        its axis in its own frame; bodies from the joints' masses and centres of
        mass; the flange, load point and markers on the last joint."""
        model = pin.Model()
        model.name = self.name
        model.gravity = pin.Motion(np.array(self.gravity), np.zeros(3))
        parent = 0
        for i, (joint, placement, axis) in enumerate(zip(self.joints, placements, axes), start=1):
            if with_link_springs and i - 1 in self.spring_links:
                link = i - 1
                u, v = normal_axes(axis)
                parent = model.addJoint(parent, _joint_model(JointKind.REVOLUTE, u), placement, f"link{link}_x")
                parent = model.addJoint(parent, _joint_model(JointKind.REVOLUTE, v), pin.SE3.Identity(),
                                        f"link{link}_y")
                placement = pin.SE3.Identity()
            parent = model.addJoint(parent, _joint_model(joint.kind, axis), placement, f"joint{i}")
            if joint.mass > 0.0:
                inertia = pin.Inertia.FromSphere(joint.mass, LINK_SPHERE_RADIUS_M)
                inertia = pin.Inertia(joint.mass, np.array(joint.com), inertia.inertia)
                model.appendBodyToJoint(parent, inertia, pin.SE3.Identity())
        model.addFrame(pin.Frame(FLANGE_FRAME, parent, flange, pin.FrameType.OP_FRAME))
        model.addFrame(pin.Frame(LOAD_FRAME, parent, flange * pin.SE3(np.eye(3), np.array(self.tool.flange_p_load)),
                                 pin.FrameType.OP_FRAME))
        for name, flange_p in self.tool.flange_p_markers:
            model.addFrame(pin.Frame(MARKER_PREFIX + name, parent, flange * pin.SE3(np.eye(3), np.array(flange_p)),
                                     pin.FrameType.OP_FRAME))
        return model

    def create_data(self) -> RobotData:
        """Work buffers for one computation (module docstring)."""
        return RobotData(rigid=self.model.createData(), links=self.link_model.createData(), model=self.model)

    # ------------------------------------------------------------ properties
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def joint_kinds(self) -> tuple[JointKind, ...]:
        return tuple(j.kind for j in self.joints)

    @property
    def prismatic(self) -> np.ndarray:
        """(N,) bool: which joints are prismatic."""
        return np.array([j.kind is JointKind.PRISMATIC for j in self.joints])

    @property
    def has_torque_constants(self) -> bool:
        return all(j.torque_constant is not None for j in self.joints)

    @property
    def torque_constants(self) -> np.ndarray:
        """(N,) xi of every joint; refused, naming the joint, when the description lacks one
        (currents cannot be turned into torques without it)."""
        for i, j in enumerate(self.joints, start=1):
            if j.torque_constant is None:
                raise InputError(f"joint {i} ({j.name or f'joint{i}'}) has no torque_constant: motor currents "
                                 "need one per joint", source=self.source, column=f"joint[{i}].torque_constant")
        return np.array([j.torque_constant for j in self.joints], dtype=float)

    @property
    def offsets(self) -> np.ndarray:
        return np.array([j.offset for j in self.joints])

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.lower for j in self.joints])

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.upper for j in self.joints])

    @property
    def marker_names(self) -> tuple[str, ...]:
        return self.tool.marker_names

    @property
    def nominal_stiffness(self) -> np.ndarray | None:
        """k1..kN [N·m/rad, N/m] from robot.toml's ``stiffness`` keys, None unless every joint gives one."""
        k = [j.stiffness for j in self.joints]
        return None if any(v is None for v in k) else np.array(k, dtype=float)

    def prior_stiffness(self) -> np.ndarray:
        """(N,) a stiffness to plan with when nothing is measured: robot.toml's ``stiffness``
        keys where given, else Yang's analysis values for the revolute joints (in the order of
        a six-axis arm's, the last one repeated for more) and a track's for prismatic ones."""
        out = np.empty(self.n_joints)
        revolute = 0
        for i, j in enumerate(self.joints):
            if j.stiffness is not None:
                out[i] = j.stiffness
            elif j.kind is JointKind.PRISMATIC:
                out[i] = DEFAULT_PRIOR_PRISMATIC_STIFFNESS
            else:
                out[i] = DEFAULT_PRIOR_STIFFNESS[min(revolute, len(DEFAULT_PRIOR_STIFFNESS) - 1)]
            revolute += j.kind is JointKind.REVOLUTE
        return out

    @property
    def has_masses(self) -> bool:
        return any(j.mass > 0.0 for j in self.joints)

    @property
    def sweep_joint(self) -> int:
        """The joint (1-based) the run table's ``+``/``-`` sweeps move: the compensator's, joint 2
        of a six-axis arm without one."""
        return self.compensator.joint if self.compensator is not None else 2

    @property
    def link_spring_names(self) -> tuple[str, ...]:
        """Parameters of link_model's passive springs, in its order: ``cl<l>x, cl<l>y`` per spring link."""
        return tuple(f"cl{l}{a}" for l in self.spring_links for a in "xy")

    @property
    def link_joint_order(self) -> tuple[str, ...]:
        """link_model's configuration, named: ``q<i>`` for the actuated joints, the spring names."""
        out: list[str] = []
        for i in range(1, self.n_joints + 1):
            if i - 1 in self.spring_links:
                out += [f"cl{i - 1}x", f"cl{i - 1}y"]
            out.append(f"q{i}")
        return tuple(out)

    @property
    def actuated_in_link_model(self) -> np.ndarray:
        """Indices of the actuated joints in link_model's configuration."""
        return np.array([k for k, n in enumerate(self.link_joint_order) if n.startswith("q")])

    @property
    def springs_in_link_model(self) -> np.ndarray:
        """Indices of the passive springs in link_model's configuration."""
        return np.array([k for k, n in enumerate(self.link_joint_order) if n.startswith("cl")], dtype=int)

    def frame_id(self, frame: str, *, links: bool = False) -> int:
        model = self.link_model if links else self.model
        name = frame if frame in (LOAD_FRAME, FLANGE_FRAME) else MARKER_PREFIX + frame
        if not model.existFrame(name):
            raise InputError(f"unknown marker {frame!r}; the robot has {', '.join(self.marker_names)}",
                             source=self.source)
        return model.getFrameId(name)

    def theta(self, q: np.ndarray, dtheta: np.ndarray | None = None) -> np.ndarray:
        """Link-side joint variable ``q + offset (+ dtheta)``."""
        q = np.asarray(q, dtype=float)
        out = q + self.offsets
        return out if dtheta is None else out + dtheta

    def theta_links(self, theta: np.ndarray, link_angles: np.ndarray | None = None) -> np.ndarray:
        """Configuration of ``link_model`` from the N joint variables and the link-spring angles."""
        out = np.zeros(len(self.link_joint_order))
        out[self.actuated_in_link_model] = theta
        if link_angles is not None:
            out[self.springs_in_link_model] = link_angles
        return out

    # ------------------------------------------------------------ kinematics
    def _data(self, data: RobotData | None, links: bool) -> tuple[pin.Model, pin.Data]:
        model = self.link_model if links else self.model
        return model, (model.createData() if data is None else data.of(links))

    def positions(self, theta: np.ndarray, frames: Sequence[str], *, links: bool = False,
                  data: RobotData | None = None) -> np.ndarray:
        """Base-frame positions (len(frames), 3) of markers or the load point."""
        model, pdata = self._data(data, links)
        pin.framesForwardKinematics(model, pdata, np.asarray(theta, dtype=float))
        return np.array([pdata.oMf[self.frame_id(f, links=links)].translation for f in frames])

    def jacobians(self, theta: np.ndarray, frames: Sequence[str], *, links: bool = False,
                  data: RobotData | None = None) -> np.ndarray:
        """Frame Jacobians (len(frames), 6, nv), LOCAL_WORLD_ALIGNED: rows 0-2 the
        velocity of the frame origin in base axes, rows 3-5 the angular velocity."""
        model, pdata = self._data(data, links)
        theta = np.asarray(theta, dtype=float)
        pin.computeJointJacobians(model, pdata, theta)
        pin.updateFramePlacements(model, pdata)
        return np.array([
            pin.getFrameJacobian(model, pdata, self.frame_id(f, links=links), pin.LOCAL_WORLD_ALIGNED)
            for f in frames
        ])

    def gravity_torque(self, theta: np.ndarray, *, links: bool = False, data: RobotData | None = None) -> np.ndarray:
        """Generalised gravity g(theta): the effort that holds the links against gravity."""
        model, pdata = self._data(data, links)
        return pin.computeGeneralizedGravity(model, pdata, np.asarray(theta, dtype=float)).copy()

    def load_torque(self, theta: np.ndarray, wrench: np.ndarray | None,
                    compensator_params: Sequence[float] | None = None, *, gravity: bool = True,
                    links: bool = False, q_compensator: float | None = None,
                    data: RobotData | None = None) -> np.ndarray:
        """Load effort the joints carry, ``J_f^T W - g(theta) - M e_c`` (docs/formats.md sign).

        ``wrench`` is (fx, fy, fz, mx, my, mz) on the load point in base axes;
        ``q_compensator`` is the compensator's joint coordinate (default ``theta_c - offset_c``).
        """
        theta = np.asarray(theta, dtype=float)
        nv = (self.link_model if links else self.model).nv
        tau = np.zeros(nv)
        if wrench is not None:
            jac = self.jacobians(theta, [LOAD_FRAME], links=links, data=data)[0]
            tau += jac.T @ np.asarray(wrench, dtype=float)
        if gravity and self.has_masses:
            tau -= self.gravity_torque(theta, links=links, data=data)
        if self.compensator is not None and compensator_params is not None:
            c = self.compensator.index
            idx = int(self.actuated_in_link_model[c]) if links else c
            if q_compensator is None:
                q_compensator = theta[idx] - self.joints[c].offset
            tau[idx] -= float(self.compensator.torque(q_compensator, compensator_params))
        return tau

    # ------------------------------------------------------------ serialise
    def to_toml(self) -> str:
        """The description as robot.toml text (docs/formats.md §1)."""
        from elastocal.formats.robot_toml import robot_toml   # the format lives with the formats

        return robot_toml(self)

    def to_urdf(self, *, controller_angles: bool = True) -> str:
        """The chain as URDF text (:func:`elastocal.model.urdf_export.robot_urdf`): joint
        variable the controller's q (offsets in the joint origins), or with
        ``controller_angles=False`` theta = q + offset; flange, load point and marker
        frames; limits, masses and centres of mass from the description."""
        from elastocal.model.urdf_export import robot_urdf

        return robot_urdf(self, controller_angles=controller_angles)
