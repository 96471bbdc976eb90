"""What a fleet run analyses: the logs and table folders under some paths, and their cells.

A **log** is any ``*.mcap`` file. A **table folder** is a folder holding
``static.csv`` and/or ``runs.csv`` (docs/formats.md §2-3) and no MCAP log (a folder
written by ``elastocal sim`` holds ``log.mcap`` beside the tables it came
from: the log is analysed, once). Hidden files and folders (``.name``) are
skipped. Inputs come in path order (sorted, each path's own entries together).

The **cell** of an input is the nearest ``cell.toml`` in its folder or a
folder above it (a plant keeps ``plant/<cell>/cell.toml`` beside the cell's
logs), unless one cell config is given for all.
"""

from __future__ import annotations

import os
import pathlib
from dataclasses import dataclass

from elastocal.errors import InputError

LOG_SUFFIX = ".mcap"
TABLE_FILES = ("static.csv", "runs.csv")
CELL_FILE = "cell.toml"


@dataclass(frozen=True)
class FleetInput:
    """One log or table folder, and the cell config that owns it (None: none found)."""

    path: pathlib.Path
    tables: bool                 # a table folder, not a log
    cell_config: pathlib.Path | None


def _is_table_folder(folder: pathlib.Path, names: set[str]) -> bool:
    return any(t in names for t in TABLE_FILES) and not any(n.endswith(LOG_SUFFIX) for n in names)


def _walk(root: pathlib.Path) -> list[tuple[pathlib.Path, bool]]:
    found: list[tuple[pathlib.Path, bool]] = []
    for folder, dirs, files in os.walk(root, onerror=None):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        here = pathlib.Path(folder)
        names = {f for f in files if not f.startswith(".")}
        if _is_table_folder(here, names):
            found.append((here, True))
        found.extend((here / f, False) for f in sorted(names) if f.endswith(LOG_SUFFIX))
    return sorted(found, key=lambda item: str(item[0]))


def find_cell_config(path: pathlib.Path, cache: dict[pathlib.Path, pathlib.Path | None] | None = None
                     ) -> pathlib.Path | None:
    """The nearest ``cell.toml`` in the folder of ``path`` (or in ``path``, a folder) or above."""
    cache = {} if cache is None else cache
    folder = path if path.is_dir() else path.parent
    folder = folder.resolve()
    seen = []
    found = None
    for candidate in (folder, *folder.parents):
        if candidate in cache:
            found = cache[candidate]
            break
        seen.append(candidate)
        if (candidate / CELL_FILE).is_file():
            found = candidate / CELL_FILE
            break
    for s in seen:
        cache[s] = found
    return found


def find_inputs(paths: list[str | pathlib.Path], *, cell_config: str | pathlib.Path | None = None
                ) -> list[FleetInput]:
    """Every log and table folder under ``paths`` (files or folders), in path
    order, each once; a path that does not exist, or holds nothing to analyse,
    is refused."""
    out: list[FleetInput] = []
    seen: set[pathlib.Path] = set()
    cache: dict[pathlib.Path, pathlib.Path | None] = {}
    forced = None if cell_config is None else pathlib.Path(cell_config)
    for given in paths:
        p = pathlib.Path(given)
        if not p.exists():
            raise InputError("no such file or folder", source=str(given))
        if p.is_file():
            if p.suffix.lower() != LOG_SUFFIX:
                raise InputError("not an MCAP log (.mcap) nor a folder of logs or tables", source=str(given))
            items = [(p, False)]
        else:
            items = _walk(p)
            if not items:
                raise InputError("holds no MCAP log and no table folder (static.csv or runs.csv)",
                                 source=str(given))
        for item, tables in items:
            key = item.resolve()
            if key in seen:
                continue
            seen.add(key)
            cell = forced if forced is not None else find_cell_config(item, cache)
            out.append(FleetInput(path=item, tables=tables, cell_config=cell))
    return out
