"""Robot description (``robot.toml``, docs/formats.md §1) and its Pinocchio models.

The description is resolved once into frozen dataclasses; :class:`Robot` holds
two immutable Pinocchio models built from the modified-DH table, or from a
URDF (:mod:`elastocal.model.urdf`):

* ``model``: the rigid 6-joint chain, configuration ``theta`` (the link-side DH
  or URDF joint variable, ``theta = q + offset + dtheta``);
* ``link_model``: the same chain with two passive revolute joints (about x and
  y of the next joint's frame, for a URDF two axes normal to its axis) at the
  distal ends of links 2 and 3, used by the ``link_compliance`` effect
  and by the simulator. Its configuration is ``theta_links`` (10 values, in the
  order of :data:`LINK_JOINT_ORDER`).

Every method allocates its own Pinocchio ``Data`` (or takes one), so a
``Robot`` can be shared between threads. Kinematics, Jacobians and gravity all
come from Pinocchio.

Why one module over 500 lines: the description's validation (every key named
with its file), the Pinocchio models built from it and the immutable :class:`Robot`
are one fact, the robot model of the bottom layer; split, each half would need the
other's private tables.
"""

from __future__ import annotations

import json
import math
import pathlib
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import pinocchio as pin

from elastocal.errors import InputError, check_known_keys
from elastocal.formats.textfiles import read_text_file
from elastocal.model.urdf import UrdfSource, dh_urdf, urdf_chain

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

N_JOINTS = 6
LOAD_FRAME = "load_point"
FLANGE_FRAME = "flange"
MARKER_PREFIX = "marker:"
#: names of the passive link-compliance joints, in the order of their parameters
LINK_SPRINGS = ("cl2x", "cl2y", "cl3x", "cl3y")
#: radius of the solid sphere whose inertia a link gets about its centre of mass (statics use only
#: the mass and the centre of mass)
LINK_SPHERE_RADIUS_M = 0.05
#: index in ``link_model``'s configuration of each actuated joint and link spring
LINK_JOINT_ORDER = ("q1", "q2", "cl2x", "cl2y", "q3", "cl3x", "cl3y", "q4", "q5", "q6")
ACTUATED_IN_LINK_MODEL = np.array([0, 1, 4, 7, 8, 9])
SPRINGS_IN_LINK_MODEL = np.array([2, 3, 5, 6])
#: plausibility limits of robot.toml values: beyond them a value is taken as the wrong unit
#: (millimetres for metres, degrees for radians, grams for kilograms)
MAX_LENGTH_M = 10.0
MAX_ANGLE_RAD = 2 * math.pi + 1e-9
MAX_LINK_MASS_KG = 1e4
MAX_GRAVITY_M_S2 = 20.0
#: prior joint stiffness when nothing better is known: Yang Table 3, the
#: "arbitrary values" of his analysis (the good zone barely depends on them) [N·m/rad]
DEFAULT_PRIOR_STIFFNESS = (1.0e6, 1.5e6, 2.0e6, 0.5e6, 0.5e6, 0.5e6)


def _plausible_length(value: float, *, source: str, column: str) -> None:
    if abs(value) > MAX_LENGTH_M:
        raise InputError(f"{value:g} m is longer than {MAX_LENGTH_M:g} m; millimetres? lengths are metres",
                         source=source, column=column)


def _plausible_angle(value: float, *, source: str, column: str) -> None:
    if abs(value) > MAX_ANGLE_RAD:
        raise InputError(f"{value:g} rad is more than a full turn; degrees? angles are radians",
                         source=source, column=column)


def _vec3(value, *, source: str, column: str) -> tuple[float, float, float]:
    try:
        arr = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"expected a list of 3 numbers, got {value!r}", source=source, column=column) from None
    if len(arr) != 3 or not all(math.isfinite(v) for v in arr):
        raise InputError(f"expected 3 finite numbers, got {value!r}", source=source, column=column)
    return arr  # type: ignore[return-value]


