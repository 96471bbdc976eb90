"""robot.toml (docs/formats.md §1): read into a :class:`~elastocal.model.robot.Robot`, and written back.

Any serial chain: one ``[[joint]]`` table per actuated joint, base to tip, each
revolute (default) or ``type = "prismatic"``; the geometry from a modified-DH
table or from a URDF (``urdf``/``urdf_xml`` with the chain's ``base_link`` and
``tip_link``). Every error names the key (``joint[3].lower``) and the file, and
values beyond what is plausible in the file's units (millimetres for metres,
degrees for radians, grams for kilograms) are refused with the likely mistake.
"""

from __future__ import annotations

import json
import math
import pathlib
from typing import Mapping

import tomli_w

from elastocal.errors import InputError, check_known_keys
from elastocal.formats.textfiles import read_text_file
from elastocal.model.compensator import GEOMETRY_KEYS, PARAMETER_NAMES, CompensatorSpec
from elastocal.model.kinds import CompensatorKind, JointKind
from elastocal.model.robot import JointSpec, Robot, ToolSpec
from elastocal.model.tracker_noise import TrackerNoise, parse_tracker_noise, tracker_noise_doc
from elastocal.model.urdf import UrdfChain, UrdfSource, urdf_chain

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

#: plausibility limits of robot.toml values: beyond them a value is taken as the wrong unit
#: (millimetres for metres, degrees for radians, grams for kilograms)
MAX_LENGTH_M = 10.0
MAX_ANGLE_RAD = 2 * math.pi + 1e-9
MAX_LINK_MASS_KG = 1e4
MAX_GRAVITY_M_S2 = 20.0

#: the keys robot.toml knows (docs/formats.md §1 plus elastocal's optional keys)
TOP_KEYS = ("name", "convention", "gravity", "urdf", "urdf_xml", "base_link", "tip_link", "joint", "tool",
            "compensator", "tracker")
#: robot.toml's [tracker] table: the tracker noise law a dataset's description may state
TRACKER_KEYS = ("noise",)
JOINT_KEYS = ("name", "type", "a", "alpha", "d", "theta", "beta", "offset", "lower", "upper", "torque_constant",
              "mass", "com", "stiffness", "velocity", "effort")
TOOL_KEYS = ("load_point", "markers", "flange")
COMPENSATOR_KEYS = {kind: ("kind", "joint", *GEOMETRY_KEYS[kind], *PARAMETER_NAMES[kind]) for kind in CompensatorKind}


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


def _kind(t: Mapping, *, source: str, where: str) -> JointKind:
    value = t.get("type", "revolute")
    try:
        return JointKind(value)
    except ValueError:
        raise InputError(f"type must be 'revolute' or 'prismatic', got {value!r}", source=source,
                         column=f"{where}.type") from None


# ---------------------------------------------------------------- reading
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
    if not isinstance(tables, list) or not tables:
        raise InputError("expected one [[joint]] table per actuated joint, base to tip", source=source,
                         column="joint")
    for i, t in enumerate(tables, start=1):
        check_known_keys(_table(t, source=source, column=f"joint[{i}]"), JOINT_KEYS, source=source,
                         where=f"joint[{i}]")
    tool = doc.get("tool")
    if not isinstance(tool, dict):
        raise InputError("missing [tool] table", source=source, column="tool")
    check_known_keys(tool, TOOL_KEYS, source=source, where="tool")
    urdf = _urdf_source(doc, tool, source=source, base_dir=base_dir)
    chain = None
    if urdf is None:
        convention = doc.get("convention", "modified-dh")
        if convention != "modified-dh":
            raise InputError(f"convention must be 'modified-dh', got {convention!r}", source=source,
                             column="convention")
    else:
        chain = urdf_chain(urdf, _urdf_joint_names(tables, source=source), source=source)
    joints = tuple(_joint(t, i, chain, source=source) for i, t in enumerate(tables, start=1))
    return Robot(name=str(name), joints=joints, gravity=gravity, tool=_tool(tool, source=source),
                 compensator=_compensator(doc, source=source), source=source, urdf=urdf,
                 tracker_noise=_tracker_noise(doc, source=source))


