"""The results table of a fleet run (docs/cli.md ``fleet``): columns, CSV and Parquet.

One row per input, in path order. Columns: ``path``, ``cell``, ``robot``,
``sha256``, ``error`` (empty when it worked), ``note`` (optional extension: a
log read up to its last complete chunk), the parameters as ``k1..k6`` then the
other effects' names in the order the rows first give them, each with
``<name>_std`` beside it, ``residual_rms``, ``noise_floor``, ``verdict``
(diagnose), ``decision`` (check), ``seconds``. Floats are written as Python's
shortest round-trip text in CSV (the value read back is the value computed),
as float64 in Parquet; a missing value is an empty CSV field or a Parquet null.
"""

from __future__ import annotations

import csv
import pathlib
from typing import Sequence

from elastocal.errors import InputError
from elastocal.formats.calibration import is_stiffness_name
from elastocal.fleet.tasks import LogResult

FORMATS = {".csv": "csv", ".parquet": "parquet"}
HEAD = ("path", "cell", "robot", "sha256", "error", "note")
TAIL = ("residual_rms", "noise_floor", "verdict", "decision", "seconds")
TEXT_COLUMNS = frozenset(HEAD) | {"verdict", "decision"}


def table_format(path: str | pathlib.Path) -> str:
    """``csv`` or ``parquet`` from the file name; Parquet needs pyarrow."""
    kind = FORMATS.get(pathlib.Path(path).suffix.lower())
    if kind is None:
        raise InputError("the results are written as .csv or .parquet (by the file name)", source=str(path))
    if kind == "parquet":
        import importlib.util

        if importlib.util.find_spec("pyarrow") is None:
            raise InputError("writing .parquet needs pyarrow, which is not installed: pip install "
                             "'elastocal[fleet]' (or write .csv)", source=str(path))
    return kind


def parameter_names(results: Sequence[LogResult]) -> list[str]:
    """k1..kN first, then every other parameter in the order the rows first name it."""
    seen: dict[str, None] = {}
    for r in results:
        for name, _, _ in r.parameters:
            seen.setdefault(name, None)
    stiff = sorted((n for n in seen if is_stiffness_name(n)), key=lambda n: int(n[1:]))
    return stiff + [n for n in seen if n not in stiff]


def columns(results: Sequence[LogResult]) -> list[str]:
    params = []
    for name in parameter_names(results):
        params += [name, f"{name}_std"]
    return [*HEAD, *params, *TAIL]


def rows(results: Sequence[LogResult]) -> tuple[list[str], list[dict]]:
    """(column names, one dict per result); missing values are None."""
    cols = columns(results)
    out = []
    for r in results:
        row = dict.fromkeys(cols)
        row.update(path=r.path, cell=r.cell, robot=r.robot, sha256=r.sha256, error=r.error, note=r.note,
                   residual_rms=r.residual_rms, noise_floor=r.noise_floor, verdict=r.verdict, decision=r.decision,
                   seconds=r.seconds)
        for name, value, std in r.parameters:
            row[name] = value
            row[f"{name}_std"] = std
        out.append(row)
    return cols, out


def _csv_text(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def write_table(path: str | pathlib.Path, results: Sequence[LogResult], kind: str | None = None) -> None:
    """Write the results as CSV or Parquet (``kind``, default from the name)."""
    kind = kind or table_format(path)
    cols, data = rows(results)
    if kind == "csv":
        with open(path, "w", encoding="utf-8", newline="") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(cols)
            for row in data:
                writer.writerow([_csv_text(row[c]) for c in cols])
        return
    import pyarrow as pa
    import pyarrow.parquet as pq

    arrays, fields = [], []
    for c in cols:
        values = [row[c] for row in data]
        if c in TEXT_COLUMNS:
            typ = pa.string()
            values = [None if v is None else str(v) for v in values]
        else:
            typ = pa.float64()
        arrays.append(pa.array(values, type=typ))
        fields.append(pa.field(c, typ))
    pq.write_table(pa.Table.from_arrays(arrays, schema=pa.schema(fields)), str(path))


def read_table(path: str | pathlib.Path) -> list[dict]:
    """A results table back as dicts (text as str, empty when missing; floats as
    float, None when missing) -- for tests and scripts."""
    path = pathlib.Path(path)
    if table_format(path) == "parquet":
        import pyarrow.parquet as pq

        return [{k: ("" if v is None else v) if k in TEXT_COLUMNS else v for k, v in row.items()}
                for row in pq.read_table(str(path)).to_pylist()]
    with open(path, encoding="utf-8", newline="") as fh:
        reader = csv.DictReader(fh)
        out = []
        for row in reader:
            out.append({k: (None if v == "" and k not in TEXT_COLUMNS else
                            v if k in TEXT_COLUMNS else float(v)) for k, v in row.items()})
        return out
