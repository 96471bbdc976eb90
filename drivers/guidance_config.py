"""The ``[guidance]`` and ``[force_sensor]`` sections of cell.toml (docs/cell-config.md).

``[guidance]`` names the controller's real-time guidance channel (``egm://`` or ``rsi://``: the
address elastocal listens on) and the limits the corrections keep; ``[force_sensor]`` a
force/torque sensor on the tool (``netft://``) and how old its sample may be when a cycle uses it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

from elastocal.drivers.urls import FORCE_SCHEMES, GUIDANCE_SCHEMES, DeviceUrl, parse_device_url
from elastocal.errors import InputError, check_known_keys

GUIDANCE_KEYS = ("url", "max_correction_deg", "max_rate_deg_s")
FORCE_SENSOR_KEYS = ("url", "max_age_s")


@dataclass(frozen=True)
class GuidanceConfig:
    url: DeviceUrl
    #: per-joint limits of the correction (defaults: elastocal.stream.correction)
    max_correction_deg: float | None = None
    max_rate_deg_s: float | None = None

    @property
    def name(self) -> str:
        return "guidance"


@dataclass(frozen=True)
class ForceSensorConfig:
    url: DeviceUrl
    #: a sample older than this when a cycle needs it makes the cycle late [s]
    max_age_s: float = 0.02

    @property
    def name(self) -> str:
        return "force sensor"


def _positive(table: Mapping, key: str, *, source: str, where: str) -> float | None:
    if key not in table:
        return None
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise InputError(f"expected a positive number, got {v!r}", source=source, column=f"{where}.{key}")
    return float(v)


def _table(t, where: str, source: str, keys: tuple[str, ...]) -> Mapping:
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    check_known_keys(t, keys, source=source, where=where)
    if "url" not in t:
        raise InputError("missing required key", source=source, column=f"{where}.url")
    return t


def parse_guidance(t, *, source: str) -> GuidanceConfig:
    t = _table(t, "guidance", source, GUIDANCE_KEYS)
    url = parse_device_url(t["url"], allowed=GUIDANCE_SCHEMES, source=f"{source}, guidance.url")
    return GuidanceConfig(url=url, max_correction_deg=_positive(t, "max_correction_deg", source=source,
                                                                where="guidance"),
                          max_rate_deg_s=_positive(t, "max_rate_deg_s", source=source, where="guidance"))


def parse_force_sensor(t, *, source: str) -> ForceSensorConfig:
    t = _table(t, "force_sensor", source, FORCE_SENSOR_KEYS)
    url = parse_device_url(t["url"], allowed=FORCE_SCHEMES, source=f"{source}, force_sensor.url")
    age = _positive(t, "max_age_s", source=source, where="force_sensor")
    return ForceSensorConfig(url=url, max_age_s=0.02 if age is None else age)


def guidance_doc(g: GuidanceConfig | None, f: ForceSensorConfig | None) -> dict:
    """The two sections as cell.toml tables (round-trip of the parsers above)."""
    doc: dict = {}
    if g is not None:
        doc["guidance"] = {"url": g.url.text}
        if g.max_correction_deg is not None:
            doc["guidance"]["max_correction_deg"] = g.max_correction_deg
        if g.max_rate_deg_s is not None:
            doc["guidance"]["max_rate_deg_s"] = g.max_rate_deg_s
    if f is not None:
        doc["force_sensor"] = {"url": f.url.text, "max_age_s": f.max_age_s}
    return doc
