"""Typed errors shared by every part of elastocal.

The CLI maps :class:`InputError` to exit code 2 and :class:`DeviceError` (and
its subclasses) to exit code 1, printing ``str(error)`` as one line.
"""

from __future__ import annotations


class ElastocalError(Exception):
    """Base of every expected error: its message is one line for the user."""


class InputError(ElastocalError, ValueError):
    """A file, table, flag or config value is wrong.

    ``source`` names the input (a path or flag), ``row`` is the 1-based line in
    a file (header = line 1), ``column`` the column or field name.
    """

    def __init__(self, message: str, *, source: str | None = None,
                 row: int | None = None, column: str | None = None) -> None:
        self.source = source
        self.row = row
        self.column = column
        self.detail = message
        where = []
        if source:
            where.append(str(source))
        if row is not None:
            where.append(f"line {row}")
        if column:
            where.append(f"column {column}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class UnidentifiableError(ElastocalError):
    """The data cannot determine the requested parameters."""


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
