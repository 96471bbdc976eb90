"""The fits run their linear algebra on one BLAS thread.

Their matrices are small and many (thousands of rows, tens of columns; per-pose
blocks of tens): OpenBLAS's threads cost more to wake than they save, and on a
shared machine every process's threads compete for the same cores, so each
small call waits for all of them. Measured on the shared 2-core development
machine (load average 10): ``lstsq`` of 2160 x 90 took 1.6-2.4 s with OpenBLAS's
two threads and 0.05-0.06 s on one; a 27 x 27 triangular solve 3.9 ms against
0.19 ms. :func:`one_blas_thread` limits BLAS to one thread while a fit runs
(threadpoolctl, the library for it) and restores the setting after; results
differ at most in their last bits (sums taken in another order). The setting is
the process's: fits running at once in several threads (a viewer's server, a
thread pool) may restore it in another order and leave BLAS on one thread after
them, which changes speed on a large machine, never a result.
"""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

F = TypeVar("F", bound=Callable)


@functools.lru_cache(maxsize=1)
def _controller():
    """threadpoolctl's view of the BLAS libraries loaded (numpy's and scipy's), found once:
    finding them costs milliseconds, limiting them microseconds."""
    import importlib

    from threadpoolctl import ThreadpoolController

    for module in ("numpy", "scipy.linalg"):      # both BLAS libraries loaded before they are looked up
        importlib.import_module(module)

    return ThreadpoolController()


def one_blas_thread(fn: F) -> F:
    """Run ``fn`` with BLAS limited to one thread (module docstring)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
