"""Fixtures shared by the test files, and the test suite's markers.

* ``robot``: the bundled HH-150 :class:`~elastocal.model.robot.Robot`. The robot model
  is immutable (Pinocchio data are per call), so one instance serves the whole session.
* ``robot_path``: its robot.toml.
* ``static_dataset``: a small simulated static experiment (``elastocal sim static``:
  robot.toml, static.csv, log.mcap, truth.json) in a session folder; copy it before
  changing a file in it.
* ``runs_dataset``: the same for ``elastocal sim runs`` with friction hidden.

Markers (registered in pyproject.toml): ``slow`` marks tests that run simulated devices or
procedures in wall-clock time; ``python -m pytest -m "not slow"`` leaves them out for a
quick run. ``heavy`` marks statistics over hundreds of seeds and long end-to-end runs:
the default run leaves them out (``-m 'not heavy'`` in pyproject's addopts), ``python -m
pytest -m heavy`` runs them (the ``acceptance`` ones among them), and ``.ci/run`` runs
both. A heavy test is slow too.

The run is spread over the cores by pytest-xdist (``-n auto --dist loadgroup``): the tests
of a module that share one of its module-scoped fixtures (or a session-scoped one the
module defines) go to one worker, so the fixture is computed once; every other test goes
wherever a worker is free. Session fixtures are made once per worker. Each worker, and
each process a test starts, runs BLAS on one thread (the workers already fill the cores). A test therefore never assumes it runs alone: ports are 0 (the
system picks), files go to ``tmp_path``, and global state is restored by a fixture.

A run leaves nothing behind: files go to ``tmp_path`` (pytest removes a green run's
folders, ``tmp_path_retention_policy = "failed"``), and the session's end lists whatever
appeared in the temporary folder or in ~/.config during the run (a warning; a failure
with ``ELASTOCAL_CHECK_LEFTOVERS=1``, as ``.ci/run`` sets: on a shared machine another
user's files may show up). Matplotlib's configuration folder is the session's own.

A new test file uses these by naming them as arguments; a file that needs another robot
defines its own fixture of the same name, which takes precedence in that file.
"""

from __future__ import annotations

import os
import pathlib
import tempfile

import pytest

# One BLAS thread per test process, set before numpy or scipy loads (so also in the xdist
# workers and the subprocesses, which inherit it): xdist already runs one worker per core,
# and BLAS threads beside them only oversubscribe the cores. Idle OpenBLAS threads spin, and
# the many small solves of the simulations and of scipy's L-BFGS-B then cost up to 17 times
# the CPU time (the tracker-noise law of build_dataset after a fit: 0.34 s against 0.02 s
# per HH-150 table). A value already in the environment is kept.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path  # noqa: E402


#: where a run must leave nothing: the temporary folder and the user's configuration
WATCHED = (pathlib.Path(tempfile.gettempdir()), pathlib.Path.home() / ".config")
_LEFTOVER_KEY = pytest.StashKey[dict]()


def _entries() -> dict[pathlib.Path, set[str]]:
    return {d: set(os.listdir(d)) if d.is_dir() else set() for d in WATCHED}


def pytest_configure(config):
    if hasattr(config, "workerinput"):              # an xdist worker: it sends the tests' ids to the scheduler
        config.pluginmanager.register(_GroupSuffix(), "elastocal-xdist-group-suffix")
    else:          # the controller (or a run without workers)
        config.stash[_LEFTOVER_KEY] = _entries()
        # matplotlib makes ~/.config/matplotlib on first import: this session's one instead
        # (inherited by the xdist workers and by subprocesses), removed at the end
        if "MPLCONFIGDIR" not in os.environ:
            os.environ["MPLCONFIGDIR"] = tempfile.mkdtemp(prefix="elastocal-tests-mpl-")
            config.stash[_MPL_KEY] = os.environ["MPLCONFIGDIR"]


_MPL_KEY = pytest.StashKey[str]()


def pytest_unconfigure(config):
    import shutil

    mpl = config.stash.get(_MPL_KEY, None)
    if mpl:
        shutil.rmtree(mpl, ignore_errors=True)


@pytest.hookimpl(trylast=True)          # after pytest's own removal of a green run's tmp_path folders
def pytest_sessionfinish(session, exitstatus):
    config = session.config
    before = config.stash.get(_LEFTOVER_KEY, None)
    if before is None:
        return
    mpl = config.stash.get(_MPL_KEY, None)
    user_root = f"pytest-of-{_user()}"
    left = []
    for folder, names in _entries().items():
        for name in sorted(names - before[folder]):
            path = folder / name
            if mpl and path == pathlib.Path(mpl):
                continue                                # removed at pytest_unconfigure
            # pytest's own root of its numbered folders stays, without a file once a green run is removed
            if name == user_root and path.is_dir() and not any(p.is_file() for p in path.rglob("*")):
                continue
            left.append(str(path))
    if not left:
        return
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    strict = os.environ.get("ELASTOCAL_CHECK_LEFTOVERS") == "1"
    if reporter is not None:
        reporter.ensure_newline()
        reporter.write_line(f"{'error' if strict else 'warning'}: this test run left {', '.join(left)}",
                            red=strict, yellow=not strict)
    if strict and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def _user() -> str:
    import getpass

    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "unknown"


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.get_closest_marker("heavy") and not item.get_closest_marker("slow"):
            item.add_marker(pytest.mark.slow)
        if not item.get_closest_marker("xdist_group") and _uses_module_fixture(item):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))


