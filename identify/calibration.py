"""Calibration JSON (formats.md §4): write and read."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import pathlib
from dataclasses import dataclass
from typing import Mapping, Sequence

from elastocal.errors import InputError
from elastocal.textfiles import read_text_file

FORMAT = "elastocal.calibration/1"
#: the torque a calibration was identified from: motor currents or the measured wrench
TORQUES = ("current", "force")


def file_sha256(path: str | pathlib.Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


@dataclass(frozen=True)
class Calibration:
    robot: str
    created: str
    model: tuple[str, ...]
    torque: str
    parameters: Mapping[str, Mapping[str, float | str]]
    residual: Mapping[str, float]
    data: tuple[Mapping[str, str], ...] = ()

    def value(self, name: str) -> float:
        try:
            return float(self.parameters[name]["value"])
        except KeyError:
            raise InputError(f"the calibration has no parameter {name!r}") from None

    def stiffness(self) -> list[float]:
        return [self.value(f"k{j}") for j in range(1, 7)]

    def to_json(self) -> dict:
        return {"format": FORMAT, "robot": self.robot, "created": self.created, "model": list(self.model),
                "torque": self.torque, "parameters": {k: dict(v) for k, v in self.parameters.items()},
                "residual": dict(self.residual), "data": [dict(d) for d in self.data]}


def calibration_from_fit(robot_name: str, fit_json: dict, data_paths: Sequence[str | pathlib.Path] = (),
                         created: str | None = None) -> Calibration:
    """A Calibration from an ``identify --json`` object and the files it used."""
    created = created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")
    residual = {k: v for k, v in fit_json["residual"].items() if k in ("rms", "max", "n")}
    if fit_json.get("noise_floor") is not None:  # optional extension: what noise alone leaves [m]
        residual["noise_floor"] = fit_json["noise_floor"]
    data = tuple({"path": str(p), "sha256": file_sha256(p)} for p in data_paths)
    return Calibration(robot=robot_name, created=created, model=tuple(fit_json["model"]),
                       torque=fit_json.get("torque", "current"), parameters=fit_json["parameters"],
                       residual=residual, data=data)


def write_calibration(path: str | pathlib.Path, cal: Calibration) -> None:
    pathlib.Path(path).write_text(json.dumps(cal.to_json(), indent=2) + "\n", encoding="utf-8")


def read_calibration(path: str | pathlib.Path) -> Calibration:
    path = pathlib.Path(path)
    text = read_text_file(path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}", source=str(path)) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not an elastocal calibration (format must be {FORMAT!r})", source=str(path),
                         column="format")
    src = str(path)
    robot = doc.get("robot")
    if not isinstance(robot, str) or not robot.strip():
        what = "missing" if robot is None else f"expected the robot's name, got {robot!r}"
        raise InputError(f"{what}: the calibration must name its robot (formats.md §4)", source=src, column="robot")
    params = doc.get("parameters")
    if not isinstance(params, dict):
        raise InputError("missing parameters", source=src, column="parameters")
    for name, p in params.items():
        v = p.get("value") if isinstance(p, dict) else None
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
            raise InputError(f"parameter {name} has no finite value", source=src, column=f"parameters.{name}")
    model = doc.get("model", ["joint_stiffness"])
    if not isinstance(model, list) or not model or not all(isinstance(m, str) and m for m in model):
        raise InputError(f"expected a list of effect names, got {model!r}", source=src, column="model")
    torque = doc.get("torque", "current")
    if torque not in TORQUES:
        raise InputError(f"expected one of {', '.join(TORQUES)}, got {torque!r}", source=src, column="torque")
    created = doc.get("created", "")
    if not isinstance(created, str):
        raise InputError(f"expected a date-time text, got {created!r}", source=src, column="created")
    residual = doc.get("residual", {})
    if not isinstance(residual, dict):
        raise InputError(f"expected an object, got {residual!r}", source=src, column="residual")
    data = doc.get("data", [])
    if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
        raise InputError("expected a list of objects with path and sha256", source=src, column="data")
    return Calibration(robot=robot, created=created, model=tuple(model), torque=torque,
                       parameters=params, residual=residual, data=tuple(data))
