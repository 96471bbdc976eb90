"""A word on the terminal while a command works in silence.

Every command that can take more than ~3 s says what it is doing; those without progress
of their own (compensate, geometry, import, history, ...) get this one:
when stderr is a terminal and the command has printed nothing for ``after_s``, one line
``elastocal compensate: working, 3 s so far`` on stderr, then one every ``every_s``. Nothing
when stderr is a file or a pipe (a script, a timer, a test reads the command's own lines).
"""

from __future__ import annotations

import sys
import threading
import time

#: commands that report their own progress (a bar, a line per step or per log)
OWN_PROGRESS = frozenset({"calibrate", "check", "demo", "devices", "fleet", "stream", "view", "schedule",
                          # elastocal.progress.long_work: their line after 3 s, kept going on a terminal
                          "identify", "diagnose", "report", "plan", "validate", "sim"})


class _Watched:
    """stdout or stderr, noting when the command last wrote to it."""

    def __init__(self, inner, heartbeat: "Heartbeat") -> None:
        self._inner, self._heartbeat = inner, heartbeat

    def write(self, text: str) -> int:
        self._heartbeat.touch()
        return self._inner.write(text)

    def __getattr__(self, name):
        return getattr(self._inner, name)


class Heartbeat:
    """``with Heartbeat(command):`` around a command's run (see the module docstring)."""

    def __init__(self, command: str, *, stream=None, after_s: float = 3.0, every_s: float = 10.0,
                 force: bool = False, serves: bool = False) -> None:
        self.command = command
        self.stream = stream if stream is not None else sys.stderr
        self.after_s, self.every_s = after_s, every_s
        try:
            terminal = self.stream.isatty()
        except (AttributeError, ValueError, OSError):
            terminal = False
        # a server (`sim serve`) is silent on purpose until Ctrl-C
        self.active = force or (terminal and command not in OWN_PROGRESS and not serves)
        self._clear = "\r\x1b[2K" if terminal else ""
        self._stop = threading.Event()
        self._t0 = self._last = time.monotonic()
        self._thread: threading.Thread | None = None
        self._saved = None

    def touch(self) -> None:
        self._last = time.monotonic()

    def _run(self) -> None:
        wait = self.after_s
        while not self._stop.wait(wait):
            quiet = time.monotonic() - self._last
            if quiet < self.after_s:                 # the command spoke lately: wait for it to fall silent
                wait = self.after_s - quiet
                continue
            # over a progress line left open on the terminal (elastocal/progress.py), not after it
            print(f"{self._clear}elastocal {self.command}: working, {time.monotonic() - self._t0:.0f} s so far",
                  file=self.stream, flush=True)
            self._last = time.monotonic() - self.after_s + self.every_s
            wait = self.every_s

    def __enter__(self) -> "Heartbeat":
        if self.active:            # what the command writes, on stdout or stderr, counts as speaking
            self._saved = (sys.stdout, sys.stderr)
            sys.stdout, sys.stderr = _Watched(sys.stdout, self), _Watched(sys.stderr, self)
            self._thread = threading.Thread(target=self._run, name="elastocal-heartbeat", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            sys.stdout, sys.stderr = self._saved