def _uses_module_fixture(item) -> bool:
    """Whether the test needs a fixture computed once per module (or class): a module-,
    class- or package-scoped one, or a session-scoped one its own module defines (only
    that module's tests use it, so on two workers it would be computed twice)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    module = item.module.__name__
    return any(defs and (defs[-1].scope in ("module", "class", "package")
                         or defs[-1].scope == "session" and getattr(defs[-1].func, "__module__", None) == module)
               for defs in info.name2fixturedefs.values())


class _GroupSuffix:
    """pytest-xdist's loadgroup tells its scheduler a test's group by appending ``@group`` to
    the test's id in the worker, through ``item._nodeid``; pytest 9 keeps the id in
    ``item._id``, so the suffix never arrives and every test is scheduled alone (a module's
    fixture then computed on each worker: the heavy fleet fixtures twice, ~50 s of CPU each).
    https://github.com/pytest-dev/pytest-xdist/issues/1386. This appends it where xdist
    could not, and does nothing where xdist did (an older pytest, a fixed xdist)."""

    @pytest.hookimpl(trylast=True)          # after xdist's hook of the same name
    def pytest_collection_modifyitems(self, config, items):
        try:
            from _pytest.nodeid import NodeId       # pytest >= 9
        except ImportError:
            return
        if not config.getvalue("loadgroup"):
            return

        for item in items:
            names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                            for m in item.iter_markers("xdist_group")})
            if names and "@" not in item.nodeid.rpartition("]")[2] and isinstance(getattr(item, "_id", None), NodeId):
                item._id = NodeId.parse(f"{item.nodeid}@{'_'.join(names)}")


@pytest.fixture(scope="session")
def robot():
    """The bundled HH-150 (immutable: shared by every test)."""
    return bundled_robot()


@pytest.fixture(scope="session")
def robot_path() -> pathlib.Path:
    return bundled_robot_path()


@pytest.fixture(scope="session")
def static_dataset(tmp_path_factory) -> pathlib.Path:
    """``elastocal sim static --seed 1 --poses 6`` (no hidden effect), made once per session."""
    from elastocal.cli import main

    out = tmp_path_factory.mktemp("static-dataset")
    assert main(["sim", "static", "--hidden", "none", "--seed", "1", "--poses", "6", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def runs_dataset(tmp_path_factory) -> pathlib.Path:
    """``elastocal sim runs --hidden friction --seed 5``, made once per session."""
    from elastocal.cli import main

    out = tmp_path_factory.mktemp("runs-dataset")
    assert main(["sim", "runs", "--hidden", "friction", "--seed", "5", "--out", str(out)]) == 0
    return out


class Terminal:
    """A child process on a pseudo-terminal: what it shows, what we type."""

    def __init__(self, args):
        import os
        import subprocess

        self.master, slave = os.openpty()
        self.proc = subprocess.Popen(args, stdin=slave, stdout=slave, stderr=slave, close_fds=True,
                                     start_new_session=True)
        os.close(slave)
        self.screen = ""

    def read(self, seconds: float) -> None:
        import os
        import select
        import time

        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            ready, _, _ = select.select([self.master], [], [], left)
            if not ready:
                return
            try:
                chunk = os.read(self.master, 65536)
            except OSError:          # the child closed the terminal
                return
            if not chunk:
                return
            self.screen += chunk.decode("utf-8", errors="replace")

    def wait_for(self, text: str, timeout_s: float, start: int = 0) -> int:
        import time

        end = time.monotonic() + timeout_s
        while text not in self.screen[start:]:
            if time.monotonic() > end or (self.proc.poll() is not None and not self._more()):
                raise AssertionError(f"{text!r} not shown in {timeout_s} s; screen:\n{self.screen[-3000:]}")
            self.read(0.2)
        return self.screen.index(text, start)

    def _more(self) -> bool:
        before = len(self.screen)
        self.read(0.2)
        return len(self.screen) > before

    def type(self, text: str) -> None:
        import os

        os.write(self.master, text.encode())

    def close(self) -> None:
        import os

        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        os.close(self.master)


@pytest.fixture(name="Terminal")
def terminal_class():
    """:class:`Terminal`: a child process on a real pseudo-terminal (what it shows, what is typed)."""
    return Terminal


@pytest.fixture(autouse=True, scope="session")
def _quick_commands_say_no_progress():
    """A command's progress (elastocal.progress.long_work) speaks once its work has taken 3 s; on a
    busy test machine a small command can take that long, and the tests that read its stderr line
    by line would read progress lines too. Silent unless a test asks for it
    (tests/test_progress_commands.py sets the time to 0)."""
    import elastocal.progress

    with pytest.MonkeyPatch.context() as mp:      # session-wide: module fixtures run commands too
        mp.setattr(elastocal.progress, "LONG_WORK_S", float("inf"))
        yield
