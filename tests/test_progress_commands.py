"""Long work is not silent: every command whose work grows with its inputs says on stderr where it
stands through elastocal/progress.py once it has worked for ``LONG_WORK_S``, its library telling it
through a callback; a quick run says nothing, and --json never (stdout is the one object)."""

import io
import json
import threading

import pytest

import elastocal.progress as progress_module
from elastocal.cli import main
from elastocal.progress import Progress


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    root = tmp_path_factory.mktemp("progress")
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "2", "--poses", "6",
                 "--out", str(root / "s")]) == 0
    assert main(["identify", "--robot", str(root / "s" / "robot.toml"), "--static", str(root / "s" / "static.csv"),
                 "--model", "joint_stiffness,kinematic_errors,tracker_frame", "--out", str(root / "cal.json")]) == 0
    return root


def _commands(root, out):
    out.mkdir(exist_ok=True)
    robot, static = str(root / "s" / "robot.toml"), str(root / "s" / "static.csv")
    return {
        "sim static": ["sim", "static", "--seed", "1", "--poses", "3", "--out", str(out / "ss")],
        "sim runs": ["sim", "runs", "--seed", "1", "--out", str(out / "sr")],
        "identify": ["identify", "--robot", robot, "--static", static],
        "diagnose": ["diagnose", "--robot", robot, "--static", static],
        "report": ["report", "--robot", robot, "--static", static, "--out", str(out / "r.html")],
        "validate": ["validate", "--calibration", str(root / "cal.json"), "--static", static],
        "plan": ["plan", "--robot", robot, "--test-pose", "0.3,0.5,-0.3,0.2,1.0,0.1", "--wrench", "800,-300,-600",
                 "--poses", "4", "--candidates", "100", "--out", str(out / "plan.toml")],
    }


@pytest.mark.parametrize("command", ["sim static", "sim runs", "identify", "diagnose", "report", "validate", "plan"])
def test_a_long_run_says_where_it_stands_and_json_says_nothing(tables, tmp_path, capsys, monkeypatch, command):
    # every run counts as long: the line is what a run of minutes shows after its first 3 s
    monkeypatch.setattr(progress_module, "LONG_WORK_S", 0.0)
    capsys.readouterr()
    argv = _commands(tables, tmp_path / "text")[command]
    assert main(argv) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(f"{command}: [")]
    assert lines, err
    assert lines[-1].split("]")[1].split()[0].split("/")[0] == lines[-1].split("]")[1].split()[0].split("/")[1]
    assert "elapsed" in lines[0]
    if command in ("sim static", "diagnose", "report"):       # the library's own units, told through the callback
        assert len(lines) >= 4, err
    assert main([*_commands(tables, tmp_path / "json")[command], "--json"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)
    assert f"{command}: [" not in captured.err, captured.err


def test_a_quick_run_says_nothing(tables, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(progress_module, "LONG_WORK_S", 60.0)       # a small validate takes about a second
    capsys.readouterr()
    assert main(["validate", "--calibration", str(tables / "cal.json"), "--static",
                 str(tables / "s" / "static.csv")]) == 0
    assert "validate: [" not in capsys.readouterr().err


def test_a_long_first_unit_is_told_when_it_has_taken_long_enough():
    """One long unit (a single fit of a large table) says where it stands after ``after_s``,
    not only when it ends; the context's end closes an open terminal line."""
    spoke = threading.Event()

    class Err(io.StringIO):
        def write(self, text):
            n = super().write(text)
            spoke.set()
            return n

    err = Err()
    with Progress("identify", 2, stream=err, after_s=0.05) as p:
        p(0, "fitting the static table")
        assert spoke.wait(30.0)                 # the timer's word (an event, not a duration)
        assert "identify: [" in err.getvalue() and "fitting the static table" in err.getvalue()
    quiet = Err()
    with Progress("identify", 2, stream=quiet, after_s=3600.0) as p:
        p(0, "fitting")
        p.done()
    assert quiet.getvalue() == ""               # quicker than after_s: nothing at all


def test_on_a_terminal_the_line_keeps_its_elapsed_time_going(monkeypatch):
    monkeypatch.setattr(progress_module, "REDRAW_S", 0.01)
    drawn = threading.Semaphore(0)

    class Terminal(io.StringIO):
        def isatty(self):
            return True

        def write(self, text):
            n = super().write(text)
            if text.startswith("\r"):
                drawn.release()
            return n

    tty = Terminal()
    with Progress("diagnose", 11, stream=tty, after_s=0.01) as p:
        p(3, "testing link_compliance against joint_stiffness")
        for _ in range(3):                      # the first word, then redraws of the same unit
            assert drawn.acquire(timeout=30.0)
    text = tty.getvalue()
    assert text.count("\r\x1b[2Kdiagnose: [") >= 3 and "3/11  testing link_compliance" in text
    assert text.endswith("\n")                  # the open line ended when the work stopped

