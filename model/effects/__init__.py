"""The physical effects a model can hold (docs/cli.md, "Effects").

Each effect is one module named after it (its parameters and units, how it
enters the static and the run model, the data that can show it, and the
sentence that explains it to a user); this table maps names to modules and is
imported lazily. Effects that only run data can show are here too, so that a
request for them on static data is refused with the reason.
"""

from __future__ import annotations

import importlib

from elastocal.errors import InputError
from elastocal.model.effects.base import Effect

_PACKAGE = "elastocal.model.effects"
#: effect name -> module that defines EFFECT (docs/cli.md's table, then elastocal's extensions)
EFFECT_MODULES = {
    name: f"{_PACKAGE}.{name}"
    for name in (
        "joint_stiffness",
        "compensator",
        "gravity",
        "coulomb_friction",
        "viscous_friction",
        "load_dependent_friction",
        "complementary_stiffness",
        "link_compliance",
        "thermal_drift",
        "backlash",
        "tracker_frame",
        "kinematic_errors",
        "static_friction",
        "nonlinear_stiffness",
    )
}
ALL_EFFECTS = tuple(EFFECT_MODULES)


def get_effect(name: str, robot=None) -> Effect:
    """The effect ``name``; with ``robot``, its parameters sized for that robot's joints
    (``k1..kN``; without one, the six-axis table of docs/cli.md)."""
    if name not in EFFECT_MODULES:
        raise InputError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}", argument="model")
    return importlib.import_module(EFFECT_MODULES[name]).EFFECT.for_robot(robot)


def run_effects(part: str | None = None) -> tuple[str, ...]:
    """Names of the effects run data show (``part``: only those of "uv/vu" or "sweep"),
    in the table's order; each effect module declares its ``run_part``."""
    return tuple(n for n in ALL_EFFECTS if get_effect(n).run_part is not None
                 and (part is None or get_effect(n).run_part == part))


def absolute_effects() -> tuple[str, ...]:
    """Names of the effects only absolute positions show, in the table's order; each effect
    module declares it (``Effect.absolute_only``)."""
    return tuple(n for n in ALL_EFFECTS if get_effect(n).absolute_only)


#: the default model of an absolute-only table (docs/cli.md "Absolute-only tables")
ABSOLUTE_ONLY_MODEL = ("kinematic_errors", "tracker_frame")


def parse_model(text: str | None, *, absolute_only: bool = False) -> tuple[str, ...]:
    """``--model`` text -> effect names, joint_stiffness always first; on an absolute-only table
    (no loads) the effects named, joint_stiffness only when named, and without ``--model``
    :data:`ABSOLUTE_ONLY_MODEL`."""
    if absolute_only:
        names = [n.strip() for n in (text or ",".join(ABSOLUTE_ONLY_MODEL)).split(",") if n.strip()]
        for n in names:
            get_effect(n)
        return tuple(dict.fromkeys(names))
    names = [n.strip() for n in (text or "joint_stiffness").split(",") if n.strip()]
    for n in names:
        get_effect(n)
    out = ["joint_stiffness"] + [n for n in dict.fromkeys(names) if n != "joint_stiffness"]
    return tuple(out)
