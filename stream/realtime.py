"""Real-time scheduling for the stream's threads, where the operating system allows it.

A 4 ms cycle on a machine whose cores are busy with other work needs the scheduler's help:
the stream's threads run under ``SCHED_FIFO`` (Linux; threads started afterwards inherit
it). They block on their sockets between cycles and compute for microseconds, so they never
keep a core from the rest of the machine for long. Without the permission (not root, no
``CAP_SYS_NICE``, another system) the stream runs at normal priority and says so.
"""

from __future__ import annotations

import contextlib
import os

#: SCHED_FIFO priority of the stream (1..99; below the kernel's own interrupt threads at 50 on PREEMPT_RT)
STREAM_PRIORITY = 40


@contextlib.contextmanager
def realtime(priority: int = STREAM_PRIORITY):
    """Run the block (and the threads it starts) under SCHED_FIFO ``priority``; yields a description
    of the scheduling in force (``"SCHED_FIFO 40"`` or why not)."""
    set_policy = getattr(os, "sched_setscheduler", None)
    if set_policy is None or not hasattr(os, "SCHED_FIFO"):
        yield "normal scheduling (this system has no SCHED_FIFO)"
        return
    previous = (os.sched_getscheduler(0), os.sched_getparam(0))
    try:
        set_policy(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        yield f"normal scheduling (SCHED_FIFO refused: {exc.strerror})"
        return
    try:
        yield f"SCHED_FIFO {priority}"
    finally:
        set_policy(0, previous[0], previous[1])
