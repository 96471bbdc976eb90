"""Many logs at once: replay, re-identify and check a plant's logs (docs/fleet.md).

:func:`~elastocal.fleet.discover.find_inputs` lists every log (MCAP) and table
folder under some paths, each with the cell it belongs to;
:func:`~elastocal.fleet.tasks.run_task` analyses one of them in whatever
process runs it — it opens its own file and returns a small frozen
:class:`~elastocal.fleet.tasks.LogResult`, computed by the same library
functions as ``elastocal identify|diagnose|check``;
:func:`~elastocal.fleet.pool.run_tasks` runs the tasks on Dask
(``dask.distributed``: a scheduler, or a ``LocalCluster``) or, without it, on a
local process pool; :mod:`~elastocal.fleet.plant` records results into each
cell's history and draws the plant's drift table. Nothing here prints.
"""

from elastocal.fleet.tasks import COMMANDS, FleetTask, LogResult, run_task

__all__ = ["COMMANDS", "FleetTask", "LogResult", "run_task"]
