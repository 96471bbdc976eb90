"""The layers of docs/architecture.md, checked on the imports of every module.

Nothing imports upward; within the middle layer identification and the drivers
never import the simulation (nor each other, except the bottom layer's modules
that happen to live in their folders). The check reads the source with ``ast``
(imports inside functions count as well), so it needs nothing installed, and it
is tested on a copy of the tree with a deliberate upward import.
"""

from __future__ import annotations

import ast
import functools
import pathlib
import shutil
import sys

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: layer of each package, bottom (0) to top (4), by folder; a module belongs to the longest prefix.
#: The bottom layer: the robot model and the effects (model/), the file formats (formats/), the
#: package's own root, its typed errors (elastocal.errors) and its progress line (elastocal.progress).
LAYER = {
    "elastocal": 0, "elastocal.errors": 0, "elastocal.progress": 0, "elastocal.model": 0, "elastocal.formats": 0,
    "elastocal.drivers": 1, "elastocal.identify": 1, "elastocal.sims": 1,
    "elastocal.diagnose": 2, "elastocal.design": 2, "elastocal.acquisition": 2, "elastocal.compensation": 2,
    "elastocal.report": 2,
    "elastocal.fleet": 3, "elastocal.stream": 3,
    "elastocal.cli": 4, "elastocal.commands": 4, "elastocal.__main__": 4,
}
#: imports forbidden although the layers allow them: (importer, imported) packages
FORBIDDEN = {
    ("elastocal.identify", "elastocal.sims"), ("elastocal.drivers", "elastocal.sims"),
    ("elastocal.identify", "elastocal.drivers"), ("elastocal.drivers", "elastocal.identify"),
    ("elastocal.compensation", "elastocal.sims"), ("elastocal.compensation", "elastocal.acquisition"),
    ("elastocal.acquisition", "elastocal.compensation"),
    ("elastocal.diagnose", "elastocal.sims"), ("elastocal.design", "elastocal.sims"),
    ("elastocal.report", "elastocal.sims"), ("elastocal.compensation", "elastocal.report"),
    ("elastocal.acquisition", "elastocal.sims"),
    # the simulator is an independent witness: it computes the physics its own way, never with
    # the fits' code (docs/physics.md); only the bottom layer's description and formats
    ("elastocal.sims", "elastocal.identify"), ("elastocal.sims", "elastocal.diagnose"),
    ("elastocal.sims", "elastocal.design"),
}


def modules(root: pathlib.Path) -> dict[str, pathlib.Path]:
    """Module name -> file, from the package folders of pyproject.toml."""
    config = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    folders = {pkg: root / pkg.replace(".", "/") for pkg in config["packages"]}
    folders.update({pkg: root / folder for pkg, folder in config.get("package-dir", {}).items()})
    out = {}
    for pkg, folder in folders.items():
        for path in sorted(folder.glob("*.py")):
            name = pkg if path.stem == "__init__" else f"{pkg}.{path.stem}"
            out[name] = path
    return out


@functools.lru_cache(maxsize=None)
def _parsed(text: str) -> ast.Module:
    """A module's syntax tree, parsed once per text (the copies of the tree share them; the
    walk below only reads it)."""
    return ast.parse(text)