def _tracker_noise(doc: Mapping, *, source: str) -> TrackerNoise | None:
    """robot.toml's ``[tracker] noise`` (the syntax of cell.toml's, docs/cell-config.md), or None."""
    if "tracker" not in doc:
        return None
    tracker = _table(doc["tracker"], source=source, column="tracker")
    check_known_keys(tracker, TRACKER_KEYS, source=source, where="tracker")
    return parse_tracker_noise(tracker["noise"], source=source) if "noise" in tracker else None


def _urdf_joint_names(tables: list, *, source: str) -> list[str]:
    names = []
    for i, t in enumerate(tables, start=1):
        if not isinstance(t.get("name"), str) or not t["name"]:
            raise InputError("a URDF robot's joint needs the name of its URDF joint", source=source,
                             column=f"joint[{i}].name")
        for key in ("a", "alpha", "d", "beta", "theta"):
            if key in t:
                raise InputError("a URDF robot takes its geometry from the URDF, not from DH parameters",
                                 source=source, column=f"joint[{i}].{key}")
        names.append(t["name"])
    return names


def _limits(t: Mapping, i: int, kind: JointKind, offset: float, chain: UrdfChain | None, *,
            source: str) -> tuple[float, float]:
    where = f"joint[{i}]"
    if chain is None or "lower" in t or "upper" in t:
        lower = _number(t, "lower", source=source, where=where)
        upper = _number(t, "upper", source=source, where=where)
    elif math.isnan(chain.lower[i - 1]):
        raise InputError(f"URDF joint {t['name']!r} is continuous: give lower and upper", source=source,
                         column=f"{where}.lower")
    else:                                   # URDF limits are in the joint variable q + offset
        lower, upper = float(chain.lower[i - 1]) - offset, float(chain.upper[i - 1]) - offset
    if kind is JointKind.REVOLUTE and max(abs(lower), abs(upper)) > 4 * math.pi:
        raise InputError(f"joint limits {lower}..{upper} look like degrees; limits are radians",
                         source=source, column=f"{where}.lower")
    if kind is JointKind.PRISMATIC and max(abs(lower), abs(upper)) > MAX_LENGTH_M * 10:
        raise InputError(f"joint limits {lower}..{upper} look like millimetres; a prismatic joint's limits are "
                         "metres", source=source, column=f"{where}.lower")
    return lower, upper


def _geometry(t: Mapping, i: int, kind: JointKind, chain: UrdfChain | None, *, source: str) -> dict[str, float]:
    where = f"joint[{i}]"
    if chain is not None:
        return {key: math.nan for key in ("a", "alpha", "d", "theta")}
    if kind is JointKind.PRISMATIC:
        if "d" in t:
            raise InputError("a prismatic joint's d is its variable (d = q + offset); give theta, the fixed angle",
                             source=source, column=f"{where}.d")
        geometry = {key: _number(t, key, source=source, where=where) for key in ("a", "alpha")}
        geometry["d"] = 0.0
        geometry["theta"] = _number(t, "theta", source=source, where=where, default=0.0)
        _plausible_angle(geometry["theta"], source=source, column=f"{where}.theta")
    else:
        if "theta" in t:
            raise InputError("a revolute joint's theta is its variable (theta = q + offset); theta is for "
                             "prismatic joints", source=source, column=f"{where}.theta")
        geometry = {key: _number(t, key, source=source, where=where) for key in ("a", "alpha", "d")}
        _plausible_length(geometry["d"], source=source, column=f"{where}.d")
    _plausible_length(geometry["a"], source=source, column=f"{where}.a")
    _plausible_angle(geometry["alpha"], source=source, column=f"{where}.alpha")
    geometry["beta"] = _number(t, "beta", source=source, where=where, default=0.0)
    _plausible_angle(geometry["beta"], source=source, column=f"{where}.beta")
    return geometry


