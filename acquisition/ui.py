"""Operator interface in the terminal: progress, prompts, abort.

The procedure engine talks to an :class:`OperatorUI`; :class:`TerminalUI`
shows a progress bar (steps done, time left) on a terminal and asks the
operator to confirm every step that needs a person — with a deliberate
``yes`` (or the load's name) typed after the prompt appeared; typing ``a``
(or Ctrl-C, or closing the input) at any prompt aborts. :class:`AutoUI` answers every
prompt itself (``--yes``, simulated cells and the demo) and can stay silent.
"""

from __future__ import annotations

import abc
import contextlib
import os
import sys
import threading
from typing import Callable, TextIO

from elastocal.errors import ElastocalError
from elastocal.progress import progress_line


class Aborted(ElastocalError):
    """The operator aborted the procedure at a prompt."""


class OperatorUI(abc.ABC):
    """How the procedure reports progress and asks the operator."""

    #: True when prompts are answered without a person (--yes)
    automatic: bool = False
    #: who answers the prompts, as the log records it with each answer
    answer_source: str = "operator"

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

    def confirm_load(self, text: str, load_id: str) -> str:
        """Ask the operator to change the load (hang or remove ``load_id``); a
        terminal accepts the load's name as the answer too. By default the
        same as :meth:`confirm`."""
        return self.confirm(text)

    def close(self) -> None:
        """End the progress display."""


class NotATerminal(Exception):
    """The standard input is not a terminal: nobody can be asked."""


#: why a prompt is never answered from a pipe or a file
NOT_A_TERMINAL = ("the standard input is not a terminal (a pipe or a file): prompts are answered by a person "
                  "at the terminal")


def stdin_is_terminal() -> bool:
    """True when the standard input is a terminal (a person can answer prompts there)."""
    return TerminalUI._stdin_fd() is not None


ABORT_WORDS = ("a", "abort", "q", "quit")
#: the deliberate answer to a prompt (a bare Enter, or a key pressed while the robot moved, is not one)
YES_WORDS = ("yes",)


def flush_typed_ahead(fd: int) -> None:
    """Discard what was typed on the terminal ``fd`` and not read yet (a key
    pressed while the robot moved must not answer the next prompt)."""
    import termios

    with contextlib.suppress(termios.error, OSError):   # not a terminal (a pipe, a file): nothing typed ahead
        termios.tcflush(fd, termios.TCIFLUSH)


