"""The packages are pyflakes-clean: no unused imports or variables, no undefined names
(an unused import is a layer edge nobody needs; tests/test_layers.py counts it too)."""

from __future__ import annotations

import pathlib

from pyflakes.api import checkPath, check
from pyflakes.reporter import Reporter

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: the folders of the elastocal distribution (pyproject.toml's package-dir)
PACKAGES = ("elastocal", "drivers", "acquisition", "identify", "compensation", "sims", "fleet")


class _Collect(Reporter):
    def __init__(self) -> None:
        self.messages: list[str] = []

    def unexpectedError(self, filename, message) -> None:
        self.messages.append(f"{filename}: {message}")

    def syntaxError(self, filename, msg, lineno, offset, text) -> None:
        self.messages.append(f"{filename}:{lineno}: {msg}")

    def flake(self, message) -> None:
        self.messages.append(str(message))


def test_packages_are_pyflakes_clean():
    report = _Collect()
    files = sorted(f for pkg in PACKAGES for f in (ROOT / pkg).rglob("*.py"))
    assert len(files) > 100
    for f in files:
        checkPath(str(f), report)
    assert not report.messages, "\n".join(report.messages)


def test_the_check_sees_an_unused_import():
    report = _Collect()
    check("import json\n", "example.py", report)
    assert report.messages and "'json' imported but unused" in report.messages[0]