def _joint(t: Mapping, i: int, chain: UrdfChain | None, *, source: str) -> JointSpec:
    where = f"joint[{i}]"
    kind = _kind(t, source=source, where=where)
    if chain is not None and "type" not in t:
        kind = chain.kinds[i - 1]
    offset = _number(t, "offset", source=source, where=where, default=0.0)
    if kind is JointKind.REVOLUTE:
        _plausible_angle(offset, source=source, column=f"{where}.offset")
    else:
        _plausible_length(offset, source=source, column=f"{where}.offset")
    lower, upper = _limits(t, i, kind, offset, chain, source=source)
    xi = None
    if "torque_constant" in t:
        xi = _number(t, "torque_constant", source=source, where=where)
        if xi == 0.0:
            raise InputError("torque_constant must be non-zero", source=source, column=f"{where}.torque_constant")
    mass = _number(t, "mass", source=source, where=where, default=0.0 if chain is None else float(chain.masses[i - 1]))
    if mass < 0:
        raise InputError("mass must be >= 0", source=source, column=f"{where}.mass")
    if mass > MAX_LINK_MASS_KG:
        raise InputError(f"{mass:g} kg is not a plausible link mass; grams? masses are kg", source=source,
                         column=f"{where}.mass")
    urdf_com = [0.0, 0.0, 0.0] if chain is None else [float(x) for x in chain.coms[i - 1]]
    com = _vec3(t.get("com", urdf_com), source=source, column=f"{where}.com")
    for axis, x in zip("xyz", com):
        if abs(x) > MAX_LENGTH_M:
            raise InputError(f"the centre of mass is {x:g} m from the joint frame along {axis}; millimetres? "
                             "positions are metres", source=source, column=f"{where}.com")
    stiffness = None
    if "stiffness" in t:
        stiffness = _number(t, "stiffness", source=source, where=where)
        if not stiffness > 0.0:
            raise InputError(f"stiffness = {stiffness:g} {kind.stiffness_unit}: a joint's stiffness is positive",
                             source=source, column=f"{where}.stiffness")
    geometry = _geometry(t, i, kind, chain, source=source)
    limits = _speed_effort(t, i, kind, chain, source=source)
    try:
        return JointSpec(**geometry, offset=offset, lower=lower, upper=upper,
                         torque_constant=xi, mass=mass, com=com, stiffness=stiffness, kind=kind,
                         name=str(t.get("name", f"joint{i}")), **limits)
    except InputError as exc:
        raise InputError(exc.detail, source=source, column=where) from None


def _speed_effort(t: Mapping, i: int, kind: JointKind, chain: UrdfChain | None, *,
                  source: str) -> dict[str, float | None]:
    """The joint's ``velocity`` and ``effort`` limits (optional; a URDF robot's default: its URDF's)."""
    out: dict[str, float | None] = {}
    for key, unit in (("velocity", kind.unit + "/s"), ("effort", "N·m" if kind is JointKind.REVOLUTE else "N")):
        value = None
        if key in t:
            value = _number(t, key, source=source, where=f"joint[{i}]")
            if not value > 0.0:
                raise InputError(f"{key} = {value:g} {unit}: a joint's {key} limit is positive", source=source,
                                 column=f"joint[{i}].{key}")
        elif chain is not None and math.isfinite(getattr(chain, key)[i - 1]):
            value = float(getattr(chain, key)[i - 1])
        out[key] = value
    return out


def _tool(tool: Mapping, *, source: str) -> ToolSpec:
    if "load_point" not in tool:
        raise InputError("missing required key", source=source, column="tool.load_point")
    load = _vec3(tool["load_point"], source=source, column="tool.load_point")
    if max(abs(x) for x in load) > MAX_LENGTH_M:
        raise InputError(f"the load point {load} is over {MAX_LENGTH_M:g} m from the flange; millimetres? "
                         "positions are metres", source=source, column="tool.load_point")
    markers = tool.get("markers", {})
    if not isinstance(markers, dict) or not markers:
        raise InputError("at least one marker is needed", source=source, column="tool.markers")
    items = tuple((str(k), _vec3(v, source=source, column=f"tool.markers.{k}")) for k, v in markers.items())
    for mname, p in items:
        if max(abs(x) for x in p) > MAX_LENGTH_M:
            raise InputError(f"marker {mname} at {p} is over 10 m from the flange; positions are metres",
                             source=source, column=f"tool.markers.{mname}")
    return ToolSpec(flange_p_load=load, flange_p_markers=items)