#: the keys robot.toml knows (docs/formats.md §1 plus elastocal's optional URDF keys)
TOP_KEYS = ("name", "convention", "gravity", "urdf", "urdf_xml", "joint", "tool", "compensator")
JOINT_KEYS = ("name", "a", "alpha", "d", "beta", "offset", "lower", "upper", "torque_constant", "mass", "com",
              "stiffness")
TOOL_KEYS = ("load_point", "markers", "flange")
COMPENSATOR_KEYS = {"hydropneumatic": ("kind", "joint", "a", "b", "h", "C", "l_c"),
                    "spring": ("kind", "joint", "a", "L", "alpha", "K_c", "s0")}


def _table(value, *, source: str, column: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise InputError(f"expected a table, got {value!r}", source=source, column=column)
    return value


def _number(table: Mapping, key: str, *, source: str, where: str, default: float | None = None) -> float:
    if key not in table:
        if default is None:
            raise InputError("missing required key", source=source, column=f"{where}.{key}")
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"expected a finite number, got {value!r}", source=source, column=f"{where}.{key}")
    return float(value)


@dataclass(frozen=True)
class JointSpec:
    """One actuated revolute joint in modified-DH form (Craig); ``a``, ``alpha``
    and ``d`` are nan for a URDF robot, whose URDF holds the geometry."""

    a: float
    alpha: float
    d: float
    offset: float
    lower: float
    upper: float
    torque_constant: float
    mass: float = 0.0
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = ""
    #: Hayati's rotation about y [rad] (elastocal extension of docs/formats.md §1, for
    #: calibrated robots whose axes i-1 and i are parallel): Rx(alpha) Tx(a) Ry(beta) Rz(theta) Tz(d)
    beta: float = 0.0
    #: the joint's nominal stiffness [N·m/rad] (an elastocal extension of docs/formats.md §1,
    #: e.g. the gear maker's catalogue value); None when not given
    stiffness: float | None = None

    def __post_init__(self) -> None:
        if not self.lower < self.upper:
            raise InputError(f"joint {self.name}: lower limit {self.lower} is not below upper {self.upper}")
        if self.torque_constant == 0.0:
            raise InputError(f"joint {self.name}: torque_constant must be non-zero")
        if self.mass < 0.0:
            raise InputError(f"joint {self.name}: mass must be >= 0")
        if self.stiffness is not None and not self.stiffness > 0.0:
            raise InputError(f"joint {self.name}: stiffness must be positive")


@dataclass(frozen=True)
class ToolSpec:
    """Load point and tracker markers, in flange (frame 6) coordinates [m]."""

    flange_p_load: tuple[float, float, float]
    flange_p_markers: tuple[tuple[str, tuple[float, float, float]], ...]

    @property
    def marker_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.flange_p_markers)


HYDRO_PARAMS = ("C", "l_c")
SPRING_PARAMS = ("K_c", "s0")
HYDRO_UNITS = {"C": "N*m", "l_c": "m"}
SPRING_UNITS = {"K_c": "N/m", "s0": "m"}


