"""Reading the user's text files (TOML, JSON, CSV, URDF) with one kind of error.

Every reader of a user file goes through :func:`read_text_file`: the file is
decoded as UTF-8, a leading byte-order mark is dropped (editors on Windows
write one), and an unreadable or non-UTF-8 file becomes one
:class:`~elastocal.errors.InputError` naming the file (and, for bytes that are
not UTF-8, the line of the first bad byte) instead of a traceback.
"""

from __future__ import annotations

import codecs
import pathlib

from elastocal.errors import InputError


def read_text_file(path: str | pathlib.Path, *, source: str | None = None,
                   column: str | None = None, what: str = "") -> str:
    """The text of ``path`` (UTF-8, optional BOM dropped, newlines as ``\\n``).

    ``source`` names the input in errors (default: the path). For a file named
    inside another one (the URDF of a robot.toml), ``source`` and ``column`` name
    the outer file and its key and ``what`` the inner file (``"URDF /x/r.urdf"``).
    """
    path = pathlib.Path(path)
    src = str(path) if source is None else source
    try:
        data = path.read_bytes()
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise InputError(f"cannot read {what}: {reason}" if what else f"cannot read: {reason}",
                         source=src, column=column) from None
    if data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8):]
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        bad = f"byte 0x{data[exc.start]:02x}"
        if what:        # the line is the inner file's
            raise InputError(f"{what} is not a UTF-8 text file ({bad} at line {line})", source=src,
                             column=column) from None
        raise InputError(f"not a UTF-8 text file ({bad} is not UTF-8)", source=src, row=line,
                         column=column) from None
    return text.replace("\r\n", "\n").replace("\r", "\n")     # universal newlines, as text mode reads