def _compensator(doc: Mapping, *, source: str) -> CompensatorSpec | None:
    if doc.get("compensator") is None:      # robot.toml's [compensator] table
        return None
    c = _table(doc["compensator"], source=source, column="compensator")
    try:
        kind = CompensatorKind(c.get("kind"))
    except ValueError:
        raise InputError(f"kind must be 'hydropneumatic' or 'spring', got {c.get('kind')!r}",
                         source=source, column="compensator.kind") from None
    check_known_keys(c, COMPENSATOR_KEYS[kind], source=source, where="compensator", what=f" for a {kind} compensator")
    geometry = tuple((k, _number(c, k, source=source, where="compensator")) for k in GEOMETRY_KEYS[kind])
    for k, v in geometry:
        if k == "alpha":
            _plausible_angle(v, source=source, column=f"compensator.{k}")
        else:
            _plausible_length(v, source=source, column=f"compensator.{k}")
    nominal = tuple((k, _number(c, k, source=source, where="compensator")) for k in PARAMETER_NAMES[kind] if k in c)
    for k, v in nominal:
        _plausible_compensator_parameter(k, v, source=source, column=f"compensator.{k}")
    joint_no = c.get("joint", 2)
    n = len(doc["joint"])
    if isinstance(joint_no, bool) or not isinstance(joint_no, int) or not 1 <= joint_no <= n:
        raise InputError(f"compensator joint must be a joint number 1..{n}, got {joint_no!r}", source=source,
                         column="compensator.joint")
    return CompensatorSpec(kind=kind, joint=joint_no, geometry=geometry, nominal=nominal)


def _plausible_compensator_parameter(name: str, value: float, *, source: str, column: str) -> None:
    """A compensator's C [N·m] and K_c [N/m] are positive (it pushes against gravity);
    its lengths l_c, s0 [m] are positive and below :data:`MAX_LENGTH_M`."""
    if value <= 0:
        unit = {"C": "N*m", "K_c": "N/m"}.get(name, "m")
        raise InputError(f"{name} = {value:g} {unit}: a compensator's {name} is positive (it balances gravity)",
                         source=source, column=column)
    if name in ("l_c", "s0"):
        _plausible_length(value, source=source, column=column)


def _link_name(doc: Mapping, tool: Mapping, key: str, *, source: str) -> str:
    value = doc.get(key, "")
    if not isinstance(value, str):
        raise InputError(f"expected the name of a URDF link, got {value!r}", source=source, column=key)
    if key == "tip_link" and "flange" in tool:       # the older spelling: [tool] flange
        if value:
            raise InputError("give the chain's tip as tip_link or as [tool] flange, not both", source=source,
                             column="tool.flange")
        value = tool["flange"]
        if not isinstance(value, str):
            raise InputError(f"expected the name of a URDF link or frame, got {value!r}", source=source,
                             column="tool.flange")
    return value


def _urdf_source(doc: Mapping, tool: Mapping, *, source: str, base_dir: pathlib.Path | None) -> UrdfSource | None:
    """The URDF of a robot.toml (``urdf`` path or ``urdf_xml`` text), or None for a DH robot."""
    if "urdf" not in doc and "urdf_xml" not in doc:
        for key in ("base_link", "tip_link"):
            if key in doc:
                raise InputError(f"only a URDF robot names its {key}; a DH robot's chain is its [[joint]] tables",
                                 source=source, column=key)
        if "flange" in tool:
            raise InputError("only a URDF robot names its flange; a DH robot's flange is the last joint's frame",
                             source=source, column="tool.flange")
        return None
    if "urdf" in doc and "urdf_xml" in doc:
        raise InputError("give the URDF as a path (urdf) or inline (urdf_xml), not both", source=source,
                         column="urdf_xml")
    if "convention" in doc:
        raise InputError("a URDF robot has no DH convention; remove convention", source=source,
                         column="convention")
    links = {"base_link": _link_name(doc, tool, "base_link", source=source),
             "tip_link": _link_name(doc, tool, "tip_link", source=source),
             "tip_column": "tool.flange" if "flange" in tool else "tip_link"}
    if "urdf_xml" in doc:
        if not isinstance(doc["urdf_xml"], str):
            raise InputError("expected the URDF text", source=source, column="urdf_xml")
        return UrdfSource(xml=doc["urdf_xml"], **links)
    if not isinstance(doc["urdf"], str):
        raise InputError("expected a path to a URDF file", source=source, column="urdf")
    path = pathlib.Path(doc["urdf"])
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    xml = read_text_file(path, source=source, column="urdf", what=f"URDF {path}")
    return UrdfSource(xml=xml, path=str(path), **links)


def load_robot(path: str | pathlib.Path) -> Robot:
    """Read a robot.toml file."""
    path = pathlib.Path(path)
    text = read_text_file(path)
    return parse_robot(text, source=str(path), base_dir=path.parent)


# ---------------------------------------------------------------- writing
def _num(x: float) -> str:
    return repr(float(x))


