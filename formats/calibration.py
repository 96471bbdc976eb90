"""Calibration JSON (docs/formats.md §4): write and read, as frozen typed results.

A :class:`Calibration` holds :class:`CalibratedParameter` values (name, value in
its SI unit, std, unit, and identify's optional ``determined``/``note`` marks),
its :class:`Residual` and the :class:`DataFile` records of the data it was
identified from. Fields of a parameter, the residual or a data record that this
version does not know are kept, as JSON text, and written back after the known
ones (a calibration read and recorded in the history keeps them); the known
fields are written in the order of the format (``value, std, unit, determined,
note``), numbers as floats in their SI unit.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import pathlib
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

from elastocal.errors import InputError
from elastocal.formats.textfiles import read_text_file
from elastocal.model.kinds import TorqueSource, expect

FORMAT = "elastocal.calibration/1"
#: ``friction_sign`` of a calibration holding friction (elastocal extension of docs/formats.md §4):
#: ``xi i = tau_load + f sign(dq)``, the drive supplies friction in the direction of motion, so
#: real friction is positive. Files without it were written under the old run model
#: ``xi i = tau_load - f sign(dq)``: their friction is read with the sign turned, and said in a note.
FRICTION_SIGN = "direction_of_motion"
#: the torque a calibration was identified from: motor currents or the measured wrench
TORQUES = tuple(t.value for t in TorqueSource)
#: the joint stiffness of a six-axis arm; a robot of N joints has k1..kN (:func:`stiffness_names`)
STIFFNESS_NAMES = tuple(f"k{j}" for j in range(1, 7))


def stiffness_names(n_joints: int) -> tuple[str, ...]:
    return tuple(f"k{j}" for j in range(1, n_joints + 1))


def is_stiffness_name(name: str) -> bool:
    """``k1``, ``k2``, ...: a joint's stiffness."""
    return len(name) > 1 and name[0] == "k" and name[1:].isdigit() and name[1] != "0"


def prismatic_unit(revolute: str) -> str:
    """The unit a per-joint parameter has on a prismatic joint, from its revolute unit: newtons
    for newton-metres, metres for radians (N*m/rad -> N/m, rad/(N*m) -> m/N, N*m*s/rad -> N*s/m)."""
    return revolute.replace("N*m", "N").replace("rad", "m")