def imports(name: str, path: pathlib.Path, known: dict[str, pathlib.Path]) -> set[tuple[int, str]]:
    """(line, imported elastocal module) of every import statement in the file.
    ``from elastocal.design import search`` imports the module ``elastocal.design.search``;
    ``from elastocal.design.search import plan_experiment`` the module ``elastocal.design.search``."""
    tree = _parsed(path.read_text(encoding="utf-8"))
    package = name if path.stem == "__init__" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {(node.lineno, a.name) for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for a in node.names:
                sub = f"{target}.{a.name}"
                found.add((node.lineno, sub if sub in known else target))
    return {(line, t) for line, t in found if t == "elastocal" or t.startswith("elastocal.")}


def placement(name: str, known: dict[str, pathlib.Path]) -> tuple[int, str] | None:
    """(layer, package) of a module, or None for a name that is no module (an imported object)."""
    if name not in known:
        return None
    for prefix, layer in sorted(LAYER.items(), key=lambda kv: -len(kv[0])):
        if name == prefix or (prefix != "elastocal" and name.startswith(prefix + ".")):
            return layer, prefix
    raise LookupError(name)


def violations(root: pathlib.Path) -> list[str]:
    known = modules(root)
    problems = []
    for name, path in known.items():
        try:
            here = placement(name, known)
        except LookupError:
            problems.append(f"{path.relative_to(root)}: module {name} has no layer; add it to tests/test_layers.py")
            continue
        for line, target in sorted(imports(name, path, known)):
            there = placement(target, known)
            if there is None or there[1] == here[1]:
                continue
            where = f"{path.relative_to(root)}:{line}: {name} imports {target}"
            if there[0] > here[0]:
                problems.append(f"{where} (upward: layer {here[0]} imports layer {there[0]})")
            elif (here[1], there[1]) in FORBIDDEN:
                problems.append(f"{where} ({here[1]} never imports {there[1]})")
    return problems


def test_nothing_imports_upward():
    problems = violations(ROOT)
    assert not problems, "\n".join(problems)


def test_the_simulator_uses_no_fitting_or_effect_code():
    """sims/ reads the robot description and writes the file formats; its physics is its own
    (sims/physics.py): no identify/, diagnose/ or design/ module, no effect module."""
    known = modules(ROOT)
    bad = [f"{name} imports {target}" for name, path in known.items() if name.startswith("elastocal.sims")
           for _, target in imports(name, path, known)
           if target.startswith(("elastocal.identify", "elastocal.diagnose", "elastocal.design",
                                 "elastocal.model.effects"))]
    assert not bad, bad


def test_every_module_has_a_layer():
    known = modules(ROOT)
    assert len(known) > 80 and "elastocal.identify.static" in known and "elastocal.commands.plan" in known
    bottom = [n for n in known if placement(n, known)[0] == 0]
    assert "elastocal.model.robot" in bottom and "elastocal.formats.tables" in bottom, bottom


@pytest.fixture
def tree(tmp_path) -> pathlib.Path:
    """A copy of the sources (pyproject.toml and the package folders)."""
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    for path in modules(ROOT).values():
        target = tmp_path / path.relative_to(ROOT)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    return tmp_path


@pytest.mark.parametrize("file,line,message", [
    ("design/search.py", "from elastocal.sims.cell import SimCell", "never imports"),
    ("drivers/config.py", "    from elastocal.identify.static import identify_static", "never imports"),
    ("model/robot.py", "from elastocal.identify import static", "upward: layer 0 imports layer 1"),
    ("compensation/model.py", "from elastocal.commands import plan", "upward: layer 2 imports layer 4"),
    ("sims/world.py", "from elastocal.acquisition.procedures import run_calibration", "upward"),
    ("compensation/model.py", "from ..sims import cell", "never imports"),
])
def test_a_deliberate_bad_import_fails_the_check(tree, file, line, message):
    path = tree / file
    text = path.read_text(encoding="utf-8")
    if line.startswith(" "):   # an import inside a function counts too
        text += f"\n\ndef _sneaky():\n{line}\n"
    else:
        text += f"\n{line}\n"
    before = set(violations(tree))      # (test_nothing_imports_upward judges these)
    path.write_text(text, encoding="utf-8")
    problems = [p for p in violations(tree) if p not in before]
    assert len(problems) == 1 and problems[0].startswith(file) and message in problems[0], problems


def test_a_module_without_a_layer_is_named(tree):
    before = set(violations(tree))
    (tree / "elastocal" / "newthing.py").write_text('"""x"""\n', encoding="utf-8")
    assert [p for p in violations(tree) if p not in before] == ["elastocal/newthing.py: module elastocal.newthing has no layer; "
                                "add it to tests/test_layers.py"]


#: a module longer than this says at its top why it is one module
LONG_MODULE_LINES = 520


def test_long_modules_say_why():
    long = []
    for name, path in modules(ROOT).items():
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > LONG_MODULE_LINES:
            doc = ast.get_docstring(ast.parse(text)) or ""
            if "Why one module over 500 lines" not in doc:
                long.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
    assert not long, "split these or write at their top why they are one module: " + "; ".join(long)


#: a function longer than this says why, in a ``# long:`` comment on its def line or just above
LONG_FUNCTION_LINES = 80


def long_functions(root: pathlib.Path) -> list[str]:
    """``file:function`` of every function over LONG_FUNCTION_LINES lines without a ``# long:``
    reason (on its def line or the line above it or above its decorators), in the packages and
    the benchmarks."""
    paths = [*modules(root).values(), *sorted((root / "benchmarks").glob("*.py"))]
    out = []
    for path in paths:
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for node in ast.walk(_parsed(text)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if node.end_lineno - node.lineno + 1 <= LONG_FUNCTION_LINES:
                continue
            first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            said = lines[max(first - 2, 0):node.lineno]      # the line above, decorators, the def line
            if not any("# long:" in line for line in said):
                out.append(f"{path.relative_to(root).as_posix()}:{node.name}")
    return sorted(out)


def test_long_functions_say_why():
    found = long_functions(ROOT)
    assert not found, ("split these or write why they are one function (a '# long:' comment on the def line "
                       "or just above): " + "; ".join(found))


def test_a_long_function_without_a_reason_is_named(tree):
    body = "".join(f"    x{i} = {i}\n" for i in range(LONG_FUNCTION_LINES))
    path = tree / "model" / "units.py"
    path.write_text(path.read_text(encoding="utf-8") + f"\n\ndef sprawling():\n{body}", encoding="utf-8")
    assert "model/units.py:sprawling" in long_functions(tree)
    path.write_text(path.read_text(encoding="utf-8").replace("def sprawling():", "def sprawling():  # long: a test"),
                    encoding="utf-8")
    assert "model/units.py:sprawling" not in long_functions(tree)


# ------------------------------------------------------------------ effects closed for modification
#: the package whose modules are the effects (one module per effect, beside base.py)
EFFECTS_PACKAGE = "elastocal.model.effects"


def effect_names(root: pathlib.Path) -> frozenset[str]:
    """The effects' names: the modules of model/effects/ other than base.py and the private ones
    (__init__.py, _friction.py: the friction laws' factory)."""
    return frozenset(p.stem for p in (root / "model" / "effects").glob("*.py")
                     if p.stem != "base" and not p.stem.startswith("_"))


def _named_effects(node: ast.AST, names: frozenset[str], collections: dict[str, set[str]]) -> set[str]:
    """The effect names an operand of a comparison spells: a string literal, a tuple, list, set or
    dict literal of them (``x in ("backlash", ...)``), or a module-level constant bound to one."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return {node.value} & names
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return set().union(*(_named_effects(e, names, collections) for e in node.elts))
    if isinstance(node, ast.Dict):
        return set().union(*(_named_effects(k, names, collections) for k in node.keys if k is not None))
    if isinstance(node, ast.Starred):
        return _named_effects(node.value, names, collections)
    if isinstance(node, ast.Name):
        return collections.get(node.id, set())
    return set()


def name_branches(text: str, names: frozenset[str]) -> list[tuple[int, str]]:
    """(line, effect) of every comparison or membership test in a module's source that names an
    effect: generic code asks an effect what it can do, it never branches on which one it is."""
    tree = _parsed(text)
    collections: dict[str, set[str]] = {}
    for stmt in tree.body:           # module-level constants that list effects (NO_DRIFT = ("backlash",))
        if isinstance(stmt, (ast.Assign, ast.AnnAssign)) and stmt.value is not None \
                and isinstance(stmt.value, (ast.Tuple, ast.List, ast.Set, ast.Dict)):
            listed = _named_effects(stmt.value, names, {})
            targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target]
            for target in targets:
                if listed and isinstance(target, ast.Name):
                    collections[target.id] = listed
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            for operand in (node.left, *node.comparators):
                found += [(node.lineno, name) for name in sorted(_named_effects(operand, names, collections))]
    return found


#: packages the check does not read, because naming an effect there is no branch of generic code:
#: - the effects themselves (an effect's module names itself);
#: - the simulator. It is the world the fits are tested against, not code that serves any model: it
#:   switches on a physical phenomenon of the cell by the word a user gives ``--hidden`` ("backlash",
#:   "friction", "base_tilt", "none": the vocabulary of the world, which coincides with some
#:   effects' names so that a test can say "hide X, find X"). It may not ask the effects (it imports
#:   none of them: test_the_simulator_uses_no_fitting_or_effect_code), so hooks on the effects would
#:   make the witness compute with the fit's code; and a new effect that the simulator cannot show
#:   is one it never names, so it needs no change there. Only sims/ is exempt: the commands, the
#:   fleet and acquisition, which drive it, are checked like all generic code.
NOT_GENERIC = (EFFECTS_PACKAGE, "elastocal.sims")


def effect_name_branches(root: pathlib.Path) -> list[str]:
    names = effect_names(root)
    return [f"{path.relative_to(root)}:{line}: branches on the effect {effect!r}"
            for module, path in modules(root).items()
            if not any(module == p or module.startswith(p + ".") for p in NOT_GENERIC)
            for line, effect in name_branches(path.read_text(encoding="utf-8"), names)]


def test_no_generic_code_branches_on_an_effect_name():
    """An effect's behaviour lives in its module (model/effects/), declared as what it can do;
    generic code asks for that, never compares names."""
    problems = effect_name_branches(ROOT)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("source,expected", [
    ('if eff.name == "backlash":\n    pass\n', [(1, "backlash")]),
    ('ok = "joint_stiffness" in model\n', [(1, "joint_stiffness")]),
    ('x = [m for m in model if m not in ("link_compliance", "gravity")]\n', [(1, "gravity"), (1, "link_compliance")]),
    ('SESSION = ("thermal_drift",)\n\n\ndef f(m):\n    return m in SESSION\n', [(5, "thermal_drift")]),
    ('NOTES = {"tracker_frame": "x"}\nif name in NOTES:\n    pass\n', [(2, "tracker_frame")]),
    # naming an effect to fetch it, or a word that is no effect, is no branch
    ('eff = get_effect("backlash")\nif mode == "identify":\n    pass\n', []),
])
def test_the_name_branch_check_catches_a_deliberate_branch(source, expected):
    assert name_branches(source, effect_names(ROOT)) == expected


#: one module of every package the name-branch check reads (every package but NOT_GENERIC's)
GENERIC_MODULES = ("identify/static.py", "diagnose/static.py", "design/search.py", "compensation/model.py",
                   "report/html.py", "acquisition/procedures.py", "drivers/config.py", "fleet/tasks.py",
                   "stream/loop.py", "formats/calibration.py", "model/robot.py", "elastocal/commands/identify.py",
                   "elastocal/cli.py")


def test_every_package_but_the_effects_and_the_simulator_is_checked():
    packages = {placement(name, modules(ROOT))[1] for name in modules(ROOT)}
    checked = {placement(module_name(f), modules(ROOT))[1] for f in GENERIC_MODULES}
    exempt = {p for p in packages if any(p == q or p.startswith(q + ".") for q in NOT_GENERIC)}
    assert packages - exempt - {"elastocal", "elastocal.errors", "elastocal.progress", "elastocal.__main__"} <= checked


def module_name(file: str) -> str:
    """The module of a file of the package folders (``identify/static.py`` -> ``elastocal.identify.static``)."""
    return next(name for name, path in modules(ROOT).items() if path == ROOT / file)


@pytest.mark.parametrize("file", GENERIC_MODULES)
def test_a_name_branch_added_to_generic_code_fails_the_check(tree, file):
    before = set(effect_name_branches(tree))
    path = tree / file
    path.write_text(path.read_text(encoding="utf-8") + '\n\ndef _sneaky(eff):\n    return eff.name == "backlash"\n',
                    encoding="utf-8")
    added = [p for p in effect_name_branches(tree) if p not in before]
    assert len(added) == 1 and added[0].startswith(f"{file}:") and "'backlash'" in added[0], added
    # an effect module may name itself
    effect = tree / "model" / "effects" / "backlash.py"
    effect.write_text(effect.read_text(encoding="utf-8") + '\nassert EFFECT.name == "backlash"\n', encoding="utf-8")
    assert [p for p in effect_name_branches(tree) if p not in before] == added
    # the simulator names the world's phenomena, not the fit's effects (NOT_GENERIC)
    world = tree / "sims" / "cell.py"
    world.write_text(world.read_text(encoding="utf-8") + '\nassert "backlash" in HIDDEN_EFFECTS\n', encoding="utf-8")
    assert [p for p in effect_name_branches(tree) if p not in before] == added
