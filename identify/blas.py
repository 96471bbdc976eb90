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
them, which changes speed on a large machine, never a result. scipy is imported
where a fit first needs it (:func:`scipy_linalg`; a table without loads is fitted
with numpy's LAPACK alone): the BLAS library it brings into a running fit is
limited to one thread from then on.
"""

from __future__ import annotations

import functools
import sys
from typing import Callable, TypeVar

F = TypeVar("F", bound=Callable)


@functools.lru_cache(maxsize=2)
def _controller_of(with_scipy: bool):
    """threadpoolctl's view of the BLAS libraries loaded (numpy's, and scipy's once it is), found once
    per set: finding them costs milliseconds, limiting them microseconds."""
    import importlib

    from threadpoolctl import ThreadpoolController

    for module in ("numpy", "scipy.linalg") if with_scipy else ("numpy",):
        importlib.import_module(module)

    return ThreadpoolController()


def _controller():
    if "scipy.linalg" in sys.modules:
        _limit_late_blas()      # before a limit records scipy's setting, to restore it after
        return _controller_of(True)
    return _controller_of(False)


def scipy_linalg():
    """``scipy.linalg``, imported where a fit first needs it (a geometric calibration table's fit needs
    none of it, and its import costs more than that fit); the BLAS library scipy brings is limited to
    one thread (:func:`_limit_late_blas`)."""
    import scipy.linalg

    _limit_late_blas()
    return scipy.linalg


@functools.lru_cache(maxsize=1)
def _limit_late_blas() -> None:
    """Once per process: the BLAS libraries loaded after a fit began (scipy's, imported inside it) are
    limited to one thread from then on; the limit that fit entered held only the libraries loaded
    then. When scipy was loaded before any fit, the fits' own limit holds it and nothing is left."""
    from threadpoolctl import ThreadpoolController

    known = {lib.filepath for lib in _controller_of(False).lib_controllers}
    now = ThreadpoolController()
    late = [lib.filepath for lib in now.lib_controllers if lib.user_api == "blas" and lib.filepath not in known]
    if late:
        now.select(filepath=late).limit(limits=1, user_api="blas")


def one_blas_thread(fn: F) -> F:
    """Run ``fn`` with BLAS limited to one thread (module docstring)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with _controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
