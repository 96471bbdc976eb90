"""Running fleet tasks in parallel: on Dask, or on a local process pool.

:func:`run_tasks` sends every task to a worker process and gathers the results
in task order, calling ``progress`` as each one arrives.

* **Dask** (``dask.distributed``, the ``elastocal[fleet]`` extra): a running
  scheduler (``tcp://host:8786``), or a ``LocalCluster`` of ``workers``
  processes with one thread each, everything bound to 127.0.0.1 (its HTTP
  routes on a free port; no dashboard unless bokeh is installed).
* **Process pool** (``concurrent.futures``, no extra needed): ``workers``
  single-process pools, one task in each at a time.

The tasks and the function are the same either way, so are the results. A
worker process that dies (killed, out of memory, a crash in native code) takes
only its own task with it: that task is run once more, on a fresh worker, and
when its worker dies again it is recorded as a result with that error. On a
``LocalCluster`` and on the process pool that is exactly one retry (Dask's
``distributed.scheduler.allowed-failures`` = 1, one task per worker at a
time); a scheduler you started yourself applies its own
``allowed-failures`` (Dask's default: 3 retries).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import tempfile
from typing import Callable, Iterator, Sequence

from elastocal.errors import Arg, DeviceError, InputError
from elastocal.fleet.tasks import FleetTask, LogResult, error_text, run_task

#: times a task whose worker died is run again before it is recorded as failed
RETRIES = 1
#: how to get Dask
INSTALL_HINT = "pip install 'elastocal[fleet]' (dask, distributed, pyarrow)"
POOLS = ("auto", "dask", "processes")
#: the worker processes' numeric libraries run one thread each (as Dask's nanny sets them):
#: one task per core, and no oversubscription of a machine the workers share
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}

#: where a LocalCluster's scheduler and workers serve HTTP (Dask always serves some routes; without an
#: address the scheduler takes port 8787, which another cluster on the machine may hold)
LOOPBACK_ANY_PORT = "127.0.0.1:0"

Progress = Callable[[int, int, int, LogResult], None]


def dask_available() -> bool:
    """Whether ``dask.distributed`` can be imported."""
    import importlib.util

    return importlib.util.find_spec("dask") is not None and importlib.util.find_spec("distributed") is not None


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def died(task: FleetTask) -> LogResult:
    """The result of a task whose worker process died on every try."""
    return LogResult(path=task.path, command=task.command, cell=task.cell, cell_config=task.cell_config,
                     error=f"its worker process died {RETRIES + 1} times while analysing it (killed, out of "
                           "memory, or a crash in native code); not retried again")


def _failed(task: FleetTask, exc: BaseException) -> LogResult:
    return LogResult(path=task.path, command=task.command, cell=task.cell, cell_config=task.cell_config,
                     error=error_text(exc))


def resolve_pool(pool: str, scheduler: str | None) -> str:
    """``dask`` or ``processes`` for the requested ``pool`` (``auto``: Dask when installed)."""
    if pool not in POOLS:
        raise InputError(f"must be one of {', '.join(POOLS)}, got {pool!r}", argument="pool")
    if scheduler and pool == "processes":
        raise InputError("a Dask scheduler and the process pool exclude each other", argument="scheduler")
    if pool == "auto":
        pool = "dask" if scheduler or dask_available() else "processes"
    if pool == "dask" and not dask_available():
        raise InputError(f"needs dask.distributed, which is not installed: {INSTALL_HINT}",
                         argument="scheduler" if scheduler else "pool")
    return pool


def run_tasks(tasks: Sequence[FleetTask], *, pool: str = "auto", scheduler: str | None = None,
              workers: int | None = None, progress: Progress | None = None,
              fn: Callable[[FleetTask], LogResult] = run_task) -> list[LogResult]:
    """``fn`` (default :func:`~elastocal.fleet.tasks.run_task`) on every task, in
    parallel; the results in task order. ``fn`` must be importable by name in
    the worker processes."""
    tasks = list(tasks)
    kind = resolve_pool(pool, scheduler)
    if workers is not None and workers < 1:
        raise InputError(f"must be at least 1, got {workers}", argument="workers")
    if scheduler and workers is not None:
        raise InputError(("the scheduler's workers do the work; ", Arg("workers"), " sizes a local cluster"),
                         argument="workers")
    n_workers = workers or default_workers()
    results: list[LogResult | None] = [None] * len(tasks)
    failed = 0

    def arrived(i: int, result: LogResult) -> None:
        nonlocal failed
        results[i] = result
        failed += 0 if result.ok else 1
        if progress is not None:
            progress(sum(r is not None for r in results), len(tasks), failed, result)

    if tasks:
        runner = _dask if kind == "dask" else _processes
        for i, result in runner(tasks, fn, scheduler=scheduler, workers=min(n_workers, len(tasks))):
            arrived(i, result)
    return [r for r in results if r is not None]


# ----------------------------------------------------------------------- Dask
def _dask(tasks: list[FleetTask], fn, *, scheduler: str | None, workers: int) -> Iterator[tuple[int, LogResult]]:
    import dask
    from distributed import Client, LocalCluster, as_completed
    from distributed.scheduler import KilledWorker

    settings = {"distributed.scheduler.allowed-failures": RETRIES,
                # one task per single-thread worker at a time: a worker that dies takes only its own task
                "distributed.scheduler.worker-saturation": 1.0}
    with contextlib.ExitStack() as stack:
        # the run's own scratch space, gone with it: Dask's default, $TMPDIR/dask-scratch-space
        # (its workers' files and the lock files its nannies take even beside a local_directory),
        # stays behind
        scratch = stack.enter_context(tempfile.TemporaryDirectory(prefix="elastocal-dask-"))
        stack.enter_context(dask.config.set({**settings, "temporary-directory": scratch}))
        if scheduler:
            try:
                client = stack.enter_context(Client(scheduler, timeout="20s"))
            except (OSError, TimeoutError, ValueError) as exc:
                raise DeviceError(f"cannot reach the Dask scheduler {scheduler}: {error_text(exc)}") from None
        else:
            cluster = stack.enter_context(LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                dashboard_address=LOOPBACK_ANY_PORT, worker_dashboard_address=LOOPBACK_ANY_PORT,
                silence_logs=logging.CRITICAL, local_directory=scratch))
            client = stack.enter_context(Client(cluster))
        futures = client.map(fn, tasks, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        for future in as_completed(futures):
            i = index[future.key]
            try:
                result = future.result()
            except KilledWorker:
                result = died(tasks[i])
            except Exception as exc:  # noqa: BLE001 -- e.g. a result that cannot travel back: its file's error
                result = _failed(tasks[i], exc)
            future.release()
            yield i, result


# ------------------------------------------------------------ process pool
@contextlib.contextmanager
def _single_thread_children() -> Iterator[None]:
    """Child processes started inside get :data:`SINGLE_THREAD_ENV` (unless the user set those)."""
    added = {k: v for k, v in SINGLE_THREAD_ENV.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def _processes(tasks: list[FleetTask], fn, *, scheduler: str | None, workers: int
               ) -> Iterator[tuple[int, LogResult]]:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    context = multiprocessing.get_context("spawn")   # as Dask's workers: no state inherited from this process

    def fresh() -> ProcessPoolExecutor:
        return ProcessPoolExecutor(max_workers=1, mp_context=context)

    pending = collections.deque(range(len(tasks)))
    deaths = [0] * len(tasks)
    running: dict = {}            # future -> (slot, task index)
    with _single_thread_children():
        slots = [fresh() for _ in range(workers)]
        try:
            while pending or running:
                busy = {slot for slot, _ in running.values()}
                for slot in range(workers):
                    if slot not in busy and pending:
                        i = pending.popleft()
                        running[slots[slot].submit(fn, tasks[i])] = (slot, i)
                done, _ = wait(list(running), return_when=FIRST_COMPLETED)
                for future in done:
                    slot, i = running.pop(future)
                    try:
                        result = future.result()
                    except BrokenProcessPool:   # this slot's one process died, running task i
                        slots[slot].shutdown(wait=False, cancel_futures=True)
                        slots[slot] = fresh()
                        deaths[i] += 1
                        if deaths[i] <= RETRIES:
                            pending.appendleft(i)
                            continue
                        result = died(tasks[i])
                    except Exception as exc:  # noqa: BLE001 -- a result that cannot travel back: its file's error
                        result = _failed(tasks[i], exc)
                    yield i, result
        finally:
            for executor in slots:
                executor.shutdown(wait=True, cancel_futures=True)
