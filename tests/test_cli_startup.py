"""`elastocal --help` and `--version` import none of the heavy libraries (correctness, not
timing: benchmarks/bench_cli.py prints the time); a command's own --help still imports its module."""

import subprocess
import sys

import pytest

HEAVY = ("pinocchio", "scipy", "matplotlib", "canopen", "pymodbus", "mcap", "dask", "viser")

PROBE = """
import contextlib, io, sys
from elastocal.cli import main
with contextlib.redirect_stdout(io.StringIO()) as out:
    try:
        main({argv!r})
    except SystemExit as exc:
        code = exc.code
heavy = {heavy!r}
loaded = sorted(m for m in sys.modules if m.split('.')[0] in heavy)
print(code, out.getvalue().count('\\n'), ','.join(loaded))
"""


def probe(argv):
    done = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)],
                          capture_output=True, text=True, timeout=300, check=True)
    code, lines, loaded = (done.stdout.strip().split(" ") + [""])[:3]
    return int(code), int(lines), [m for m in loaded.split(",") if m]


@pytest.mark.parametrize("argv", [["--help"], ["--version"]])
def test_top_level_help_and_version_import_no_heavy_library(argv):
    code, lines, loaded = probe(argv)
    assert code == 0 and lines >= 1
    assert loaded == [], f"elastocal {argv[0]} imported {loaded}"


def test_the_probe_sees_a_command_that_imports_them():
    # the same probe on a command's own --help loads what that command needs: the check above can fail
    code, lines, loaded = probe(["identify", "--help"])
    assert code == 0 and lines > 5
    assert any(m.split(".")[0] in ("pinocchio", "scipy") for m in loaded), loaded


def test_every_command_is_listed_in_the_top_level_help(capsys):
    from elastocal.cli import COMMANDS, main

    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for name in COMMANDS:
        assert f"    {name} " in text or f"    {name}\n" in text, name
