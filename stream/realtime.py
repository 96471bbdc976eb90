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
import sys

#: SCHED_FIFO priority of the stream (1..99; below the kernel's own interrupt threads at 50 on PREEMPT_RT)
STREAM_PRIORITY = 40


#: the interpreter's switch interval while the stream runs: a thread that waits for the interpreter
#: lock gets it within a fraction of the 4 ms cycle (Python's default lets another keep it 5 ms)
SWITCH_INTERVAL_S = 2e-4


@contextlib.contextmanager
def realtime(priority: int = STREAM_PRIORITY):
    """Run the block (and the threads it starts) under SCHED_FIFO ``priority``, with a short
    interpreter switch interval; yields a description of the scheduling in force
    (``"SCHED_FIFO 40"`` or why not)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(min(interval, SWITCH_INTERVAL_S))
    try:
        with _fifo(priority) as description:
            yield description
    finally:
        sys.setswitchinterval(interval)


@contextlib.contextmanager
def _fifo(priority: int):
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
