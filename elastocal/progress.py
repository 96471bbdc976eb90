"""Progress of long work on stderr, one way for every command.

``[#########---------------] 4/12  static pose P4  1:23 elapsed, ~3:10 left`` — the units done
of the total, what is under way, the time so far and the time left at the pace so far. On a
terminal the line is redrawn in place; to a file or a pipe (a log, a timer's journal, a test)
a line is written per unit of work, or per tenth of the work when there are many. ``quiet``
(a command's ``--json``: stdout holds exactly one JSON object, and whoever reads it is a
program) says nothing. The guided procedure's operator interface (acquisition/ui.py), the
fleet's tasks and the simulated plant's logs all report through it; so do identify, diagnose,
report, plan, validate and sim static/runs (:func:`long_work`: silent for a quick run, then the
stage or the fit under way), their libraries through a callback they are handed; a command
without units of its own gets the heartbeat of elastocal/commands/_heartbeat.py.

Neither ``rich`` nor ``tqdm`` is a dependency of elastocal: this is the one small module
instead of a third dependency for one line of text.
"""

from __future__ import annotations

import sys
import threading
import time

#: to a file or pipe, a line per unit of work up to this many units, else a line per tenth
EVERY_UNIT_UP_TO = 20

#: work shorter than this says nothing (:func:`long_work`): a quick run's stderr stays its notes [s]
LONG_WORK_S = 3.0
#: on a terminal, a long work's line is redrawn this often while one unit runs [s]
REDRAW_S = 1.0


def format_duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def progress_line(done: int, total: int, label: str, elapsed_s: float, left_s: float | None,
                  width: int = 24) -> str:
    """``[#########-----] 4/12  static P4  1:23 elapsed, ~3:10 left``"""
    filled = 0 if total == 0 else int(round(width * done / total))
    bar = "#" * filled + "-" * (width - filled)
    left = "" if left_s is None else f", ~{format_duration(left_s)} left"
    return f"[{bar}] {done}/{total}  {label}  {format_duration(elapsed_s)} elapsed{left}"


def is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class Progress:
    """``progress(done, label)`` as the work goes, ``progress.done()`` at its end (module docstring).
    ``total`` may grow (``progress(done, label, total=...)``); ``failed`` adds ``, N failed``.
    ``after_s``: nothing is said before the work has taken that long; used as a context manager
    (``with long_work(...) as progress:``) it then says where the work stands even when the
    work's current unit is a long one (a watcher thread; on a terminal it keeps the elapsed time
    going), and ends its line however the work ends."""

    def __init__(self, command: str, total: int, *, stream=None, quiet: bool = False,
                 clock=time.monotonic, after_s: float = 0.0) -> None:
        self.command, self.total, self.quiet = command, int(total), quiet
        self.after_s = after_s
        self.stream = sys.stderr if stream is None else stream
        self.terminal = is_terminal(self.stream)
        self._clock = clock
        self._t0 = clock()
        self._shown = -1              # the last tenth written (files and pipes, many units)
        self._open = False            # a terminal line is drawn and not yet ended
        self._said = False            # a line was written
        self._last: tuple[int, str, int | None] = (0, "", None)     # where the work stands: done, label, failed
        self._lock = threading.Lock()
        self._stop: threading.Event | None = None      # the watcher's (``with``, after_s > 0)
        self._watcher: threading.Thread | None = None

    def __call__(self, done: int, label: str = "", *, total: int | None = None, failed: int | None = None) -> None:
        if total is not None:
            self.total = int(total)
        if self.quiet:
            return
        with self._lock:
            self._last = (done, label, failed)
            elapsed = self._clock() - self._t0
            if elapsed < self.after_s:
                return
            self._say(done, label, failed, elapsed)

    def _say(self, done: int, label: str, failed: int | None, elapsed: float) -> None:
        left = elapsed / done * (self.total - done) if 0 < done < self.total else (0.0 if done else None)
        text = f"{self.command}: {progress_line(done, self.total, label, elapsed, left)}"
        if failed:
            text += f", {failed} failed"
        finished = done >= self.total
        self._said = True
        if self.terminal:
            print(f"\r\x1b[2K{text}", end="\n" if finished else "", file=self.stream, flush=True)
            self._open = not finished
            return
        if self.total > EVERY_UNIT_UP_TO:
            tenth = done * 10 // max(self.total, 1)
            if tenth == self._shown and not finished:
                return
            self._shown = tenth
        print(text, file=self.stream, flush=True)

    def _watch(self, stop: threading.Event) -> None:
        """The work has taken ``after_s`` and said nothing yet: where it stands; then, on a
        terminal, the line redrawn every :data:`REDRAW_S` so its elapsed time keeps going while
        one long unit runs (a file gets a line per unit only)."""
        if stop.wait(self.after_s):
            return
        with self._lock:
            if not self._said:
                self._say(*self._last, self._clock() - self._t0)
        while self.terminal and not stop.wait(REDRAW_S):
            with self._lock:
                if self._open:
                    self._say(*self._last, self._clock() - self._t0)

    def done(self, label: str = "done", *, failed: int | None = None) -> None:
        self(self.total, label, failed=failed)

    def close(self) -> None:
        """End a terminal line left open (the work stopped before its end)."""
        if self._watcher is not None:
            self._stop.set()
            self._watcher.join()
            self._watcher = None
        with self._lock:
            if self._open and not self.quiet:
                print(file=self.stream, flush=True)
                self._open = False

    def __enter__(self) -> "Progress":
        if 0 < self.after_s < float("inf") and not self.quiet:
            self._stop = threading.Event()
            self._watcher = threading.Thread(target=self._watch, args=(self._stop,), name="elastocal-progress",
                                             daemon=True)
            self._watcher.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def long_work(command: str, total: int, *, quiet: bool = False, stream=None) -> Progress:
    """The progress of a command whose work is quick on small inputs and long on large ones: silent
    for its first :data:`LONG_WORK_S`, then as :class:`Progress` (``with long_work(...) as
    progress:``). The library it calls reports through it as a callback, ``progress(done, label,
    total=...)``; nothing prints in the library."""
    return Progress(command, total, quiet=quiet, stream=stream, after_s=LONG_WORK_S)
