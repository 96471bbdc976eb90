"""`elastocal geometry`: compensator geometry from a joint-2 marker sweep (docs/cli.md, K §IV)."""

from __future__ import annotations

import argparse
import json

from elastocal.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", required=True, help="run table (docs/formats.md §3) of the joint-2 sweep")
    parser.add_argument("--pivot", required=True, help="marker on the compensator pivot P1 (turns with joint 2)")
    parser.add_argument("--cylinder", required=True,
                        help="comma-separated markers on the compensator cylinder (turn about P0)")
    parser.add_argument("--joint", type=int, default=2,
                        help="joint whose angle turns the pivot (default 2; the compensator's, 3 on an arm on a track)")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def geometry_json(geo) -> dict:
    """The ``geometry --json`` object (docs/cli.md) of a CompensatorGeometry; SI units."""
    std = geo.std
    return {
        "L": geo.L, "a_x": geo.a_x, "a_y": geo.a_y,
        "std": {name: float(s) for name, s in zip(geo.names, std)},
        "residual": {"rms": geo.residual_rms, "pivot_rms": geo.pivot.rms, "cylinder_rms": geo.cylinder.rms,
                     "out_of_plane_rms": float((geo.out_of_plane ** 2).mean() ** 0.5),
                     "n": int(len(geo.pivot.residuals) + len(geo.cylinder.residuals)), "unit": "m"},
        "a": geo.a,
        "reflected": geo.pivot.reflected,
        "plane_axes": list(geo.plane.axis_names),
        "p2": [float(v) for v in geo.p2],
        "p0": [float(v) for v in geo.p0],
        "cylinder_radii": [float(r) for r in geo.cylinder.radii],
    }


def run(args: argparse.Namespace) -> int:
    from elastocal.identify.geometry import geometry_from_run_table
    from elastocal.formats.tables import read_run_table

    cylinder = [c.strip() for c in args.cylinder.split(",") if c.strip()]
    if not cylinder:
        raise InputError("give at least one cylinder marker", source="--cylinder")
    table = read_run_table(args.runs)
    if not 1 <= args.joint <= table.n_joints:
        raise InputError(f"must be a joint number 1..{table.n_joints}", source="--joint")
    pivot_rows = table.marker == args.pivot.strip()
    if pivot_rows.any():
        import numpy as np

        angles = table.q[pivot_rows, args.joint - 1]
        distinct = len(np.unique(np.round(angles[np.isfinite(angles)], 9)))
        if distinct < 3:
            raise InputError(f"q{args.joint} takes {distinct} distinct value(s) where marker {args.pivot.strip()} "
                             f"is read; the arc fit needs the swept joint at 3 or more angles: is joint "
                             f"{args.joint} the one the sweep turns?", source="--joint")
    geo = geometry_from_run_table(table, pivot=args.pivot.strip(), cylinder=cylinder, joint=args.joint)
    obj = geometry_json(geo)
    if args.json:
        print(json.dumps(obj))
        return 0
    ax, ay = geo.plane.axis_names
    print(f"compensator geometry from {args.runs} (pivot {args.pivot}, cylinder {', '.join(cylinder)})")
    print(f"  {'parameter':<10} {'value [mm]':>12} {'std [mm]':>10}")
    for name, value, s in zip(geo.names, geo.values, geo.std):
        print(f"  {name:<10} {value * 1e3:>12.3f} {s * 1e3:>10.3f}")
    print(f"  a = |P2 P0| = {geo.a * 1e3:.3f} mm; a_x, a_y along the measurement axes {ax}, {ay}")
    print(f"  pivot arc {'turns against' if geo.pivot.reflected else 'turns with'} q{args.joint}; "
          f"cylinder radii " + ", ".join(f"{r * 1e3:.2f}" for r in geo.cylinder.radii) + " mm")
    print(f"  residual {geo.residual_rms * 1e3:.3f} mm rms (pivot arc {geo.pivot.rms * 1e3:.3f}, "
          f"cylinder arcs {geo.cylinder.rms * 1e3:.3f})")
    return 0
