"""Typed errors shared by every part of elastocal.

The CLI maps :class:`InputError` (a bad file, table, flag or config value, and
every refusal the data decide: :class:`EffectRefused`, :class:`UnidentifiableError`)
to exit code 2 and :class:`DeviceError` (and its subclasses) to exit code 1,
printing ``str(error)`` as one line.
"""

from __future__ import annotations


class ElastocalError(Exception):
    """Base of every expected error: its message is one line for the user."""


class InputError(ElastocalError, ValueError):
    """A file, table, flag or config value is wrong.

    ``source`` names the input (a path, or a flag when the CLI raises it), ``row``
    is the 1-based line in a file (header = line 1), ``column`` the column or field
    name. The library names a bad *argument* of its own functions with ``argument``
    (``"model"``, ``"test_pose"``) and never a command-line flag; the CLI maps the
    argument onto its flag (:meth:`with_source`, ``--model``).
    """

    def __init__(self, message: str, *, source: str | None = None,
                 row: int | None = None, column: str | None = None, argument: str | None = None) -> None:
        self.source = source
        self.row = row
        self.column = column
        self.argument = argument
        self.detail = message
        where = []
        if source:
            where.append(str(source))
        elif argument:
            where.append(argument)
        if row is not None:
            where.append(f"line {row}")
        if column:
            where.append(f"column {column}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)

    def with_source(self, source: str) -> "InputError":
        """The same error naming ``source`` (e.g. the CLI flag of the library's argument)."""
        return InputError(self.detail, source=source, row=self.row, column=self.column)

    def on_command_line(self, flags: "dict[str, str] | None" = None) -> "InputError":
        """The error as a command line says it: a library argument becomes its flag
        (``flags[argument]``, else ``--`` and the argument with dashes)."""
        if self.source is not None or not self.argument:
            return self
        flag = (flags or {}).get(self.argument, "--" + self.argument.replace("_", "-"))
        return self.with_source(flag)


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

    def __init__(self, effect: str, reason: str, *, message: str | None = None,
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


class ProtocolError(DeviceError):
    """A device sent bytes that do not follow its protocol."""


class DeviceDisconnected(DeviceError, ConnectionError):
    """The connection to a device was lost."""