@dataclass(frozen=True)
class CompensatorSpec:
    """Gravity compensator on joint 2 (docs/physics.md).

    ``kind = "hydropneumatic"`` (Yang): geometry ``a, b, h`` [m], parameters
    ``C`` [N·m] and ``l_c`` [m]. ``kind = "spring"`` (Klimchik): geometry
    ``a, L`` [m] and ``alpha`` [rad], parameters ``K_c`` [N/m] and ``s0`` [m].
    ``nominal`` optionally holds known parameter values (an elastocal
    extension of docs/formats.md: keys ``C``/``l_c`` or ``K_c``/``s0`` in the table).

    The torque is the balancing torque ``M`` of the papers (Y32: ``M = tau2^0 -
    xi2 i2``): it relieves joint 2, so the load torque joint 2 carries is
    ``xi2 i2 = tau2^0 - M``.
    """

    kind: str
    joint: int
    geometry: tuple[tuple[str, float], ...]
    nominal: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("hydropneumatic", "spring"):
            raise InputError(f"compensator kind must be 'hydropneumatic' or 'spring', got {self.kind!r}")
        if self.joint != 2:
            raise InputError(f"compensator joint must be 2, got {self.joint}")

    @property
    def parameter_names(self) -> tuple[str, str]:
        return HYDRO_PARAMS if self.kind == "hydropneumatic" else SPRING_PARAMS

    @property
    def parameter_units(self) -> dict[str, str]:
        return dict(HYDRO_UNITS if self.kind == "hydropneumatic" else SPRING_UNITS)

    def geo(self, key: str) -> float:
        return dict(self.geometry)[key]

    def nominal_parameters(self) -> np.ndarray | None:
        nom = dict(self.nominal)
        names = self.parameter_names
        if all(n in nom for n in names):
            return np.array([nom[n] for n in names], dtype=float)
        return None

    def torque(self, q2: np.ndarray | float, params: Sequence[float]) -> np.ndarray:
        """Balancing torque M(q2) [N·m] for parameters (C, l_c) or (K_c, s0)."""
        q2 = np.asarray(q2, dtype=float)
        p0, p1 = float(params[0]), float(params[1])
        if self.kind == "hydropneumatic":
            a, b, h = self.geo("a"), self.geo("b"), self.geo("h")
            r = math.hypot(a, h)
            alpha = math.atan2(a, h)
            length = self.hydro_length(q2)
            return p0 * b * r * np.cos(alpha - q2) / (length * (p1 - length))
        a, big_l, alpha = self.geo("a"), self.geo("L"), self.geo("alpha")
        s = self.spring_length(q2)
        return p0 * (1.0 - p1 / s) * a * big_l * np.sin(alpha - q2)

    def torque_derivatives(self, q2: np.ndarray | float, params: Sequence[float]) -> np.ndarray:
        """d M / d params, shape (len(q2), 2), analytic."""
        q2 = np.atleast_1d(np.asarray(q2, dtype=float))
        p0, p1 = float(params[0]), float(params[1])
        if self.kind == "hydropneumatic":
            a, b, h = self.geo("a"), self.geo("b"), self.geo("h")
            r = math.hypot(a, h)
            alpha = math.atan2(a, h)
            length = self.hydro_length(q2)
            g = b * r * np.cos(alpha - q2) / length
            return np.column_stack([g / (p1 - length), -p0 * g / (p1 - length) ** 2])
        a, big_l, alpha = self.geo("a"), self.geo("L"), self.geo("alpha")
        s = self.spring_length(q2)
        g = a * big_l * np.sin(alpha - q2)
        return np.column_stack([(1.0 - p1 / s) * g, -p0 / s * g])

    def stiffness(self, q2: np.ndarray | float, params: Sequence[float], step: float = 1e-6) -> np.ndarray:
        """Equivalent stiffness k_b = dM/dq2 [N·m/rad] (Y12); it adds to k2 in the
        force-based model."""
        q2 = np.asarray(q2, dtype=float)
        return (self.torque(q2 + step, params) - self.torque(q2 - step, params)) / (2 * step)

    def hydro_length(self, q2: np.ndarray) -> np.ndarray:
        a, b, h = self.geo("a"), self.geo("b"), self.geo("h")
        r = math.hypot(a, h)
        alpha = math.atan2(a, h)
        return np.sqrt(b * b + r * r - 2.0 * b * r * np.sin(alpha - q2))

    def spring_length(self, q2: np.ndarray) -> np.ndarray:
        a, big_l, alpha = self.geo("a"), self.geo("L"), self.geo("alpha")
        return np.sqrt(a * a + big_l * big_l + 2.0 * a * big_l * np.cos(alpha - q2))


def _revolute(axis: np.ndarray) -> pin.JointModel:
    """A revolute joint about ``axis`` (unit, in the joint's frame): RX/RY/RZ when it is one of those."""
    for k, jm in enumerate((pin.JointModelRX, pin.JointModelRY, pin.JointModelRZ)):
        if abs(axis[k] - 1.0) < 1e-12 and np.linalg.norm(np.delete(axis, k)) < 1e-12:
            return jm()
    return pin.JointModelRevoluteUnaligned(*np.asarray(axis, dtype=float))


