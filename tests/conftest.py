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
quick run (CI runs everything).

A new test file uses these by naming them as arguments; a file that needs another robot
defines its own fixture of the same name, which takes precedence in that file.
"""

from __future__ import annotations

import pathlib

import pytest

from elastocal.formats.robot_toml import bundled_robot, bundled_robot_path


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
