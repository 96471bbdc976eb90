"""Output files of the commands: checked before any work, written all or nothing.

Every command that writes files checks all of them first (:class:`Outputs`):
the parent folder exists, the target is not a folder, it is none of the
command's inputs (refused even with ``--force``) and, unless ``--force``, it
does not exist yet. Only a regular file is ever replaced: a symbolic link, a
device, a FIFO or a socket at an output's path is refused, ``--force`` or not
(one rule for every command: elastocal never writes through a link; name the
file itself). The files are then written to temporary siblings and moved
into place together (:meth:`Outputs.commit`, :func:`atomic`), so a refused or failed command
leaves every existing file as it was and writes nothing half-way.

The one exception is a procedure's log (``calibrate``, ``check``): it is written
where ``--out`` says while the procedure runs, so that a killed run leaves it there
for ``--resume`` and ``elastocal repair``; it is created new (an existing regular
file removed first with ``--force``), never through a link
(:class:`elastocal.acquisition.recorder.Recorder`).
"""

from __future__ import annotations

import contextlib
import os
import pathlib
from collections.abc import Iterable

from elastocal.errors import InputError

#: the one wording of "the output exists" (acquisition/procedures.py uses the same)
EXISTS = "already exists; choose another {flag}, or --force to overwrite it"


def _same(a: pathlib.Path, b: pathlib.Path) -> bool:
    with contextlib.suppress(OSError):        # unreadable: fall back to comparing the resolved paths
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    return a.resolve() == b.resolve()


def check_replaceable(out: pathlib.Path, flag: str) -> None:
    """Refuse an output path that holds anything but a regular file (a link, a device, a FIFO)."""
    if out.is_symlink():
        raise InputError(f"is a symbolic link; elastocal does not write through links: give {flag} the file "
                         "itself", source=str(out))
    if out.exists() and not out.is_dir() and not out.is_file():
        raise InputError(f"is not a regular file (a device, a FIFO or a socket); {flag} names a file to write",
                         source=str(out))


def check_folder(path: str | os.PathLike, flag: str) -> pathlib.Path:
    """An output folder: a folder, or a path that can become one."""
    if not str(path):
        raise InputError(f"{flag} is empty; name the folder to write into", source=flag)
    out = pathlib.Path(path)
    if out.is_symlink():
        raise InputError(f"is a symbolic link; elastocal does not write through links: give {flag} the folder "
                         "itself", source=str(out))
    if out.exists() and not out.is_dir():
        raise InputError(f"is not a folder; {flag} names the folder to write into", source=str(out))
    parent = out
    while not parent.exists():
        if parent.parent == parent:
            break
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(f"cannot create the folder: {parent} is not a folder", source=str(out))
    if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write into {parent}: permission denied", source=str(out))
    return out


def _temp_name(out: pathlib.Path) -> pathlib.Path:
    """Where ``out`` is written until the command commits its outputs (same folder, same suffix)."""
    return out.with_name(f".{out.stem}.elastocal-{os.getpid()}-partial{out.suffix}")


