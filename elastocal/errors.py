"""Typed errors shared by every part of elastocal.

The CLI maps :class:`InputError` (a bad file, table, flag or config value, and
every refusal the data decide: :class:`EffectRefused`, :class:`UnidentifiableError`)
to exit code 2 and :class:`DeviceError` (and its subclasses) to exit code 1,
printing ``str(error)`` as one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence, Union


class ElastocalError(Exception):
    """Base of every expected error: its message is one line for the user."""


@dataclass(frozen=True)
class Arg:
    """A library argument that a message names (what to give, or what was wrong), said as
    its reader knows it: by the library as the keyword (``torque='force'``), on a command
    line as the flag (``--torque force``; :meth:`InputError.on_command_line`). ``value``:
    None names the argument itself, True a switch to turn on, anything else the value."""

    name: str
    value: object = None

    def library(self) -> str:
        if self.value is None:
            return self.name
        return f"{self.name}={self.value!r}"

    def command_line(self, flags: "Mapping[str, str] | None" = None) -> str:
        flag = flag_of(self.name, flags)
        return flag if self.value is None or self.value is True else f"{flag} {self.value}"


def flag_of(argument: str, flags: "Mapping[str, str] | None" = None) -> str:
    """The command-line flag of a library argument: ``flags[argument]``, else ``--`` and the
    argument with dashes (``exclude_outliers`` -> ``--exclude-outliers``)."""
    return (flags or {}).get(argument, "--" + argument.replace("_", "-"))


#: a message: a text, or texts and the arguments it names (:class:`Arg`), in order
Message = Union[str, Sequence[Union[str, Arg]]]


def say(message: Message, flags: "Mapping[str, str] | None" = None, *, command_line: bool = False) -> str:
    """``message`` as one text: its arguments in the library's words, or as flags (``command_line``)."""
    if isinstance(message, str):
        return message
    return "".join(p if isinstance(p, str) else p.command_line(flags) if command_line else p.library()
                   for p in message)


class InputError(ElastocalError, ValueError):
    """A file, table, flag or config value is wrong.

    ``source`` names the input (a path, or a flag when the CLI raises it), ``row``
    is the 1-based line in a file (header = line 1), ``column`` the column or field
    name. The library names a bad *argument* of its own functions with ``argument``
    (``"model"``, ``"test_pose"``) and never a command-line flag; a message that tells
    what to give names the arguments as :class:`Arg` parts (``("use ", Arg("torque",
    "force"))``). The CLI says both as its flags (:meth:`on_command_line`: ``--model``,
    ``use --torque force``); ``str()`` says them in the library's words.
    """

    def __init__(self, message: Message, *, source: str | None = None,
                 row: int | None = None, column: str | None = None, argument: str | None = None) -> None:
        self.source = source
        self.row = row
        self.column = column
        self.argument = argument
        self.parts: tuple[str | Arg, ...] = (message,) if isinstance(message, str) else tuple(message)
        self.detail = say(self.parts)
        super().__init__(self._where(self.source, self.argument, self.detail))

    def _where(self, source: str | None, argument: str | None, detail: str) -> str:
        where = []
        if source:
            where.append(str(source))
        elif argument:
            where.append(argument)
        if self.row is not None:
            where.append(f"line {self.row}")
        if self.column:
            where.append(f"column {self.column}")
        prefix = ", ".join(where)
        return f"{prefix}: {detail}" if prefix else detail

    def with_source(self, source: str) -> "InputError":
        """The same error naming ``source`` (e.g. the CLI flag of the library's argument)."""
        return InputError(self.parts, source=source, row=self.row, column=self.column)

    def on_command_line(self, flags: "Mapping[str, str] | None" = None) -> "InputError":
        """The error as a command line says it: a library argument becomes its flag
        (``flags[argument]``, else ``--`` and the argument with dashes), in the message too."""
        source = self.source
        if source is None and self.argument:
            source = flag_of(self.argument, flags)
        if source == self.source and all(isinstance(p, str) for p in self.parts):
            return self
        return InputError(say(self.parts, flags, command_line=True), source=source, row=self.row,
                          column=self.column)


def check_known_keys(table, known, *, source: str | None, where: str, what: str = "") -> None:
    """Refuse keys of the TOML ``table`` that are not in ``known`` (a typo would
    silently become a default): one line naming the first unknown key
    (``where.key``), the closest known key and the known keys."""
    import difflib

    known = list(known)
    unknown = [str(k) for k in table if k not in known]
    if not unknown:
        return
    close = difflib.get_close_matches(unknown[0], known, n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    keys = "key" if len(unknown) == 1 else "keys"
    raise InputError(f"unknown {keys} {', '.join(unknown)}{hint}{what}; known keys: {', '.join(known)}",
                     source=source, column=f"{where}.{unknown[0]}" if where else unknown[0])


class EffectRefused(InputError):
    """An effect the model names that these data cannot show: ``effect`` and the
    ``reason`` its module gives (identification refuses it; diagnosis lists it as
    not testable). The message is ``"<effect>: <reason>"`` unless ``message`` is given."""

    def __init__(self, effect: str, reason: str, *, message: Message | None = None,
                 source: str | None = None, argument: str | None = None) -> None:
        self.effect = effect
        self.reason = reason
        super().__init__(message if message is not None else f"{effect}: {reason}", source=source,
                         argument=argument)


class UnidentifiableError(InputError):
    """The data cannot determine the requested parameters (too few measurements for
    the model, parameters the data cannot separate): a refusal the data decide, so
    bad input like any other (the CLI exits 2 with its one line); ``source`` names
    the data when the library knows them."""


class DeviceError(ElastocalError):
    """A device misbehaved (base of the device errors)."""


class DeviceTimeout(DeviceError, TimeoutError):
    """A device did not answer in time."""


class DeviceFault(DeviceError):
    """A device reports a fault state (drive fault, beam broken, ...)."""


class BeamBroken(DeviceFault):
    """The tracker could not measure: its beam is interrupted or finds no target (a person or a
    cable in the line of sight, usually for seconds)."""


class NotAtRest(DeviceFault):
    """The robot did not come to a standstill (controller idle, joints still) before a prompt:
    nothing was asked, the procedure stopped."""


class ProtocolError(DeviceError):
    """A device sent bytes that do not follow its protocol."""


class DeviceDisconnected(DeviceError, ConnectionError):
    """The connection to a device was lost."""