def _normal_axes(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes normal to ``axis`` and to each other, right-handed with it
    (x and y for a z axis): the bending axes of a link spring."""
    axis = np.asarray(axis, dtype=float)
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ref - (ref @ axis) * axis
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def _dh_placement(joint: JointSpec) -> pin.SE3:
    """Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta) Tz(d_i): the parts of the modified-DH transform
    that do not depend on theta (Rz(theta) and Tz(d) commute); beta is Hayati's
    rotation for parallel consecutive axes (0 in a drawing's table)."""
    ca, sa = math.cos(joint.alpha), math.sin(joint.alpha)
    rot = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    if joint.beta:
        cb, sb = math.cos(joint.beta), math.sin(joint.beta)
        rot = rot @ np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    trans = np.array([joint.a, 0.0, 0.0]) + rot @ np.array([0.0, 0.0, joint.d])
    return pin.SE3(rot, trans)


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
    model: pin.Model = field(init=False, repr=False)
    link_model: pin.Model = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if len(self.joints) != N_JOINTS:
            raise InputError(f"expected {N_JOINTS} [[joint]] tables, got {len(self.joints)}", source=self.source)
        if self.urdf is None:
            placements = tuple(_dh_placement(j) for j in self.joints)
            axes = np.tile([0.0, 0.0, 1.0], (N_JOINTS, 1))
            flange = pin.SE3.Identity()
        else:
            chain = urdf_chain(self.urdf, [j.name for j in self.joints], source=self.source)
            placements, axes, flange = chain.placements, chain.axes, chain.flange_placement
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
            if with_link_springs and i in (3, 4):
                link = i - 1
                u, v = _normal_axes(axis)
                parent = model.addJoint(parent, _revolute(u), placement, f"link{link}_x")
                parent = model.addJoint(parent, _revolute(v), pin.SE3.Identity(), f"link{link}_y")
                placement = pin.SE3.Identity()
            parent = model.addJoint(parent, _revolute(axis), placement, f"joint{i}")
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

    # ------------------------------------------------------------ properties
    @property
    def torque_constants(self) -> np.ndarray:
        return np.array([j.torque_constant for j in self.joints])

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
        """k1..k6 [N·m/rad] from robot.toml's ``stiffness`` keys, None unless every joint gives one."""
        k = [j.stiffness for j in self.joints]
        return None if any(v is None for v in k) else np.array(k, dtype=float)

    @property
    def has_masses(self) -> bool:
        return any(j.mass > 0.0 for j in self.joints)

    def frame_id(self, frame: str, *, links: bool = False) -> int:
        model = self.link_model if links else self.model
        name = frame if frame in (LOAD_FRAME, FLANGE_FRAME) else MARKER_PREFIX + frame
        if not model.existFrame(name):
            raise InputError(f"unknown marker {frame!r}; the robot has {', '.join(self.marker_names)}",
                             source=self.source)
        return model.getFrameId(name)

    def theta(self, q: np.ndarray, dtheta: np.ndarray | None = None) -> np.ndarray:
        """Link-side DH variable ``q + offset (+ dtheta)``."""
        q = np.asarray(q, dtype=float)
        out = q + self.offsets
        return out if dtheta is None else out + dtheta

    def theta_links(self, theta: np.ndarray, link_angles: np.ndarray | None = None) -> np.ndarray:
        """Configuration of ``link_model`` from the 6 joint angles and 4 link-spring angles."""
        out = np.zeros(len(LINK_JOINT_ORDER))
        out[ACTUATED_IN_LINK_MODEL] = theta
        if link_angles is not None:
            out[SPRINGS_IN_LINK_MODEL] = link_angles
        return out

    # ------------------------------------------------------------ kinematics
    def positions(self, theta: np.ndarray, frames: Sequence[str], *, links: bool = False) -> np.ndarray:
        """Base-frame positions (len(frames), 3) of markers or the load point."""
        model = self.link_model if links else self.model
        data = model.createData()
        pin.framesForwardKinematics(model, data, np.asarray(theta, dtype=float))
        return np.array([data.oMf[self.frame_id(f, links=links)].translation for f in frames])

    def jacobians(self, theta: np.ndarray, frames: Sequence[str], *, links: bool = False) -> np.ndarray:
        """Frame Jacobians (len(frames), 6, nv), LOCAL_WORLD_ALIGNED: rows 0-2 the
        velocity of the frame origin in base axes, rows 3-5 the angular velocity."""
        model = self.link_model if links else self.model
        data = model.createData()
        theta = np.asarray(theta, dtype=float)
        pin.computeJointJacobians(model, data, theta)
        pin.updateFramePlacements(model, data)
        return np.array([
            pin.getFrameJacobian(model, data, self.frame_id(f, links=links), pin.LOCAL_WORLD_ALIGNED)
            for f in frames
        ])

    def gravity_torque(self, theta: np.ndarray, *, links: bool = False) -> np.ndarray:
        """Generalised gravity g(theta): the torque that holds the links against gravity."""
        model = self.link_model if links else self.model
        data = model.createData()
        return pin.computeGeneralizedGravity(model, data, np.asarray(theta, dtype=float)).copy()

    def load_torque(self, theta: np.ndarray, wrench: np.ndarray | None,
                    compensator_params: Sequence[float] | None = None, *, gravity: bool = True,
                    links: bool = False, q2: float | None = None) -> np.ndarray:
        """Load torque the joints carry, ``J_f^T W - g(theta) - M e2`` (docs/formats.md sign).

        ``wrench`` is (fx, fy, fz, mx, my, mz) on the load point in base axes;
        ``q2`` is the compensator's joint coordinate (default ``theta2 - offset2``).
        """
        theta = np.asarray(theta, dtype=float)
        nv = (self.link_model if links else self.model).nv
        tau = np.zeros(nv)
        if wrench is not None:
            jac = self.jacobians(theta, [LOAD_FRAME], links=links)[0]
            tau += jac.T @ np.asarray(wrench, dtype=float)
        if gravity and self.has_masses:
            tau -= self.gravity_torque(theta, links=links)
        if self.compensator is not None and compensator_params is not None:
            idx2 = 1
            if q2 is None:
                q2 = theta[idx2] - self.joints[1].offset
            tau[idx2] -= float(self.compensator.torque(q2, compensator_params))
        return tau

    # ------------------------------------------------------------ serialise
    def to_toml(self) -> str:
        """The description as robot.toml text (docs/formats.md §1)."""

        def num(x: float) -> str:
            return repr(float(x))

        def vec(v) -> str:
            return "[" + ", ".join(num(x) for x in v) + "]"

        if self.urdf is None:
            lines = [f'name = "{self.name}"', 'convention = "modified-dh"', f"gravity = {vec(self.gravity)}", ""]
        else:       # the URDF inline, so that the description stands alone (logs, exports)
            xml = self.urdf.xml
            literal = ("'''" not in xml and not xml.endswith("'")
                       and not any(ord(c) < 32 and c not in "\t\r\n" or ord(c) == 127 for c in xml))
            inline = (f"urdf_xml = '''\n{xml}'''" if literal       # a TOML multi-line literal string
                      else f"urdf_xml = {json.dumps(xml, ensure_ascii=True)}")   # valid TOML basic string
            lines = [f'name = "{self.name}"', f"gravity = {vec(self.gravity)}", inline, ""]
        for j in self.joints:
            lines += ["[[joint]]"]
            if j.name:
                lines.append(f'name = "{j.name}"')
            if self.urdf is None:
                lines += [f"a = {num(j.a)}", f"alpha = {num(j.alpha)}", f"d = {num(j.d)}"]
                if j.beta:
                    lines.append(f"beta = {num(j.beta)}")
            lines += [f"offset = {num(j.offset)}", f"lower = {num(j.lower)}", f"upper = {num(j.upper)}",
                      f"torque_constant = {num(j.torque_constant)}", f"mass = {num(j.mass)}",
                      f"com = {vec(j.com)}"]
            if j.stiffness is not None:
                lines.append(f"stiffness = {num(j.stiffness)}")
            lines.append("")
        lines += ["[tool]"]
        if self.urdf is not None and self.urdf.flange:
            lines.append(f'flange = "{self.urdf.flange}"')
        lines += [f"load_point = {vec(self.tool.flange_p_load)}", "[tool.markers]"]
        lines += [f"{name} = {vec(p)}" for name, p in self.tool.flange_p_markers]
        if self.compensator is not None:
            c = self.compensator
            lines += ["", "[compensator]", f'kind = "{c.kind}"', f"joint = {c.joint}"]
            lines += [f"{k} = {num(v)}" for k, v in c.geometry]
            lines += [f"{k} = {num(v)}" for k, v in c.nominal]
        return "\n".join(lines) + "\n"


    def to_urdf(self) -> str:
        """The kinematic chain and link masses as URDF text: the URDF a URDF robot
        was built from, or a DH robot written out (links ``base_link``,
        ``link1`` … ``link6``, ``link6`` being the flange; joint limits in theta =
        q + offset, so the ``[[joint]]`` tables keep their offsets)."""
        if self.urdf is not None:
            return self.urdf.xml
        placements = [_dh_placement(j) for j in self.joints]
        return dh_urdf(self.name, placements, [j.name or f"joint{i}" for i, j in enumerate(self.joints, start=1)],
                       [j.lower + j.offset for j in self.joints], [j.upper + j.offset for j in self.joints],
                       [j.mass for j in self.joints], [j.com for j in self.joints], LINK_SPHERE_RADIUS_M)


# ---------------------------------------------------------------- loading
def parse_robot(text: str, *, source: str = "<robot.toml>", base_dir: pathlib.Path | None = None) -> Robot:
    """Parse robot.toml text into a :class:`Robot`; errors name the key."""
    try:
        doc = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source=source) from None
    check_known_keys(doc, TOP_KEYS, source=source, where="")
    name = doc.get("name", "robot")
    if not isinstance(name, str) or not name:
        raise InputError(f"expected the robot's name as text, got {name!r}", source=source, column="name")
    gravity = _vec3(doc.get("gravity", [0.0, 0.0, -9.81]), source=source, column="gravity")
    if math.hypot(*gravity) > MAX_GRAVITY_M_S2:
        raise InputError(f"|gravity| = {math.hypot(*gravity):g} m/s^2; mm/s^2? gravity is m/s^2 (9.81)",
                         source=source, column="gravity")
    tables = doc.get("joint")
    if not isinstance(tables, list) or len(tables) != N_JOINTS:
        raise InputError(f"expected {N_JOINTS} [[joint]] tables", source=source, column="joint")
    for i, t in enumerate(tables, start=1):
        check_known_keys(_table(t, source=source, column=f"joint[{i}]"), JOINT_KEYS, source=source,
                    where=f"joint[{i}]")
    tool = doc.get("tool")
    if not isinstance(tool, dict):
        raise InputError("missing [tool] table", source=source, column="tool")
    check_known_keys(tool, TOOL_KEYS, source=source, where="tool")
    urdf = _urdf_source(doc, tool, source=source, base_dir=base_dir)
    if urdf is None:
        convention = doc.get("convention", "modified-dh")
        if convention != "modified-dh":
            raise InputError(f"convention must be 'modified-dh', got {convention!r}", source=source,
                             column="convention")
        chain = None
    else:
        names = []
        for i, t in enumerate(tables, start=1):
            if not isinstance(t.get("name"), str) or not t["name"]:
                raise InputError("a URDF robot's joint needs the name of its URDF joint", source=source,
                                 column=f"joint[{i}].name")
            for key in ("a", "alpha", "d", "beta"):
                if key in t:
                    raise InputError("a URDF robot takes its geometry from the URDF, not from DH parameters",
                                     source=source, column=f"joint[{i}].{key}")
            names.append(t["name"])
        chain = urdf_chain(urdf, names, source=source)
    joints = []
    for i, t in enumerate(tables, start=1):
        where = f"joint[{i}]"
        offset = _number(t, "offset", source=source, where=where, default=0.0)
        _plausible_angle(offset, source=source, column=f"{where}.offset")
        if chain is None or "lower" in t or "upper" in t:
            lower = _number(t, "lower", source=source, where=where)
            upper = _number(t, "upper", source=source, where=where)
        elif math.isnan(chain.lower[i - 1]):
            raise InputError(f"URDF joint {t['name']!r} is continuous: give lower and upper", source=source,
                             column=f"{where}.lower")
        else:                                   # URDF limits are in theta = q + offset
            lower, upper = float(chain.lower[i - 1]) - offset, float(chain.upper[i - 1]) - offset
        if max(abs(lower), abs(upper)) > 4 * math.pi:
            raise InputError(f"joint limits {lower}..{upper} look like degrees; limits are radians",
                             source=source, column=f"{where}.lower")
        xi = _number(t, "torque_constant", source=source, where=where)
        if xi == 0.0:
            raise InputError("torque_constant must be non-zero", source=source, column=f"{where}.torque_constant")
        urdf_mass = 0.0 if chain is None else float(chain.masses[i - 1])
        mass = _number(t, "mass", source=source, where=where, default=urdf_mass)
        if mass < 0:
            raise InputError("mass must be >= 0", source=source, column=f"{where}.mass")
        if mass > MAX_LINK_MASS_KG:
            raise InputError(f"{mass:g} kg is not a plausible link mass; grams? masses are kg", source=source,
                             column=f"{where}.mass")
        urdf_com = [0.0, 0.0, 0.0] if chain is None else [float(x) for x in chain.coms[i - 1]]
        if chain is None:
            geometry = {key: _number(t, key, source=source, where=where) for key in ("a", "alpha", "d")}
            _plausible_length(geometry["a"], source=source, column=f"{where}.a")
            _plausible_length(geometry["d"], source=source, column=f"{where}.d")
            _plausible_angle(geometry["alpha"], source=source, column=f"{where}.alpha")
            geometry["beta"] = _number(t, "beta", source=source, where=where, default=0.0)
            _plausible_angle(geometry["beta"], source=source, column=f"{where}.beta")
        else:
            geometry = {key: math.nan for key in ("a", "alpha", "d")}
        com = _vec3(t.get("com", urdf_com), source=source, column=f"{where}.com")
        for axis, x in zip("xyz", com):
            if abs(x) > MAX_LENGTH_M:
                raise InputError(f"the centre of mass is {x:g} m from the joint frame along {axis}; millimetres? "
                                 "positions are metres", source=source, column=f"{where}.com")
        stiffness = None
        if "stiffness" in t:
            stiffness = _number(t, "stiffness", source=source, where=where)
            if not stiffness > 0.0 or not math.isfinite(stiffness):
                raise InputError(f"stiffness = {stiffness:g} N*m/rad: a joint's stiffness is positive",
                                 source=source, column=f"{where}.stiffness")
        try:
            joints.append(JointSpec(
                **geometry, offset=offset, lower=lower, upper=upper, torque_constant=xi, mass=mass,
                com=com, stiffness=stiffness,
                name=str(t.get("name", f"joint{i}")),
            ))
        except InputError as exc:
            raise InputError(exc.detail, source=source, column=where) from None
    if "load_point" not in tool:
        raise InputError("missing required key", source=source, column="tool.load_point")
    load = _vec3(tool["load_point"], source=source, column="tool.load_point")
    if max(abs(x) for x in load) > MAX_LENGTH_M:
        raise InputError(f"the load point {load} is over {MAX_LENGTH_M:g} m from the flange; millimetres? "
                         "positions are metres", source=source, column="tool.load_point")
    markers = tool.get("markers", {})
    if not isinstance(markers, dict) or not markers:
        raise InputError("at least one marker is needed", source=source, column="tool.markers")
    marker_items = tuple((str(k), _vec3(v, source=source, column=f"tool.markers.{k}")) for k, v in markers.items())
    for mname, p in marker_items:
        if max(abs(x) for x in p) > 10.0:
            raise InputError(f"marker {mname} at {p} is over 10 m from the flange; positions are metres",
                             source=source, column=f"tool.markers.{mname}")
    comp = None
    if "compensator" in doc:
        c = _table(doc["compensator"], source=source, column="compensator")
        kind = c.get("kind")
        keys = ("a", "b", "h") if kind == "hydropneumatic" else ("a", "L", "alpha")
        if kind not in ("hydropneumatic", "spring"):
            raise InputError(f"kind must be 'hydropneumatic' or 'spring', got {kind!r}",
                             source=source, column="compensator.kind")
        check_known_keys(c, COMPENSATOR_KEYS[kind], source=source, where="compensator", what=f" for a {kind} compensator")
        geometry = tuple((k, _number(c, k, source=source, where="compensator")) for k in keys)
        params = HYDRO_PARAMS if kind == "hydropneumatic" else SPRING_PARAMS
        for k, v in geometry:
            if k == "alpha":
                _plausible_angle(v, source=source, column=f"compensator.{k}")
            else:
                _plausible_length(v, source=source, column=f"compensator.{k}")
        nominal = tuple((k, _number(c, k, source=source, where="compensator")) for k in params if k in c)
        for k, v in nominal:
            _plausible_compensator_parameter(k, v, source=source, column=f"compensator.{k}")
        joint_no = c.get("joint", 2)
        if joint_no != 2:
            raise InputError(f"compensator joint must be 2, got {joint_no!r}", source=source,
                             column="compensator.joint")
        comp = CompensatorSpec(kind=kind, joint=2, geometry=geometry, nominal=nominal)
    return Robot(name=str(name), joints=tuple(joints), gravity=gravity,
                 tool=ToolSpec(flange_p_load=load, flange_p_markers=marker_items),
                 compensator=comp, source=source, urdf=urdf)