class Outputs:
    """The files a command writes; see the module doc."""

    def __init__(self, *, force: bool, inputs: Iterable[tuple[str | os.PathLike | None, str]] = ()) -> None:
        self.force = force
        self.inputs = [(pathlib.Path(p), flag) for p, flag in inputs if p]
        self.files: list[tuple[pathlib.Path, str]] = []
        self.remove: list[pathlib.Path] = []
        self._temps: dict[pathlib.Path, pathlib.Path] = {}
        self._made_folder: pathlib.Path | None = None

    def add(self, path: str | os.PathLike, flag: str = "--out", *, in_folder: bool = False) -> pathlib.Path:
        """Check one output file (``in_folder``: its folder may not exist yet)."""
        if not str(path):
            raise InputError(f"{flag} is empty; name the file to write", source=flag)
        out = pathlib.Path(path)
        check_replaceable(out, flag)
        if out.is_dir():
            raise InputError(f"is a folder; {flag} names a file to write", source=str(out))
        parent = out.parent
        if not in_folder:
            if not parent.exists():
                raise InputError(f"cannot write: no such folder {str(parent)!r}", source=str(out))
            if not parent.is_dir():
                raise InputError(f"cannot write: {str(parent)!r} is not a folder", source=str(out))
        for other, other_flag in self.inputs:
            if _same(out, other):
                raise InputError(f"is also an input ({other_flag}); {flag} must name another file", source=str(out))
        for other, other_flag in self.files:
            if _same(out, other):
                raise InputError(f"is given twice as an output ({other_flag} and {flag})", source=str(out))
        if out.exists() and not self.force:
            raise InputError(EXISTS.format(flag=flag), source=str(out))
        self.files.append((out, flag))
        return out

    def stale(self, path: str | os.PathLike, flag: str, why: str) -> None:
        """A file this command does not write but that would mislead beside its
        outputs: refused without --force, removed on commit with it."""
        p = pathlib.Path(path)
        if p.exists() or p.is_symlink():
            check_replaceable(p, flag)
            if p.is_dir():
                raise InputError(f"is a folder in the way ({why})", source=str(p))
            if not self.force:
                raise InputError(f"{why}; choose another {flag}, or --force to remove it", source=str(p))
            self.remove.append(p)

    def make_folder(self, folder: str | os.PathLike) -> None:
        folder = pathlib.Path(folder)
        if folder.is_dir():
            return
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"cannot create: {exc.strerror}", source=str(folder)) from None
        self._made_folder = folder

    def temp(self, path: str | os.PathLike) -> pathlib.Path:
        """Where to write ``path`` until :meth:`commit` (same folder, same suffix)."""
        out = pathlib.Path(path)
        tmp = self._temps[out] = _temp_name(out)
        return tmp

    def commit(self) -> None:
        """Move every written temporary file into place; remove stale files."""
        for out, tmp in self._temps.items():
            try:
                os.replace(tmp, out)
            except OSError as exc:
                self.abort()
                raise InputError(f"cannot write: {exc.strerror}", source=str(out)) from None
        self._temps.clear()
        for p in self.remove:
            try:
                p.unlink(missing_ok=True)
            except OSError as exc:
                raise InputError(f"cannot remove: {exc.strerror}", source=str(p)) from None

    def abort(self) -> None:
        """Remove the temporary files (and the folder made for them, if empty)."""
        # best effort: the command is failing already, and its own error is the one to report
        for tmp in self._temps.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self._temps.clear()
        if self._made_folder is not None:
            with contextlib.suppress(OSError):     # not empty: something else was put there
                self._made_folder.rmdir()

    def __enter__(self) -> "Outputs":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.commit()
            return False
        self.abort()
        finals = {str(_temp_name(out)): str(out) for out, _ in self.files}
        if isinstance(exc, InputError) and exc.source in finals:
            # a writer's error about the temporary file: name the file the user gave
            raise InputError(exc.parts, source=finals[exc.source], row=exc.row, column=exc.column) from None
        if isinstance(exc, OSError):
            name = finals.get(str(exc.filename), exc.filename)
            raise InputError(f"cannot write: {exc.strerror or exc}", source=str(name or self.files[0][0])) from None
        return False



@contextlib.contextmanager
def atomic(path: str | os.PathLike, flag: str = "--out"):
    """Write ``path`` all or nothing: yields a temporary sibling to write, moved into place when
    the block ends (removed when it fails). Refuses what :func:`check_replaceable` refuses."""
    out = pathlib.Path(path)
    check_replaceable(out, flag)
    tmp = _temp_name(out)
    try:
        yield tmp
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | os.PathLike, text: str, flag: str = "--out") -> None:
    """``path.write_text(text)``, all or nothing (:func:`atomic`)."""
    with atomic(path, flag) as tmp:
        tmp.write_text(text, encoding="utf-8")


def note(args, text: str) -> None:
    """Queue a one-line note for stderr on the command's ``args.notes`` (cli.main
    prints them after the command's output, unless the command fails)."""
    notes = args.__dict__.setdefault("notes", [])
    if text not in notes:
        notes.append(text)


def log_note(command_path: str, contents) -> str | None:
    """The one-line note for a log that ends without its MCAP summary, or with bytes after
    its end (or None)."""
    extra = getattr(contents, "trailing_bytes", 0)
    if extra:
        return (f"note: {command_path} has {extra} bytes after the end of its MCAP data (a second copy or "
                f"garbage appended to the file?); they were ignored")
    if getattr(contents, "complete", True):
        return None
    return (f"note: {command_path} ends without its MCAP summary (the recorder was killed or is still "
            f"writing); everything up to its last complete chunk was read")
