"""The fits run BLAS on one thread while they run and leave the setting as it was
(identify/blas.py: small matrices on a shared machine)."""

from threadpoolctl import threadpool_info, threadpool_limits

from elastocal.identify.absolute import identify_absolute
from elastocal.identify.accuracy import validate
from elastocal.identify.blas import one_blas_thread
from elastocal.identify.static import identify_static
from elastocal.identify.trackernoise import estimate_tracker_noise


def blas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_inside_and_the_setting_restored_after():
    seen = []

    @one_blas_thread
    def probe(x):
        seen.append(blas_threads())
        return 2 * x

    with threadpool_limits(limits=2, user_api="blas"):
        assert probe(21) == 42
        assert seen[-1] and all(n == 1 for n in seen[-1])
        assert all(n == 2 for n in blas_threads())       # restored
        # nested: still one inside, restored after the outer one
        outer = one_blas_thread(lambda: (probe(1), blas_threads())[1])
        assert all(n == 1 for n in outer()) and all(n == 2 for n in blas_threads())


def test_the_fits_are_wrapped():
    for fn in (identify_static, identify_absolute, validate, estimate_tracker_noise):
        assert getattr(fn, "__wrapped__", None) is not None, fn.__name__
