"""House rules read from the source: the packages are pyflakes-clean (no unused imports or
variables, no undefined names; an unused import is a layer edge nobody needs), and the
library's messages name its arguments, never the command line's flags."""

from __future__ import annotations

import ast
import pathlib
import re

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


# ------------------------------------------------------------------ no CLI flags in the library
#: the library's packages (the CLI, elastocal.cli and elastocal.commands, names its own flags)
LIBRARY = ("drivers", "acquisition", "identify", "compensation", "sims", "fleet", "elastocal/errors.py",
           "model/units.py", "formats/textfiles.py", "elastocal/robots")
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z-]*")
#: texts that name a flag and are not messages of the library: (file, flag) -> why
NOT_MESSAGES = {
    ("acquisition/history.py", "--json"): "an SQL comment of the schema",
    ("formats/logformat.py", "--yes"): "the log schema's description of a recorded field",
}


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def flags_in_messages(root: pathlib.Path) -> list[str]:
    """``file:line: --flag`` for every text of the library (not a docstring) naming a command-line flag."""
    found = []
    for entry in LIBRARY:
        path = root / entry
        for f in sorted(path.rglob("*.py")) if path.is_dir() else [path] if path.exists() else []:
            tree = ast.parse(f.read_text(encoding="utf-8"))
            docs = _docstrings(tree)
            rel = f.relative_to(root).as_posix()
            for node in ast.walk(tree):
                if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
                    for flag in FLAG.findall(node.value):
                        if (rel, flag) not in NOT_MESSAGES:
                            found.append(f"{rel}:{node.lineno}: {flag}")
    return found


def test_library_messages_name_arguments_not_flags():
    """Errors, refusals and result texts of the library name its arguments (``Arg``); the CLI says
    them as its flags."""
    assert (ROOT / "identify" / "static.py").exists() and (ROOT / "elastocal" / "errors.py").exists()
    assert flags_in_messages(ROOT) == []


def test_the_flag_check_sees_a_flag(tmp_path):
    (tmp_path / "identify").mkdir()
    (tmp_path / "identify" / "x.py").write_text('"""Docs may say --model."""\nraise ValueError("use --torque force")\n')
    assert flags_in_messages(tmp_path) == ["identify/x.py:2: --torque"]


def test_an_argument_is_said_as_a_flag_on_the_command_line():
    from elastocal.errors import Arg, InputError

    exc = InputError(("choose another ", Arg("out"), ", or ", Arg("force", True), " to overwrite it; or use ",
                      Arg("torque", "force")), source="cal.json")
    assert str(exc) == "cal.json: choose another out, or force=True to overwrite it; or use torque='force'"
    assert str(exc.on_command_line()) == ("cal.json: choose another --out, or --force to overwrite it; or use "
                                          "--torque force")
    bad = InputError("must be at least 1, got 0", argument="workers")
    assert str(bad) == "workers: must be at least 1, got 0"
    assert str(bad.on_command_line({"workers": "-j"})) == "-j: must be at least 1, got 0"
    assert str(bad.on_command_line()) == "--workers: must be at least 1, got 0"


def _library_arguments(root: pathlib.Path) -> dict[str, str]:
    """Every argument name the library's errors name (``argument="x"``, ``Arg("x")``) -> where."""
    names: dict[str, str] = {}
    for entry in LIBRARY:
        path = root / entry
        for f in sorted(path.rglob("*.py")) if path.is_dir() else [path] if path.exists() else []:
            for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
                if not isinstance(node, ast.Call):
                    continue
                for kw in node.keywords:
                    if kw.arg == "argument" and isinstance(kw.value, ast.Constant) and isinstance(kw.value.value, str):
                        names.setdefault(kw.value.value, f"{f.relative_to(root)}:{node.lineno}")
                if (isinstance(node.func, ast.Name) and node.func.id == "Arg" and node.args
                        and isinstance(node.args[0], ast.Constant)):
                    names.setdefault(node.args[0].value, f"{f.relative_to(root)}:{node.lineno}")
    return names


def test_every_argument_the_library_names_is_a_flag_of_the_command_line():
    """The CLI says a library argument as ``--`` and its name with dashes (``InputError.on_command_line``):
    every argument an error of the library names must be such a flag of some command."""
    import argparse

    from elastocal.cli import COMMANDS, build_parser

    def options(parser) -> set[str]:
        out = set()
        for action in parser._actions:
            out.update(s for s in action.option_strings if s.startswith("--"))
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    out |= options(sub)
        return out

    flags: set[str] = set()
    for name in COMMANDS:
        flags |= options(build_parser(name)[0])
    names = _library_arguments(ROOT)
    assert {"model", "torque", "out", "workers", "calibration"} <= set(names)
    missing = {n: where for n, where in names.items() if "--" + n.replace("_", "-") not in flags}
    assert not missing, missing
