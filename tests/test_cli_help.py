"""Every command's --help (and every subcommand's) works, points at the project's docs,
uses one --json wording and one name per idea; the old spellings still parse, unlisted."""

import argparse
import contextlib
import io
import pathlib
import re

import pytest

from elastocal.cli import COMMAND_DOCS, build_parser, main
from elastocal.commands._flags import DEFAULT_SEED, JSON_HELP

ROOT = pathlib.Path(__file__).parents[1]


def help_text(argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0, argv
    return out.getvalue()


def subcommands(parser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices
    return {}


def walk():
    """(argv, parser) of every command and subcommand."""
    parser, _ = build_parser()
    for name, p in subcommands(parser).items():
        _, modules = build_parser(name)
        full, _ = build_parser(name)
        cmd = subcommands(full)[name]
        yield [name], cmd
        for sub, sp in subcommands(cmd).items():
            yield [name, sub], sp


def test_every_help_works_and_points_at_docs_that_exist():
    seen = 0
    for argv, parser in walk():
        text = help_text(argv)
        seen += 1
        if len(argv) == 1:
            assert "Documentation:" in text and "Glossary" in text, argv
            docs = COMMAND_DOCS.get(argv[0])
            if docs:
                for part in docs.replace(",", " ").split():
                    if part.endswith(".md"):
                        assert (ROOT / part).exists(), (argv, part)
        for action in parser._actions:
            if "--json" in action.option_strings:
                assert action.help == JSON_HELP, argv
            if "--seed" in action.option_strings:
                assert action.default == DEFAULT_SEED, argv
    assert seen >= 20


def test_subcommands_have_their_own_help():
    assert help_text(["history", "add"]) != help_text(["history"])
    assert "--calibration" in help_text(["history", "add"]) and "--plot" not in help_text(["history", "add"])
    static, runs = help_text(["sim", "static"]), help_text(["sim", "runs"])
    assert "link_compliance" in static and "coulomb_friction" not in static and "viscous_friction" not in static
    assert "coulomb_friction" in runs and "link_compliance" not in runs
    assert "install" in help_text(["schedule"])


def test_one_name_per_idea_and_the_old_names_still_parse():
    pairs = [(["plan"], "--wrench", "--load"), (["plan"], "--map-wrench", "--map-load"),
             (["check"], "--db", "--history"), (["sim", "static"], "--loads-per-pose", "--loads")]
    for argv, new, old in pairs:
        text = help_text(argv)
        assert new in text and f"{old} " not in text.replace(new, ""), (argv, old)
    parser, _ = build_parser("plan")
    a = parser.parse_args(["plan", "--test-pose", "0,0,0,0,0,0", "--load", "1,2,3", "--out", "p.toml"])
    b = parser.parse_args(["plan", "--test-pose", "0,0,0,0,0,0", "--wrench", "1,2,3", "--out", "p.toml"])
    assert a.load == b.load == "1,2,3"
    parser, _ = build_parser("sim")
    assert parser.parse_args(["sim", "static", "--loads", "2", "--out", "d"]).loads == 2
    assert parser.parse_args(["sim", "static", "--loads-per-pose", "2", "--out", "d"]).loads == 2
    parser, _ = build_parser("check")
    assert parser.parse_args(["check", "--cell", "c", "--history", "h.db"]).history == "h.db"
    assert parser.parse_args(["check", "--cell", "c", "--db", "h.db"]).history == "h.db"
    parser, _ = build_parser("history")
    args = parser.parse_args(["history", "--db", "h.db", "add", "--calibration", "cal.json"])
    assert (args.action, args.db, args.calibration) == ("add", "h.db", "cal.json")
    args = parser.parse_args(["history", "--db", "h.db"])
    assert args.action == "show" and args.db == "h.db"


def test_plan_without_a_wrench_is_one_line(capsys, tmp_path):
    from elastocal.formats.robot_toml import bundled_robot_path

    assert main(["plan", "--robot", str(bundled_robot_path()), "--test-pose", "0,0.3,0.2,0,0.5,0",
                 "--out", str(tmp_path / "p.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--wrench" in err[0]


def test_sim_help_lists_exactly_the_effects_each_dataset_can_hide(capsys):
    """`sim static --help` names every static effect the simulator hides and no run-only one;
    `sim runs --help` the run effects."""
    from elastocal.sims.cell import HIDDEN_EFFECTS
    from elastocal.sims.runs import RUN_HIDDEN

    for kind, effects, others in (("static", HIDDEN_EFFECTS, RUN_HIDDEN), ("runs", RUN_HIDDEN, HIDDEN_EFFECTS)):
        with pytest.raises(SystemExit):
            main(["sim", kind, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        words = set(re.findall(r"[a-z_]+", text[text.rindex("--hidden HIDDEN"):text.rindex("--seed")]))
        assert set(effects) <= words, (kind, set(effects) - words)
        assert not (set(others) - set(effects)) & words, (kind, (set(others) - set(effects)) & words)
