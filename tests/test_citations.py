"""The project stands alone: every document a package file (code, --help texts, package
data) or a document of the repository cites is in the repository.

A citation is any ``name.md`` written in a file. In package files it must be a path
from the repository root (``docs/formats.md``); in the README and in docs/ it may be
relative to the citing file. Nothing may point outside the repository (``../shared``,
``../spec``, the papers' text files): the papers are cited by author and equation in
docs/physics.md.
"""

from __future__ import annotations

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("elastocal", "drivers", "acquisition", "identify", "compensation", "sims")
CITATION = re.compile(r"(?<![\w/.-])((?:\.{1,2}/)*(?:[\w-]+/)*[\w.-]+\.md)\b")
OUTSIDE = re.compile(r"\.\./(?:shared|spec|seeds)\b|/work/shared|seeds/\d+_[0-9a-f]+\.txt")
TEXT_SUFFIXES = {".py", ".toml", ".md", ".txt", ".urdf", ".json", ".csv", ".eds", ".cfg", ".ini"}


def package_files(root: pathlib.Path) -> list[pathlib.Path]:
    return sorted(p for pkg in PACKAGES for p in (root / pkg).rglob("*")
                  if p.is_file() and p.suffix in TEXT_SUFFIXES and "__pycache__" not in p.parts)


def document_files(root: pathlib.Path) -> list[pathlib.Path]:
    return sorted([root / "README.md", *(root / "docs").glob("*.md")])


def problems(root: pathlib.Path) -> list[str]:
    out = []
    for path, relative_ok in [*((p, False) for p in package_files(root)), *((p, True) for p in document_files(root))]:
        text = path.read_text(encoding="utf-8", errors="replace")
        for lineno, line in enumerate(text.splitlines(), start=1):
            where = f"{path.relative_to(root)}:{lineno}"
            if OUTSIDE.search(line):
                out.append(f"{where}: points outside the repository: {line.strip()[:80]}")
            for m in CITATION.finditer(line):
                cited = m.group(1)
                found = (root / cited).is_file() or (relative_ok and (path.parent / cited).is_file())
                if not found:
                    out.append(f"{where}: cites {cited}, which the repository does not hold"
                               + ("" if relative_ok or "/" in cited else f" (write docs/{cited}?)"))
    return out


def test_every_cited_document_is_in_the_repository():
    found = problems(ROOT)
    assert not found, "\n".join(found)


def test_the_contract_documents_are_here():
    for name in ("formats" + ".md", "cli" + ".md", "physics" + ".md", "architecture.md"):
        assert (ROOT / "docs" / name).is_file(), name
    physics = (ROOT / "docs" / ("physics" + ".md")).read_text(encoding="utf-8")
    # the paper equation codes are explained once
    assert "`Y39` is equation (39) of Yang et al., `K40` equation (40) of Klimchik et al." in physics
    cited = {m for p in package_files(ROOT) for m in CITATION.findall(p.read_text(encoding="utf-8", errors="replace"))}
    assert {"docs/formats.md", "docs/cli.md", "docs/physics.md"} <= cited


@pytest.mark.parametrize("line,message", [
    # (the bad citations are written in pieces so that no tool rewrites them)
    ("# see " + "formats.md §2", "cites " + "formats.md, which the repository does not hold (write docs/formats.md?)"),
    ('help="robot.toml (../' + 'spec/formats' + '.md §1)"', "points outside the repository"),
    ("# the paper: ../shared/seeds/000_c7816f4a9764a4d5.txt", "points outside the repository"),
    ("# docs/nonexistent.md", "cites docs/nonexistent.md"),
])
def test_a_citation_outside_the_repository_fails(tmp_path, line, message):
    for path in [*package_files(ROOT), *document_files(ROOT)]:
        target = tmp_path / path.relative_to(ROOT)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(path.read_bytes())
    before = set(problems(tmp_path))     # (test_every_cited_document_is_in_the_repository judges these)
    bad = tmp_path / "identify" / "static.py"
    bad.write_text(bad.read_text(encoding="utf-8") + f"\n{line}\n", encoding="utf-8")
    found = [f for f in problems(tmp_path) if f not in before]
    assert found and all(f.startswith("identify/static.py:") for f in found), found
    assert any(message in f for f in found), found
