"""Human-readable tables for the CLI (the library never prints)."""

from __future__ import annotations

import math
from typing import Mapping


def _num(x: float | None) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.6g}"


def _um(x: float | None) -> str:
    return "-" if x is None else f"{x * 1e6:.1f} µm"


def format_parameters(params: Mapping[str, Mapping], truth: Mapping[str, Mapping] | None = None) -> str:
    head = f"  {'parameter':<10} {'value':>14} {'std':>12}  {'unit':<11}"
    if truth:
        head += f" {'true':>14} {'error':>8}"
    lines = [head]
    for name, p in params.items():
        if p.get("determined") is False:   # never shown as a finding (identify/evidence.py)
            lines.append(f"  {name:<10} {'NOT DETERMINED':>27}  {p.get('unit', ''):<11} {p.get('note', '')} "
                         f"[fit gave {_num(p['value'])} ± {_num(p.get('std'))}]")
            continue
        line = f"  {name:<10} {_num(p['value']):>14} {_num(p.get('std')):>12}  {p.get('unit', ''):<11}"
        if truth and name in truth:
            t = float(truth[name]["value"])
            err = (p["value"] - t) / t * 100 if t else float("nan")
            line += f" {_num(t):>14} {err:>7.2f}%"
        lines.append(line)
    return "\n".join(lines)


def verdict_line(rms: float, floor: float | None) -> str:
    if floor is None:
        return f"residual {_um(rms)} rms (no repeated readings: noise floor unknown)"
    ratio = rms / floor
    word = "at the noise floor" if ratio < 1.3 else "above the noise floor: the model misses something"
    return f"residual {_um(rms)} rms, noise floor {_um(floor)} ({ratio:.2f}x): {word}"


def format_fit(obj: Mapping, title: str, truth: Mapping[str, Mapping] | None = None) -> str:
    lines = [title, format_parameters(obj["parameters"], truth)]
    res = obj["residual"]
    bad = [n for n, p in obj["parameters"].items() if p.get("determined") is False]
    if bad:
        lines.append(f"{', '.join(bad)} not determined by these data: this is not a calibration "
                     "(more poses or larger loads; were the loads hung?)")
    if res.get("unit", "m") == "m":
        lines.append(verdict_line(res["rms"], obj.get("noise_floor")))
    else:
        line = f"torque residual {res['rms']:.4g} {res['unit']} rms over {res['n']} samples"
        floor = obj.get("noise_floor")
        if floor:
            ratio = res["rms"] / floor
            line += (f", noise floor {floor:.4g} {res['unit']} ({ratio:.2f}x): "
                     + ("at the noise floor" if ratio < 1.3 else "above the noise floor: the model misses something"))
        lines.append(line)
        if obj.get("stiffness"):
            lines.append(obj["stiffness"]["note"])
    if "torque_residual" in obj:
        tr = obj["torque_residual"]
        floor = obj.get("torque_noise_floor")
        lines.append(f"torque residual {tr['rms']:.4g} {tr['unit']} rms over {tr['n']} samples"
                     + (f", noise floor {floor:.4g} {tr['unit']} ({tr['rms'] / floor:.2f}x)" if floor else ""))
    if obj.get("absolute_residual"):
        lines.append("absolute positions (after the registration): " + absolute_line(
            obj["absolute_residual"], obj.get("absolute_noise_floor")))
    if obj.get("unidentifiable"):
        lines.append("unidentifiable from these data (left out): " + ", ".join(obj["unidentifiable"])
                     + f"; condition number {obj.get('condition_number', float('nan')):.3g}")
        for words in obj.get("absorbed_by", {}).values():
            lines.append(f"  {words}")
    return "\n".join(lines)


def absolute_line(res: Mapping, floor: float | None) -> str:
    """``653.0 µm rms, max 1.67 mm, floor 8.0 µm (81.6x)``."""
    mx = res["max"]
    text = f"{_um(res['rms'])} rms, max " + (f"{mx * 1e3:.2f} mm" if mx >= 1e-3 else _um(mx))
    if floor:
        text += f", floor {_um(floor)} ({res['rms'] / floor:.2f}x)"
    return text
