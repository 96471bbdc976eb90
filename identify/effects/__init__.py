"""The physical effects a model can hold (cli.md, "Effects").

Each effect is one module named after it; this table maps names to modules and
is imported lazily. Effects that only run data can show are described here too,
so that a request for them on static data is refused with the reason.
"""

from __future__ import annotations

import importlib

from elastocal.errors import InputError
from elastocal.identify.effects.base import Effect

#: effect name -> module that defines EFFECT
EFFECT_MODULES = {
    "joint_stiffness": "elastocal.identify.effects.joint_stiffness",
    "link_compliance": "elastocal.identify.effects.link_compliance",
    "thermal_drift": "elastocal.identify.effects.thermal_drift",
    "backlash": "elastocal.identify.effects.backlash",
    "compensator": "elastocal.identify.effects.run_only",
    "gravity": "elastocal.identify.effects.run_only",
    "coulomb_friction": "elastocal.identify.effects.run_only",
    "viscous_friction": "elastocal.identify.effects.run_only",
    "load_dependent_friction": "elastocal.identify.effects.run_only",
    "complementary_stiffness": "elastocal.identify.effects.complementary_stiffness",
    "tracker_frame": "elastocal.identify.effects.run_only",
    "kinematic_errors": "elastocal.identify.effects.run_only",
}
ALL_EFFECTS = tuple(EFFECT_MODULES)


def get_effect(name: str) -> Effect:
    if name not in EFFECT_MODULES:
        raise InputError(f"unknown effect {name!r}; known: {', '.join(ALL_EFFECTS)}", source="--model")
    module = importlib.import_module(EFFECT_MODULES[name])
    table = getattr(module, "EFFECTS", None)
    return table[name] if table is not None else module.EFFECT


def parse_model(text: str | None) -> tuple[str, ...]:
    """``--model`` text -> effect names, joint_stiffness always first."""
    names = [n.strip() for n in (text or "joint_stiffness").split(",") if n.strip()]
    for n in names:
        get_effect(n)
    out = ["joint_stiffness"] + [n for n in dict.fromkeys(names) if n != "joint_stiffness"]
    return tuple(out)
