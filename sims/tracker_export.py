"""A simulated static experiment as a tracker software and a robot controller record it
(`elastocal sim static --tracker-export`, docs/import.md): the points the tracker's own
software exports (a Leica-style CSV, millimetres, one named and timestamped point per
reading) and the controller's joint log (``t, pose, load, q1..q6, i1..i6, fx..mz``), for
`elastocal import points.csv --joints joints.csv --names 'P{pose}_L{load}_{marker}'`.

Each reading of the table is one point and one joint sample at the same instant (the
table's ``t`` from a fixed start, UTC), so the import pairs every point with its own
sample: the imported table is the simulated one (positions to 1e-9 m through the
millimetres, joints and currents exactly).
"""

from __future__ import annotations

import datetime as _dt

import numpy as np

from elastocal.formats.tables import StaticTable

#: the simulated session starts here (UTC): a fixed instant, so the files depend on the seed only
START = _dt.datetime(2026, 1, 5, 8, 0, 0, tzinfo=_dt.timezone.utc)
#: the point names the export uses, the pattern `elastocal import --names` reads them with
NAMES = "P{pose}_L{load}_{marker}"
#: seconds between readings when the table has no times
STEP_S = 2.0


def _times(table: StaticTable) -> list[str]:
    t = table.t if table.has_time else np.arange(len(table)) * STEP_S
    return [(START + _dt.timedelta(seconds=float(s))).isoformat(timespec="microseconds").replace("+00:00", "Z")
            for s in t]


def points_csv(table: StaticTable) -> str:
    """The tracker software's export: ``Point,X [mm],Y [mm],Z [mm],Timestamp``."""
    rows = ["Point,X [mm],Y [mm],Z [mm],Timestamp"]
    for n, stamp in enumerate(_times(table)):
        name = NAMES.format(pose=table.pose[n], load=table.load[n], marker=table.marker[n])
        x, y, z = (float(v) * 1e3 for v in table.xyz[n])
        rows.append(f"{name},{x!r},{y!r},{z!r},{stamp}")
    return "\n".join(rows) + "\n"


def joints_csv(table: StaticTable) -> str:
    """The controller's joint log: one sample per reading, ``t,pose,load,q1..q6,i1..i6`` and the
    nominal load ``fx..mz`` when the table knows it."""
    wrench = table.has_wrench
    header = (["t", "pose", "load"] + [f"q{j}" for j in range(1, 7)] + [f"i{j}" for j in range(1, 7)]
              + (["fx", "fy", "fz", "mx", "my", "mz"] if wrench else []))
    rows = [",".join(header)]
    for n, stamp in enumerate(_times(table)):
        values = [*table.q[n], *table.currents[n]] + (list(np.nan_to_num(table.wrench[n])) if wrench else [])
        rows.append(",".join([stamp, str(table.pose[n]), str(table.load[n])] + [repr(float(v)) for v in values]))
    return "\n".join(rows) + "\n"
