"""The cell a procedure runs on, chosen by the command (calibrate, check, demo).

* ``--sim``: the cell's simulated devices served in this process
  (:class:`elastocal.sims.serve.SimulatedCell`); loads hang in its world;
* a cell ``elastocal sim serve --write-cell`` wrote (``[sim] load_url``): its
  load rig (:class:`elastocal.drivers.load_rig.ModbusLoadRig`, checked to be one
  before anything is written) hangs the loads the operator confirms;
* any other cell is real: a person hangs the loads, confirmed at the terminal.

Only the first two are simulated, so only there may ``--yes`` answer the
prompts; a real cell's prompts are answered at a terminal, never from a pipe.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

from elastocal.errors import InputError


def check_sim_section(config) -> None:
    """An invalid ``[sim]`` section is refused whatever the command does with it."""
    if config.sim:
        from elastocal.sims.config import sim_config

        sim_config(config)


def is_simulated(config, *, sim: bool) -> bool:
    """True when the procedure will run on a simulated cell (``--sim``, or a served cell's load rig)."""
    return sim or bool(config.sim.get("load_url"))


def check_answers(config, *, sim: bool, yes: bool, prompts: bool = True) -> None:
    """Who answers the prompts, checked before anything is opened or written: ``--yes`` only on a
    simulated cell; otherwise a person at a terminal (not a pipe or a file)."""
    from elastocal.acquisition.ui import NOT_A_TERMINAL, stdin_is_terminal

    check_sim_section(config)
    simulated = is_simulated(config, sim=sim)
    if yes and not simulated:
        raise InputError("--yes answers the prompts of simulated devices only; add --sim (or use the cell "
                         "`elastocal sim serve --write-cell` wrote), or let a person answer", source="--yes")
    if prompts and not yes and not stdin_is_terminal():
        hint = "; --yes answers a simulated cell's prompts" if simulated else "; run it in a terminal"
        raise InputError(NOT_A_TERMINAL + hint, source="standard input")


@contextlib.contextmanager
def procedure_cell(config, *, sim: bool) -> Iterator[tuple[object, object | None]]:
    """``(config to open, where loads hang)`` for the procedure: see the module docstring.
    The load world is None for a real cell."""
    with contextlib.ExitStack() as stack:
        if sim:
            from elastocal.sims.serve import SimulatedCell

            served = stack.enter_context(SimulatedCell(config))
            yield served.config, served.world
            return
        load_url = config.sim.get("load_url") if config.sim else None
        if load_url:
            from elastocal.drivers.load_rig import open_load_rig

            yield config, stack.enter_context(open_load_rig(load_url, source=str(config.source)))
            return
        yield config, None


def lockstep_world(config):
    """``(world, clock)``: the simulated world of ``config``'s ``[sim]`` section on a simulated clock
    of its own, for a procedure in lockstep with it (acquisition/lockstep.py)."""
    from elastocal.sims.config import sim_config
    from elastocal.sims.world import SimClock, SimWorld

    clock = SimClock()
    markers = config.tracker.markers if config.tracker is not None else None
    world = SimWorld.from_config(config.load_robot(), sim_config(config), markers, clock_ns=clock.now_ns)
    return world, clock
