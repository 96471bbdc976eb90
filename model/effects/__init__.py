"""The physical effects a model can hold (docs/cli.md, "Effects").

Each effect is one module named after it (its parameters and units, how it
enters the static and the run model, the data that can show it, and the
sentence that explains it to a user); this table maps names to modules and is
imported lazily. Effects that only run data can show are here too, so that a
request for them on static data is refused with the reason.
"""

from __future__ import annotations

import importlib
from typing import Sequence

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


#: the effect every deflection model holds first: the joint springs (:func:`parse_model`)
BASE_EFFECT = "joint_stiffness"
#: the effects a table without loads can show, tested in this order when the model lacks them
#: (diagnose/absolute_only.py; each says why a given table cannot test it: Effect.absolute_only_refusal)
ABSOLUTE_ONLY_POOL = ("kinematic_errors", "joint_stiffness", "backlash", "thermal_drift")


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


def having(capability: str, model: Sequence[str] | None = None) -> tuple[str, ...]:
    """The effects of ``model`` (names; default: every effect, in the table's order) that declare
    the capability ``capability`` (a true attribute of :class:`Effect`: ``geometry``,
    ``registration``, ``session``, ...): what generic code asks instead of naming effects."""
    return tuple(n for n in (ALL_EFFECTS if model is None else model) if getattr(get_effect(n), capability))


def absolute_only_untested() -> tuple[str, ...]:
    """Effects that say why a table without loads never tests them (besides :data:`ABSOLUTE_ONLY_POOL`)."""
    return tuple(n for n in ALL_EFFECTS if n not in ABSOLUTE_ONLY_POOL and get_effect(n).absolute_only_refusal)


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
    names = [n.strip() for n in (text or BASE_EFFECT).split(",") if n.strip()]
    for n in names:
        get_effect(n)
    out = [BASE_EFFECT] + [n for n in dict.fromkeys(names) if n != BASE_EFFECT]
    return tuple(out)
