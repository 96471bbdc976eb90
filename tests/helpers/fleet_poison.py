"""A fleet task function whose worker process dies on one input (tests/test_fleet.py).

Imported by name in the worker processes, so it lives on their PYTHONPATH: the
test puts this folder there. Every try on ``poison.mcap`` leaves a file in
``$FLEET_POISON_DIR`` (to count the tries), then kills its own process with
SIGKILL, as the kernel's out-of-memory killer would.
"""

import os
import pathlib
import signal
import uuid

from elastocal.fleet.tasks import run_task


def kill_on_poison(task):
    if pathlib.Path(task.path).name == "poison.mcap":
        pathlib.Path(os.environ["FLEET_POISON_DIR"], f"try-{os.getpid()}-{uuid.uuid4().hex}").touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return run_task(task)
