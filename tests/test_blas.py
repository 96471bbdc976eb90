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


PROBE = """
import sys, json
from threadpoolctl import threadpool_info
from elastocal.formats.robot_toml import bundled_robot, load_robot
from elastocal.formats.tables import read_static_table
from elastocal.identify.absolute import identify_absolute
from elastocal.identify.static import identify_static
ctu = {ctu!r}
robot = load_robot(ctu + "/robot.toml")
identify_absolute(robot, read_static_table(ctu + "/train.csv", robot), model=("kinematic_errors", "tracker_frame"))
after_absolute = any(m in sys.modules for m in ("scipy.linalg", "scipy.optimize", "scipy.stats"))
numpys = [i["filepath"] for i in threadpool_info() if i["user_api"] == "blas"]
from elastocal.sims.cell import CellTruth
from elastocal.sims.static import StaticPlan, simulate_static
hh = bundled_robot()
table = simulate_static(hh, CellTruth(), seed=1, plan=StaticPlan(n_poses=6))
before_static = "scipy.linalg" in sys.modules
identify_static(hh, table)
blas = [(i["filepath"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"
        and i["filepath"] not in numpys]
print(json.dumps([after_absolute or before_static, "scipy.linalg" in sys.modules, blas]))
"""


def test_a_table_without_loads_fits_without_scipys_solvers_and_a_fit_that_loads_them_limits_their_blas():
    """The geometric calibration of a table without loads imports none of scipy's linear algebra,
    optimisation or statistics (their import cost a command more than the fit); the deflection fit imports scipy.linalg where it first needs it and leaves its
    BLAS library on one thread (the fit's limit held the libraries loaded when it began)."""
    import json
    import pathlib
    import subprocess
    import sys

    data = pathlib.Path(__file__).parent / "data"
    code = PROBE.format(ctu=str(data / "ctu_motoman"))
    import os

    # two threads where nothing limits them (the test run's own environment sets one)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True,
                          env=env)
    after_absolute, scipy_loaded, blas = json.loads(done.stdout.strip().splitlines()[-1])
    assert after_absolute is False and scipy_loaded is True
    assert all(n == 1 for _, n in blas), blas          # the BLAS libraries scipy brought (none if shared)
