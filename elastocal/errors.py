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