def _plausible_compensator_parameter(name: str, value: float, *, source: str, column: str) -> None:
    """A compensator's C [N·m] and K_c [N/m] are positive (it pushes against gravity);
    its lengths l_c, s0 [m] are positive and below :data:`MAX_LENGTH_M`."""
    if value <= 0:
        unit = {"C": "N*m", "K_c": "N/m"}.get(name, "m")
        raise InputError(f"{name} = {value:g} {unit}: a compensator's {name} is positive (it balances gravity)",
                         source=source, column=column)
    if name in ("l_c", "s0"):
        _plausible_length(value, source=source, column=column)


def _urdf_source(doc: Mapping, tool: Mapping, *, source: str, base_dir: pathlib.Path | None) -> UrdfSource | None:
    """The URDF of a robot.toml (``urdf`` path or ``urdf_xml`` text), or None for a DH robot."""
    if "urdf" not in doc and "urdf_xml" not in doc:
        if "flange" in tool:
            raise InputError("only a URDF robot names its flange; a DH robot's flange is frame 6",
                             source=source, column="tool.flange")
        return None
    if "urdf" in doc and "urdf_xml" in doc:
        raise InputError("give the URDF as a path (urdf) or inline (urdf_xml), not both", source=source,
                         column="urdf_xml")
    if "convention" in doc:
        raise InputError("a URDF robot has no DH convention; remove convention", source=source,
                         column="convention")
    flange = tool.get("flange", "")
    if not isinstance(flange, str):
        raise InputError(f"expected the name of a URDF link or frame, got {flange!r}", source=source,
                         column="tool.flange")
    if "urdf_xml" in doc:
        if not isinstance(doc["urdf_xml"], str):
            raise InputError("expected the URDF text", source=source, column="urdf_xml")
        return UrdfSource(xml=doc["urdf_xml"], flange=flange)
    if not isinstance(doc["urdf"], str):
        raise InputError("expected a path to a URDF file", source=source, column="urdf")
    path = pathlib.Path(doc["urdf"])
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    xml = read_text_file(path, source=source, column="urdf", what=f"URDF {path}")
    return UrdfSource(xml=xml, path=str(path), flange=flange)


def load_robot(path: str | pathlib.Path) -> Robot:
    """Read a robot.toml file."""
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_robot(text, source=str(path), base_dir=path.parent)


def bundled_robot_path(name: str = "hh150") -> pathlib.Path:
    """Path of a robot description shipped with elastocal (``hh150``)."""
    from importlib import resources

    ref = resources.files("elastocal") / "robots" / f"{name}.toml"
    return pathlib.Path(str(ref))


def bundled_robot(name: str = "hh150") -> Robot:
    path = bundled_robot_path(name)
    if not path.exists():
        raise InputError(f"no bundled robot named {name!r}")
    return load_robot(path)