class TerminalUI(OperatorUI):
    """Progress bar and prompts on a terminal (``stream``, default stderr;
    answers from ``read_line``, default the standard input).

    Safety on the shop floor:

    * before every prompt, input typed ahead is discarded (``termios.tcflush``
      on a terminal; ``flush_input`` replaces it): only a key pressed after
      the prompt was shown answers it;
    * only a terminal answers: a pipe or a file on the standard input answers
      nothing (the first prompt aborts the procedure, :data:`NOT_A_TERMINAL`);
    * the answer must be deliberate: ``yes`` (or, for a load change, the
      load's name), then Enter; a bare Enter asks again;
    * a prompt that waits stays the last thing on the screen: output while it
      waits (progress, messages, from any thread) goes above it and the prompt
      is drawn again.
    """

    def __init__(self, stream: TextIO | None = None, read_line: Callable[[], str] | None = None,
                 flush_input: Callable[[], None] | None = None, source: str | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self._read_line = read_line if read_line is not None else self._stdin_line
        if source is None:
            fd = self._stdin_fd() if read_line is None else None
            source = ("read_line" if read_line is not None else
                      f"terminal {os.ttyname(fd)}" if fd is not None else "no terminal")
        self.answer_source = source
        if flush_input is None:
            flush_input = (lambda: None) if read_line is not None else self._flush_stdin
        self._flush_input = flush_input
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._bar_shown = False
        self._last_plain = None
        self._lock = threading.RLock()
        self._waiting: str | None = None       # the prompt on the screen while it waits for its answer

    @staticmethod
    def _stdin_fd() -> int | None:
        try:
            fd = sys.stdin.fileno()
        except (AttributeError, OSError, ValueError):
            return None
        return fd if os.isatty(fd) else None

    @classmethod
    def _flush_stdin(cls) -> None:
        fd = cls._stdin_fd()
        if fd is not None:
            flush_typed_ahead(fd)

    @classmethod
    def _stdin_line(cls) -> str:
        fd = cls._stdin_fd()
        if fd is None:      # a pipe or a file answers nothing: a person at a terminal does
            raise NotATerminal(NOT_A_TERMINAL)
        # on a terminal, straight from the descriptor: nothing typed ahead waits in a Python buffer
        data = b""
        while not data.endswith(b"\n"):
            chunk = os.read(fd, 1024)
            if not chunk:
                raise EOFError
            data += chunk
        return data.decode("utf-8", errors="replace")

    def _clear_bar(self) -> None:
        if self._bar_shown:
            self.stream.write("\r\x1b[2K")
            self._bar_shown = False

    def _above_prompt(self, line: str) -> None:
        """``line`` above the waiting prompt, then the prompt again."""
        self.stream.write(("\r\x1b[2K" if self._tty else "\n") + line + "\n" + self._waiting)
        self.stream.flush()

    def message(self, text: str) -> None:
        with self._lock:
            if self._waiting is not None:
                self._above_prompt(text)
                return
            self._clear_bar()
            self.stream.write(text + "\n")
            self.stream.flush()

    def progress(self, done: int, total: int, label: str, elapsed_s: float, left_s: float | None) -> None:
        line = progress_line(done, total, label, elapsed_s, left_s)
        with self._lock:
            if self._waiting is not None:       # never over a prompt that waits
                if self._tty or (done, label) != self._last_plain:
                    self._last_plain = (done, label)
                    self._above_prompt(line)
                return
            if self._tty:
                self.stream.write("\r\x1b[2K" + line)
                self._bar_shown = True
            elif (done, label) != self._last_plain:  # a log file: one line per change of step
                self.stream.write(line + "\n")
                self._last_plain = (done, label)
            self.stream.flush()

    def confirm(self, text: str) -> str:
        return self._ask(text, ())

    def confirm_load(self, text: str, load_id: str) -> str:
        return self._ask(text, (load_id,))

    def _ask(self, text: str, names: tuple[str, ...]) -> str:
        accepted = YES_WORDS + tuple(n.lower() for n in names)
        say = " or ".join(f"'{w}'" for w in (*YES_WORDS, *names))
        prompt = f">>> {text}; type {say} and Enter (a + Enter aborts): "
        while True:
            with self._lock:
                self._clear_bar()
                self._flush_input()             # keys pressed before the prompt was shown do not answer it
                self._waiting = prompt
                self.stream.write(prompt)
                self.stream.flush()
            try:
                try:
                    answer = self._read_line().strip().lower()
                finally:
                    with self._lock:
                        self._waiting = None
            except NotATerminal:
                self.stream.write("\n")
                raise Aborted(f"{NOT_A_TERMINAL}; aborted at: {text}") from None
            except (EOFError, KeyboardInterrupt):
                self.stream.write("\n")
                raise Aborted(f"aborted by the operator at: {text}") from None
            if answer in accepted:
                return "yes"
            if answer in ABORT_WORDS:
                raise Aborted(f"aborted by the operator at: {text}")
            with self._lock:
                self.stream.write(f"    answer {say} to go on, or 'a' to abort\n")

    def close(self) -> None:
        with self._lock:
            if self._bar_shown:
                self.stream.write("\n")
                self.stream.flush()
                self._bar_shown = False


class AutoUI(TerminalUI):
    """Answers every prompt with "yes" (``--yes``); ``stream=None`` with
    ``quiet=True`` prints nothing. ``answered_by`` says who answered in the
    transcript (the CLI names its flag)."""

    automatic = True

    def __init__(self, stream: TextIO | None = None, *, quiet: bool = False,
                 answered_by: str = "answered automatically") -> None:
        super().__init__(stream, read_line=lambda: "yes", source=answered_by)
        self.quiet = quiet
        self.answered_by = answered_by
        self.prompts: list[str] = []

    def message(self, text: str) -> None:
        if not self.quiet:
            super().message(text)

    def progress(self, done: int, total: int, label: str, elapsed_s: float, left_s: float | None) -> None:
        if not self.quiet:
            super().progress(done, total, label, elapsed_s, left_s)

    def confirm_load(self, text: str, load_id: str) -> str:
        return self.confirm(text)

    def confirm(self, text: str) -> str:
        self.prompts.append(text)
        if not self.quiet:
            self.message(f">>> {text}: yes ({self.answered_by})")
        return "yes"

    def close(self) -> None:
        if not self.quiet:
            super().close()
