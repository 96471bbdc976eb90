"""One vocabulary of flags (README, "Flags"): the words shared by several commands, and the
old spellings kept as hidden aliases (argparse.SUPPRESS) so that scripts keep working."""

from __future__ import annotations

import argparse

JSON_HELP = "print exactly one JSON object on stdout"
#: the default random seed of every command that draws random numbers (demo, sim, plan)
DEFAULT_SEED = 0
#: loaded states per pose, the same default in `plan` and `sim static`
DEFAULT_LOADS_PER_POSE = 3


def add_json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help=JSON_HELP)


def add_seed(parser: argparse.ArgumentParser, what: str = "random seed") -> None:
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help=f"{what} (default {DEFAULT_SEED})")


def add_aliased(parser, name: str, old: str, **kwargs) -> None:
    """``name`` with its help; ``old`` the same option, accepted but not listed."""
    dest = kwargs.pop("dest", None) or name.lstrip("-").replace("-", "_")
    parser.add_argument(name, dest=dest, **kwargs)
    hidden = {k: v for k, v in kwargs.items() if k in ("type", "metavar", "choices", "action")}
    parser.add_argument(old, dest=dest, help=argparse.SUPPRESS, default=argparse.SUPPRESS, **hidden)


def parse_wrench(text: str, flag: str = "--wrench") -> tuple[float, ...]:
    """``FX,FY,FZ[,MX,MY,MZ]`` [N, N*m]: three or six finite numbers, the moments 0 when left out."""
    import math

    from elastocal.errors import InputError

    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (3, 6):
        raise InputError(f"expected 3 or 6 comma-separated numbers FX,FY,FZ[,MX,MY,MZ], got {len(parts)}",
                         source=flag)
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise InputError(f"not numbers: {text!r}", source=flag) from None
    if not all(math.isfinite(v) for v in values):
        raise InputError("values must be finite", source=flag)
    return values + (0.0,) * (6 - len(values))