def _text(key: str, value: str) -> str:
    """``key = "value"``, quoted and escaped as TOML wants."""
    return tomli_w.dumps({key: value}).rstrip("\n")


def _vec(v) -> str:
    return "[" + ", ".join(_num(x) for x in v) + "]"


def _urdf_lines(robot: Robot) -> list[str]:
    """The URDF inline, so that the description stands alone (logs, exports)."""
    urdf = robot.urdf
    xml = urdf.xml
    literal = ("'''" not in xml and not xml.endswith("'")
               and not any(ord(c) < 32 and c not in "\t\r\n" or ord(c) == 127 for c in xml))
    inline = (f"urdf_xml = '''\n{xml}'''" if literal       # a TOML multi-line literal string
              else f"urdf_xml = {json.dumps(xml, ensure_ascii=True)}")   # valid TOML basic string
    lines = [_text("name", robot.name), f"gravity = {_vec(robot.gravity)}"]
    if urdf.base_link:
        lines.append(_text("base_link", urdf.base_link))
    return lines + [inline, ""]


def robot_toml(robot: Robot) -> str:
    """The description as robot.toml text (docs/formats.md §1).

    Written line by line, not by tomli-w: a calibration file embeds this text as
    its ``robot_description``, so its bytes are part of every calibration file made
    so far, and tomli-w would spread each 3-vector over five lines. Text values
    (names, links) are quoted and escaped by tomli-w."""
    if robot.urdf is None:
        lines = [_text("name", robot.name), 'convention = "modified-dh"', f"gravity = {_vec(robot.gravity)}", ""]
    else:
        lines = _urdf_lines(robot)
    for j in robot.joints:
        lines += ["[[joint]]"]
        if j.name:
            lines.append(_text("name", j.name))
        if j.kind is JointKind.PRISMATIC:
            lines.append('type = "prismatic"')
        if robot.urdf is None:
            lines += [f"a = {_num(j.a)}", f"alpha = {_num(j.alpha)}"]
            lines.append(f"theta = {_num(j.theta)}" if j.kind is JointKind.PRISMATIC else f"d = {_num(j.d)}")
            if j.beta:
                lines.append(f"beta = {_num(j.beta)}")
        lines += [f"offset = {_num(j.offset)}", f"lower = {_num(j.lower)}", f"upper = {_num(j.upper)}"]
        if j.torque_constant is not None:
            lines.append(f"torque_constant = {_num(j.torque_constant)}")
        lines += [f"mass = {_num(j.mass)}", f"com = {_vec(j.com)}"]
        if j.stiffness is not None:
            lines.append(f"stiffness = {_num(j.stiffness)}")
        lines += [f"{key} = {_num(getattr(j, key))}" for key in ("velocity", "effort") if getattr(j, key) is not None]
        lines.append("")
    lines += ["[tool]"]
    if robot.urdf is not None and robot.urdf.tip_link:
        lines.append(_text("flange", robot.urdf.tip_link))
    lines += [f"load_point = {_vec(robot.tool.flange_p_load)}", "[tool.markers]"]
    lines += [f"{name} = {_vec(p)}" for name, p in robot.tool.flange_p_markers]
    if robot.compensator is not None:
        c = robot.compensator
        lines += ["", "[compensator]", f'kind = "{c.kind.value}"', f"joint = {c.joint}"]
        lines += [f"{k} = {_num(v)}" for k, v in c.geometry]
        lines += [f"{k} = {_num(v)}" for k, v in c.nominal]
    if robot.tracker_noise is not None:
        n = tracker_noise_doc(robot.tracker_noise)
        lines += ["", "[tracker]", f"noise = {{ along = {_vec(n['along'])}, across = {_vec(n['across'])}, "
                  f"k = {_num(n['k'])} }}"]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- shipped robots
def bundled_robot_path(name: str = "hh150") -> pathlib.Path:
    """Path of a robot description shipped with elastocal (``hh150``, ``hh150_urdf``, ...)."""
    from importlib import resources

    ref = resources.files("elastocal") / "robots" / f"{name}.toml"
    return pathlib.Path(str(ref))


def bundled_robot(name: str = "hh150") -> Robot:
    """A robot description shipped with elastocal."""
    path = bundled_robot_path(name)
    if not path.exists():
        raise InputError(f"no bundled robot named {name!r}")
    return load_robot(path)