def file_sha256(path: str | pathlib.Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _extra(doc: Mapping[str, Any], known: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """The fields of ``doc`` not in ``known``, as (key, JSON text): kept frozen, written back as they were."""
    return tuple((str(k), json.dumps(v)) for k, v in doc.items() if k not in known)


def _with_extra(out: dict, extra: tuple[tuple[str, str], ...]) -> dict:
    for k, text in extra:
        out.setdefault(k, json.loads(text))
    return out


@dataclass(frozen=True)
class CalibratedParameter:
    """One calibrated parameter (docs/formats.md §4): its value [SI unit] and standard deviation."""

    name: str
    value: float
    std: float | None = None
    unit: str | None = None
    #: identify's mark (identify/evidence.py): False for a stiffness the data did not determine
    #: (None: the file says nothing, i.e. determined)
    determined: bool | None = None
    #: why it is not determined (or why it is sensitive)
    note: str | None = None
    extra: tuple[tuple[str, str], ...] = field(default=(), repr=False)
    #: identify's mark: True for a parameter the absolute fit moved by more than 2 std from the
    #: deflection-only fit while leaving an unexplained residual (identify/evidence.py); None: no mark
    sensitive: bool | None = None

    FIELDS = ("value", "std", "unit", "determined", "note", "sensitive")

    @property
    def is_result(self) -> bool:
        """Not marked ``"determined": false``."""
        return self.determined is not False

    @property
    def std_or_zero(self) -> float:
        """The standard deviation, 0 when the file gives none (or a non-finite one)."""
        return self.std if self.std is not None and math.isfinite(self.std) else 0.0

    def to_json(self) -> dict:
        out: dict = {"value": self.value}
        if self.std is not None:
            out["std"] = self.std
        if self.unit is not None:
            out["unit"] = self.unit
        if self.determined is not None:
            out["determined"] = self.determined
        if self.note is not None:
            out["note"] = self.note
        if self.sensitive is not None:
            out["sensitive"] = self.sensitive
        return _with_extra(out, self.extra)


@dataclass(frozen=True)
class Residual:
    """What the calibrated model left [m]: rms, max, the number of components and, optionally,
    what noise alone leaves (``noise_floor``)."""

    rms: float | None = None
    max: float | None = None
    n: int | None = None
    noise_floor: float | None = None
    extra: tuple[tuple[str, str], ...] = field(default=(), repr=False)

    FIELDS = ("rms", "max", "n", "noise_floor")

    def to_json(self) -> dict:
        out = {k: getattr(self, k) for k in self.FIELDS if getattr(self, k) is not None}
        return _with_extra(out, self.extra)


@dataclass(frozen=True)
class DataFile:
    """A file the calibration was identified from, with its SHA-256."""

    path: str
    sha256: str | None = None
    extra: tuple[tuple[str, str], ...] = field(default=(), repr=False)

    def to_json(self) -> dict:
        out: dict = {"path": self.path}
        if self.sha256 is not None:
            out["sha256"] = self.sha256
        return _with_extra(out, self.extra)


@dataclass(frozen=True)
class Calibration:
    robot: str
    created: str
    model: tuple[str, ...]
    torque: TorqueSource
    parameters: tuple[CalibratedParameter, ...]
    residual: Residual = Residual()
    data: tuple[DataFile, ...] = ()
    #: the file it was read from, for errors (not part of the calibration)
    source: str = field(default="", compare=False)
    #: optional (elastocal extension of docs/formats.md §4): the absolute comparison of
    #: the fit, rms/max/n/noise_floor [m] of the marker positions after the registration
    absolute_residual: Residual | None = None
    #: optional (elastocal extension): the robot.toml text the calibration was
    #: identified against, so that `elastocal robot` can write the calibrated one
    robot_description: str | None = None
    #: optional (elastocal extension): the parameters of the model the data did not determine
    #: (``identify --json``'s ``unidentifiable``): not held, so read as absent (a joint stiffness
    #: not held is a rigid joint where the calibration is used)
    unidentifiable: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        expect(TorqueSource, self.torque, "torque")
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise InputError("a parameter is named twice", source=self.source or None, column="parameters")

    @property
    def names(self) -> tuple[str, ...]:
        """The parameter names, in the calibration's order."""
        return tuple(p.name for p in self.parameters)

    def has(self, name: str) -> bool:
        return any(p.name == name for p in self.parameters)

    def find(self, name: str) -> CalibratedParameter | None:
        """The parameter ``name``, None when the calibration does not hold it."""
        return next((p for p in self.parameters if p.name == name), None)

    def value(self, name: str) -> float:
        p = self.find(name)
        if p is None:
            raise InputError(f"the calibration has no parameter {name!r}", source=self.source or None)
        return p.value

    @property
    def n_stiffness(self) -> int:
        """How many joint stiffnesses (k1..kN) the calibration holds."""
        return sum(1 for p in self.parameters if is_stiffness_name(p.name))

    def stiffness(self) -> list[float]:
        return [self.value(k) for k in stiffness_names(self.n_stiffness)]

    def undetermined(self) -> tuple[str, ...]:
        """Names of the parameters marked not determined (identify/evidence.py)."""
        return tuple(p.name for p in self.parameters if not p.is_result)

    def to_json(self) -> dict:
        out = {"format": FORMAT, "robot": self.robot, "created": self.created, "model": list(self.model),
               "torque": self.torque,
               **({"friction_sign": FRICTION_SIGN} if any(is_friction(p.name) for p in self.parameters) else {}),
               "parameters": {p.name: p.to_json() for p in self.parameters},
               "residual": self.residual.to_json(), "data": [d.to_json() for d in self.data],
               **({} if self.absolute_residual is None else {"absolute_residual": self.absolute_residual.to_json()}),
               **({} if self.robot_description is None else {"robot_description": self.robot_description}),
               **({"unidentifiable": list(self.unidentifiable)} if self.unidentifiable else {})}
        return out


def make_calibration(robot_name: str, *, model: Sequence[str], torque: TorqueSource,
                     parameters: Sequence[CalibratedParameter], residual: Residual,
                     absolute_residual: Residual | None = None, data_paths: Sequence[str | pathlib.Path] = (),
                     created: str | None = None, robot_description: str | None = None,
                     unidentifiable: Sequence[str] = ()) -> Calibration:
    """A Calibration from a fit's typed results and the files it used; each parameter checked
    and in its SI unit as the reader would have it (what the reader would refuse is not written)."""
    created = created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")
    data = tuple(DataFile(path=str(p), sha256=file_sha256(p)) for p in data_paths)
    source = str(data_paths[0]) if data_paths else "the fit"
    checked = []
    for p in parameters:
        try:
            checked.append(_checked(p, source))
        except InputError as exc:
            raise InputError(f"the fit gives {p.name}: {exc.detail}; not a calibration (the robot description's "
                             "torque constants and geometry, the data's units?)", source=source) from None
    return Calibration(robot=robot_name, created=created, model=tuple(model), torque=torque,
                       parameters=tuple(checked), residual=residual, data=data, absolute_residual=absolute_residual,
                       robot_description=robot_description, unidentifiable=tuple(unidentifiable))


def calibration_from_fit(robot_name: str, fit_json: dict, data_paths: Sequence[str | pathlib.Path] = (),
                         created: str | None = None, robot_description: str | None = None) -> Calibration:
    """A Calibration from an ``identify --json`` object (a file's, at the edge) and the files it used."""
    created = created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")
    res = fit_json["residual"]
    residual = Residual(rms=res.get("rms"), max=res.get("max"), n=res.get("n"),
                        noise_floor=fit_json.get("noise_floor"))   # optional extension: what noise alone leaves [m]
    absolute = None
    if fit_json.get("absolute_residual"):        # optional extension: the absolute comparison [m]
        a = fit_json["absolute_residual"]
        absolute = Residual(rms=a.get("rms"), max=a.get("max"), n=a.get("n"),
                            noise_floor=fit_json.get("absolute_noise_floor"))
    data = tuple(DataFile(path=str(p), sha256=file_sha256(p)) for p in data_paths)
    source = str(data_paths[0]) if data_paths else "the fit"
    parameters = []
    for name, p in fit_json["parameters"].items():   # what the reader would refuse is not written
        try:
            parameters.append(_parameter(name, p, source))
        except InputError as exc:
            raise InputError(f"the fit gives {name}: {exc.detail}; not a calibration (the robot description's "
                             "torque constants and geometry, the data's units?)", source=source) from None
    return Calibration(robot=robot_name, created=created, model=tuple(fit_json["model"]),
                       torque=TorqueSource(fit_json.get("torque", "current")), parameters=tuple(parameters),
                       residual=residual, data=data, absolute_residual=absolute,
                       robot_description=robot_description,
                       unidentifiable=tuple(str(n) for n in fit_json.get("unidentifiable", ())))


def write_calibration(path: str | pathlib.Path, cal: Calibration) -> None:
    pathlib.Path(path).write_text(json.dumps(cal.to_json(), indent=2) + "\n", encoding="utf-8")


#: a joint stiffness whose size is outside this range is not one of a robot joint [N·m/rad]
#: (its sign is judged where it is used: compensation refuses a negative one)
STIFFNESS_RANGE = (1.0, 1e12)
#: no calibrated value is larger than this, in its SI unit
MAX_VALUE = 1e30


def parameter_unit(name: str) -> str | None:
    """The SI unit of a calibration parameter (docs/formats.md §4, docs/cli.md's effect table), None if unknown."""
    from elastocal.model.effects import ALL_EFFECTS, get_effect
    from elastocal.model.compensator import HYDRO_UNITS, SPRING_UNITS

    if is_stiffness_name(name):
        return "N*m/rad"
    if name in HYDRO_UNITS or name in SPRING_UNITS:
        return {**HYDRO_UNITS, **SPRING_UNITS}[name]
    kind = name.rstrip("0123456789")        # kinematic_errors (identify/kinematics.py)
    if kind != name and kind in ("dq", "dalpha", "dbeta", "dtheta"):
        return "rad"
    if kind != name and kind in ("da", "dd") or name.startswith(("dx_", "dy_", "dz_")):
        return "m"
    joint_prefix = name.rstrip("0123456789")
    for effect in ALL_EFFECTS:
        e = get_effect(effect)
        if name in e.parameters:
            return e.units[e.parameters.index(name)]
        if joint_prefix != name and f"{joint_prefix}1" in e.parameters and name[len(joint_prefix)] != "0":
            return e.units[e.parameters.index(f"{joint_prefix}1")]     # joint 7 and beyond: as joint 1
            return e.units[e.parameters.index(name)]
    return None


def is_friction(name: str) -> bool:
    """A friction parameter of the run model (fc1.., fv1.., fl1..: every "uv/vu" effect's)."""
    from elastocal.model.effects import get_effect, run_effects

    kind = name.rstrip("0123456789")
    return kind != name and any(get_effect(e).run_prefix == kind for e in run_effects("uv/vu"))


def _old_friction_sign(parameters: tuple[CalibratedParameter, ...]) -> tuple[CalibratedParameter, ...]:
    """Friction written under the old run model ``xi i = tau_load - f sign(dq)``, turned to the
    physical sign (the drive supplies friction in the direction of motion), with a note."""
    from dataclasses import replace

    out = []
    for p in parameters:
        if is_friction(p.name):
            said = (f"sign converted: written as {p.value:g} under the old run model "
                    "xi i = tau_load - f sign(dq); the drive supplies friction in the direction of motion")
            p = replace(p, value=-p.value, note=said if p.note is None else f"{p.note}; {said}")
        out.append(p)
    return tuple(out)


def _number_or_none(p: dict, key: str) -> float | None:
    v = p.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(key)
    return float(v)


def _parameter(name: str, p: object, src: str) -> CalibratedParameter:
    """One parameter, checked and in its SI unit: a finite value, a std >= 0 (or none), a known unit
    (a value given in another unit of the same kind, N*m/deg for N*m/rad, is converted)."""
    where = f"parameters.{name}"
    if not isinstance(p, dict):
        raise InputError(f"expected an object with value, std and unit, got {p!r}", source=src, column=where)
    try:
        value = _number_or_none(p, "value")
        std = _number_or_none(p, "std")
    except ValueError as exc:
        raise InputError(f"{exc.args[0]} must be a finite number, got {p.get(exc.args[0])!r}", source=src,
                         column=f"{where}.{exc.args[0]}") from None
    if value is None:
        raise InputError(f"parameter {name} has no finite value", source=src, column=where)
    unit = p.get("unit")
    if unit is not None and not isinstance(unit, str):
        raise InputError(f"expected a unit text, got {unit!r}", source=src, column=f"{where}.unit")
    determined, note = p.get("determined"), p.get("note")
    if determined is not None and not isinstance(determined, bool):
        raise InputError(f"expected true or false, got {determined!r}", source=src, column=f"{where}.determined")
    if note is not None and not isinstance(note, str):
        raise InputError(f"expected a text, got {note!r}", source=src, column=f"{where}.note")
    sensitive = p.get("sensitive")
    if sensitive is not None and not isinstance(sensitive, bool):
        raise InputError(f"expected true or false, got {sensitive!r}", source=src, column=f"{where}.sensitive")
    return _checked(CalibratedParameter(name=name, value=value, std=std, unit=unit, determined=determined,
                                        note=note, extra=_extra(p, CalibratedParameter.FIELDS),
                                        sensitive=sensitive), src)


def _checked(p: CalibratedParameter, src: str) -> CalibratedParameter:
    """``p`` checked and in its SI unit: a finite value, a std >= 0 (or none), a known unit (a value
    given in another unit of the same kind, N*m/deg for N*m/rad, is converted)."""
    from elastocal.model.units import UnitError, conversion, parse_unit

    name, value, std, unit = p.name, float(p.value), p.std, p.unit
    where = f"parameters.{name}"
    if not math.isfinite(value):
        raise InputError(f"parameter {name} has no finite value", source=src, column=where)
    if std is not None and not (std >= 0):
        raise InputError(f"a standard deviation is >= 0, got {std!r}", source=src, column=f"{where}.std")
    target = parameter_unit(name)
    if unit is not None and target is not None and isinstance(unit, str) and name[-1].isdigit():
        # a per-joint parameter of a prismatic joint (k7 in N/m): its own unit
        alternative = prismatic_unit(target)
        try:
            if alternative != target and parse_unit(unit)[1] == parse_unit(alternative)[1]:
                target = alternative
        except UnitError:
            pass
    if unit is not None:
        try:
            factor = conversion(unit, target) if target is not None else (parse_unit(unit), 1.0)[1]
        except UnitError as exc:
            hint = f"; {name} is in {target}" if target is not None else ""
            raise InputError(f"{exc}{hint}", source=src, column=f"{where}.unit") from None
        if factor != 1.0:
            value *= factor
            std = None if std is None else std * factor
            unit = target
    if target in ("N*m/rad", "N/m") and not STIFFNESS_RANGE[0] <= abs(value) <= STIFFNESS_RANGE[1]:
        raise InputError(f"{value:g} {target} is not a plausible joint stiffness (|k| between "
                         f"{STIFFNESS_RANGE[0]:g} and {STIFFNESS_RANGE[1]:g})", source=src, column=f"{where}.value")
    if not abs(value) <= MAX_VALUE:
        raise InputError(f"{value:g} is not a plausible value", source=src, column=f"{where}.value")
    if std is not None and not std <= MAX_VALUE:
        raise InputError(f"{std:g} is not a plausible standard deviation", source=src, column=f"{where}.std")
    return replace(p, value=float(value), std=std, unit=unit)


def read_calibration(path: str | pathlib.Path) -> Calibration:
    path = pathlib.Path(path)
    text = read_text_file(path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}", source=str(path)) from None
    return calibration_from_json(doc, str(path))


def _residual(doc: object, src: str, where: str) -> Residual:
    if not isinstance(doc, dict):
        raise InputError(f"expected an object, got {doc!r}", source=src, column=where)
    for key in Residual.FIELDS:
        v = doc.get(key)
        if v is None:
            continue
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
        if not ok or (key == "n" and v != int(v)):
            what = "a count" if key == "n" else "a finite number >= 0 [m]"
            raise InputError(f"expected {what}, got {v!r}", source=src, column=f"{where}.{key}")
    number = {k: (None if doc.get(k) is None else float(doc[k])) for k in ("rms", "max", "noise_floor")}
    return Residual(**number, n=None if doc.get("n") is None else int(doc["n"]),
                    extra=_extra(doc, Residual.FIELDS))


def _data_file(doc: dict, src: str, k: int) -> DataFile:
    path, sha = doc.get("path", ""), doc.get("sha256")
    if not isinstance(path, str) or (sha is not None and not isinstance(sha, str)):
        raise InputError("expected a path and a sha256 text", source=src, column=f"data[{k}]")
    return DataFile(path=path, sha256=sha, extra=_extra(doc, ("path", "sha256")))


def calibration_from_json(doc: object, source: str) -> Calibration:
    """The calibration a JSON document holds, checked (one error naming ``source`` and the key)."""
    src = source
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not an elastocal calibration (format must be {FORMAT!r})", source=src,
                         column="format")
    robot = doc.get("robot")
    if not isinstance(robot, str) or not robot.strip():
        what = "missing" if robot is None else f"expected the robot's name, got {robot!r}"
        raise InputError(f"{what}: the calibration must name its robot (docs/formats.md §4)", source=src, column="robot")
    model = doc.get("model", ["joint_stiffness"])
    if not isinstance(model, list) or not model or not all(isinstance(m, str) and m for m in model):
        raise InputError(f"expected a list of effect names, got {model!r}", source=src, column="model")
    from elastocal.model.effects import ALL_EFFECTS

    for name in model:
        if name not in ALL_EFFECTS:
            raise InputError(f"unknown effect {name!r} in the calibration; known: {', '.join(ALL_EFFECTS)}",
                             source=src, column="model")
    params = doc.get("parameters")
    if not isinstance(params, dict):
        raise InputError("missing parameters", source=src, column="parameters")
    parameters = tuple(_parameter(name, p, src) for name, p in params.items())
    sign = doc.get("friction_sign")
    if sign is not None and sign != FRICTION_SIGN:
        raise InputError(f"expected {FRICTION_SIGN!r} (the drive supplies friction in the direction of motion), "
                         f"got {sign!r}", source=src, column="friction_sign")
    if sign is None and any(is_friction(p.name) for p in parameters):
        parameters = _old_friction_sign(parameters)
    unidentifiable = doc.get("unidentifiable", [])
    if not isinstance(unidentifiable, list) or not all(isinstance(n, str) for n in unidentifiable):
        raise InputError(f"expected a list of parameter names, got {unidentifiable!r}", source=src,
                         column="unidentifiable")
    given = [int(k[1:]) for k in (*params, *unidentifiable) if is_stiffness_name(k)]
    if given:   # run data alone give none; static data give one per joint, k1..kN (or say which they could not)
        for k in stiffness_names(max(given)):
            if k not in params and k not in unidentifiable:
                raise InputError(f"missing {k}: a calibration with joint stiffness holds k1..k{max(given)} (or "
                                 "lists the undetermined ones in unidentifiable)", source=src,
                                 column=f"parameters.{k}")
    torque = doc.get("torque", "current")
    if torque not in TORQUES:
        raise InputError(f"expected one of {', '.join(TORQUES)}, got {torque!r}", source=src, column="torque")
    created = doc.get("created", "")
    if not isinstance(created, str):
        raise InputError(f"expected a date-time text, got {created!r}", source=src, column="created")
    residual = _residual(doc.get("residual", {}), src, "residual")
    data = doc.get("data", [])
    if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
        raise InputError("expected a list of objects with path and sha256", source=src, column="data")
    absolute = doc.get("absolute_residual")
    absolute = None if absolute is None else _residual(absolute, src, "absolute_residual")
    description = doc.get("robot_description")
    if description is not None and not isinstance(description, str):
        raise InputError("expected the robot.toml text", source=src, column="robot_description")
    return Calibration(robot=robot, created=created, model=tuple(model), torque=TorqueSource(torque),
                       parameters=parameters, residual=residual,
                       data=tuple(_data_file(d, src, k) for k, d in enumerate(data)), source=src,
                       absolute_residual=absolute, robot_description=description,
                       unidentifiable=tuple(unidentifiable))
