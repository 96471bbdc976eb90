"""Units of the values in the user's files: parse a unit text, convert to SI.

A unit is a product and quotient of known symbols (``N*m/rad``, ``kN·m/deg``,
``rad/(N*m)``, ``N*m*s/rad``, ``mm``, ``-`` for none), each symbol with an
optional integer power (``m^2``). :func:`conversion` gives the factor that turns
a value in one unit into another of the same dimension, and refuses units it
does not know or whose dimensions differ, so a calibration written in N·m/deg
is converted, and one in furlongs is refused, never silently misread.
"""

from __future__ import annotations

import math
import re

#: symbol -> (factor to SI, dimension exponents over BASE)
BASE = ("kg", "m", "s", "A", "rad")
_N = (1, 1, -2, 0, 0)
_SYMBOLS: dict[str, tuple[float, tuple[int, ...]]] = {
    "N": (1.0, _N), "kN": (1e3, _N), "mN": (1e-3, _N), "daN": (10.0, _N),
    "m": (1.0, (0, 1, 0, 0, 0)), "mm": (1e-3, (0, 1, 0, 0, 0)), "cm": (1e-2, (0, 1, 0, 0, 0)),
    "um": (1e-6, (0, 1, 0, 0, 0)), "µm": (1e-6, (0, 1, 0, 0, 0)), "km": (1e3, (0, 1, 0, 0, 0)),
    "s": (1.0, (0, 0, 1, 0, 0)), "ms": (1e-3, (0, 0, 1, 0, 0)), "min": (60.0, (0, 0, 1, 0, 0)),
    "A": (1.0, (0, 0, 0, 1, 0)), "mA": (1e-3, (0, 0, 0, 1, 0)),
    "kg": (1.0, (1, 0, 0, 0, 0)), "g": (1e-3, (1, 0, 0, 0, 0)),
    "rad": (1.0, (0, 0, 0, 0, 1)), "mrad": (1e-3, (0, 0, 0, 0, 1)), "urad": (1e-6, (0, 0, 0, 0, 1)),
    "µrad": (1e-6, (0, 0, 0, 0, 1)), "deg": (math.pi / 180, (0, 0, 0, 0, 1)),
    "arcmin": (math.pi / 10800, (0, 0, 0, 0, 1)), "arcsec": (math.pi / 648000, (0, 0, 0, 0, 1)),
    "Nm": (1.0, (1, 2, -2, 0, 0)), "kNm": (1e3, (1, 2, -2, 0, 0)),
    "in": (0.0254, (0, 1, 0, 0, 0)), "inch": (0.0254, (0, 1, 0, 0, 0)), "ft": (0.3048, (0, 1, 0, 0, 0)),
}
_PA = (1, -1, -2, 0, 0)
#: pressures as a tracker's weather station quotes them, in hPa (so that x hPa reads back as exactly x)
_SYMBOLS.update({sym: (hpa * 100.0, _PA) for sym, hpa in (
    ("hPa", 1.0), ("mbar", 1.0), ("kPa", 10.0), ("Pa", 0.01), ("mmHg", 1.333224), ("inHg", 33.8639),
    ("psi", 68.9476))})
_NONE = ("", "-", "1")
_TOKEN = re.compile(r"\s*(?:(?P<sym>[A-Za-zµ]+)(?:\^(?P<pow>[+-]?\d+))?|(?P<op>[*·/()])|(?P<one>1))")


class UnitError(ValueError):
    """A unit text that is not a known unit."""


def parse_unit(text: str) -> tuple[float, tuple[int, ...]]:
    """(factor to SI, dimension exponents) of a unit text; :class:`UnitError` if unknown."""
    s = text.strip().replace(" ", "*").replace(".", "*")
    if s in _NONE:
        return 1.0, (0,) * len(BASE)
    tokens = []
    pos = 0
    while pos < len(s):
        m = _TOKEN.match(s, pos)
        if m is None or m.end() == pos:
            raise UnitError(f"cannot read the unit {text!r}")
        tokens.append(m)
        pos = m.end()
    value, dims, rest = _product(tokens, 0, text)
    if rest != len(tokens):
        raise UnitError(f"cannot read the unit {text!r} (unbalanced parentheses)")
    return value, dims


def _product(tokens, i: int, text: str) -> tuple[float, tuple[int, ...], int]:
    factor, dims = 1.0, [0] * len(BASE)
    sign, expect_term = 1, True
    while i < len(tokens):
        m = tokens[i]
        op = m.group("op")
        if op in ("*", "·", "/"):
            if expect_term:
                raise UnitError(f"cannot read the unit {text!r}")
            sign = -1 if op == "/" else 1
            expect_term = True
            i += 1
            continue
        if op == ")":
            break
        if not expect_term:
            raise UnitError(f"cannot read the unit {text!r}")
        if op == "(":
            f, d, i = _product(tokens, i + 1, text)
            if i >= len(tokens) or tokens[i].group("op") != ")":
                raise UnitError(f"cannot read the unit {text!r} (unbalanced parentheses)")
            i += 1
        elif m.group("one"):
            f, d = 1.0, (0,) * len(BASE)
            i += 1
        else:
            sym = m.group("sym")
            if sym not in _SYMBOLS:
                raise UnitError(f"unknown unit symbol {sym!r} in {text!r}")
            power = int(m.group("pow") or 1)
            f0, d0 = _SYMBOLS[sym]
            f, d = f0 ** power, tuple(power * x for x in d0)
            i += 1
        factor *= f if sign > 0 else 1.0 / f
        dims = [a + sign * b for a, b in zip(dims, d)]
        sign = 1                            # "a/b*c" reads as (a/b)*c
        expect_term = False
    if expect_term:                         # empty, or ends with an operator
        raise UnitError(f"cannot read the unit {text!r}")
    return factor, tuple(dims), i


def conversion(unit: str, target: str) -> float:
    """Factor ``f`` such that a value in ``unit`` is ``f * value`` in ``target``;
    :class:`UnitError` when ``unit`` is unknown or not of ``target``'s dimension."""
    f_from, d_from = parse_unit(unit)
    f_to, d_to = parse_unit(target)
    if d_from != d_to:
        raise UnitError(f"{unit!r} is not a unit of the same kind as {target!r}")
    return f_from / f_to


def unit_table(target: str) -> dict[str, float]:
    """Every known symbol of ``target``'s dimension -> the factor that turns a value in it
    into ``target`` (``unit_table("m")["mm"] == 1e-3``), in the order the symbols are declared."""
    f_to, d_to = parse_unit(target)
    return {sym: f / f_to for sym, (f, d) in _SYMBOLS.items() if d == d_to}
