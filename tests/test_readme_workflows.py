"""Every command of the README's "Try every command on simulated data" block runs, as
written, in an empty folder with only simulated data (the view is started and stopped)."""

import pathlib
import shlex

import pytest

from elastocal.cli import main

README = pathlib.Path(__file__).parents[1] / "README.md"


def readme_block() -> list[list[str]]:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Try every command on simulated data"):]
    body = section[section.index("```bash") + len("```bash"):]
    body = body[:body.index("```")]
    commands = []
    for line in body.strip().splitlines():
        argv = shlex.split(line, comments=True)
        assert argv[0] == "elastocal", line
        commands.append(argv[1:])
    return commands


def test_the_block_covers_the_offline_workflows():
    names = {argv[0] for argv in readme_block()}
    assert names >= {"sim", "identify", "diagnose", "report", "export", "history", "geometry", "plan",
                     "validate", "robot", "view"}


@pytest.mark.slow
def test_every_readme_workflow_runs_from_simulated_data(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for argv in readme_block():
        if argv[0] == "view":     # serves until Ctrl-C: build its page on a free port, then stop it
            from elastocal.cli import build_parser
            from elastocal.commands.view import ViewPage, build_view

            args = build_parser("view")[0].parse_args(argv)
            args.notes = []
            page = ViewPage(build_view(args), port=0)
            assert page.url.startswith("http://127.0.0.1:")
            page.stop()
            continue
        code = main(argv)
        out = capsys.readouterr()
        assert code == 0, (argv, out.err)
    for f in ("sim/report.html", "sim/cal.json", "sim/export/static.csv", "drift.png", "runs/sweep.csv",
              "plan.toml", "abs/cal.json", "calibrated.toml", "calibrated.urdf", "history.sqlite"):
        assert (tmp_path / f).stat().st_size > 0, f
