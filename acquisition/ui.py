"""Operator interface in the terminal: progress, prompts, abort.

The procedure engine talks to an :class:`OperatorUI`; :class:`TerminalUI`
shows a progress bar (steps done, time left) on a terminal and asks the
operator to confirm every step that needs a person; typing ``a`` (or Ctrl-C,
or closing the input) at any prompt aborts. :class:`AutoUI` answers every
prompt itself (``--yes``, simulated cells and the demo) and can stay silent.
"""

from __future__ import annotations

import abc
import sys
from typing import Callable, TextIO

from elastocal.errors import ElastocalError


class Aborted(ElastocalError):
    """The operator aborted the procedure at a prompt."""


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


class OperatorUI(abc.ABC):
    """How the procedure reports progress and asks the operator."""

    #: True when prompts are answered without a person (--yes)
    automatic: bool = False

    @abc.abstractmethod
    def message(self, text: str) -> None:
        """A line of information for the operator."""

    @abc.abstractmethod
    def progress(self, done: int, total: int, label: str, elapsed_s: float, left_s: float | None) -> None:
        """Steps done of total, what is happening, time elapsed and estimated left."""

    @abc.abstractmethod
    def confirm(self, text: str) -> str:
        """Ask the operator to do something and confirm; returns the answer
        (``"yes"``) or raises :class:`Aborted`."""

    def close(self) -> None:
        """End the progress display."""


ABORT_WORDS = ("a", "abort", "q", "quit")
YES_WORDS = ("", "y", "yes", "ok")


class TerminalUI(OperatorUI):
    """Progress bar and prompts on a terminal (``stream``, default stderr)."""

    def __init__(self, stream: TextIO | None = None, read_line: Callable[[], str] | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self._read_line = read_line if read_line is not None else self._stdin_line
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._bar_shown = False
        self._last_plain = None

    @staticmethod
    def _stdin_line() -> str:
        line = sys.stdin.readline()
        if line == "":
            raise EOFError
        return line

    def _clear_bar(self) -> None:
        if self._bar_shown:
            self.stream.write("\r\x1b[2K")
            self._bar_shown = False

    def message(self, text: str) -> None:
        self._clear_bar()
        self.stream.write(text + "\n")
        self.stream.flush()

    def progress(self, done: int, total: int, label: str, elapsed_s: float, left_s: float | None) -> None:
        line = progress_line(done, total, label, elapsed_s, left_s)
        if self._tty:
            self.stream.write("\r\x1b[2K" + line)
            self._bar_shown = True
        elif (done, label) != self._last_plain:  # a log file: one line per change of step
            self.stream.write(line + "\n")
            self._last_plain = (done, label)
        self.stream.flush()

    def confirm(self, text: str) -> str:
        self._clear_bar()
        while True:
            self.stream.write(f">>> {text}; press Enter (a + Enter aborts): ")
            self.stream.flush()
            try:
                answer = self._read_line().strip().lower()
            except (EOFError, KeyboardInterrupt):
                self.stream.write("\n")
                raise Aborted(f"aborted by the operator at: {text}") from None
            if answer in YES_WORDS:
                return "yes"
            if answer in ABORT_WORDS:
                raise Aborted(f"aborted by the operator at: {text}")
            self.stream.write("    answer Enter to go on or 'a' to abort\n")

    def close(self) -> None:
        if self._bar_shown:
            self.stream.write("\n")
            self.stream.flush()
            self._bar_shown = False


class AutoUI(TerminalUI):
    """Answers every prompt with "yes" (``--yes``); ``stream=None`` with
    ``quiet=True`` prints nothing."""

    automatic = True

    def __init__(self, stream: TextIO | None = None, *, quiet: bool = False) -> None:
        super().__init__(stream)
        self.quiet = quiet
        self.prompts: list[str] = []

    def message(self, text: str) -> None:
        if not self.quiet:
            super().message(text)

    def progress(self, done: int, total: int, label: str, elapsed_s: float, left_s: float | None) -> None:
        if not self.quiet:
            super().progress(done, total, label, elapsed_s, left_s)

    def confirm(self, text: str) -> str:
        self.prompts.append(text)
        if not self.quiet:
            self.message(f">>> {text}: yes (--yes)")
        return "yes"

    def close(self) -> None:
        if not self.quiet:
            super().close()
