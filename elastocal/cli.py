"""The ``elastocal`` command line: parse, call the library, print.

Each subcommand lives in ``elastocal.commands.<module>`` and is imported only
when it is used (a lazy table, like python-can's interface table). A command
module defines ``add_arguments(parser)`` and ``run(args) -> int``.

Expected errors print one line on stderr and exit 2 (bad input or usage) or
1 (device or runtime fault); see docs/cli.md.
"""

from __future__ import annotations

import contextlib
import argparse
import importlib
import importlib.util
import logging
import os
import sys

from elastocal import __version__
from elastocal.errors import DeviceError, ElastocalError, InputError

#: command name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("elastocal.commands.demo", "run the whole chain on the embedded simulated cell"),
    "sim": ("elastocal.commands.sim", "make datasets from the simulated cell, or serve simulated devices"),
    "identify": ("elastocal.commands.identify", "fit the elastostatic model to tables or a log"),
    "diagnose": ("elastocal.commands.diagnose", "compare model and measurements; rank missing effects"),
    "report": ("elastocal.commands.report", "write an HTML page showing where the model fails"),
    "devices": ("elastocal.commands.devices", "connect to the cell's devices and stream live readings"),
    "calibrate": ("elastocal.commands.calibrate", "run the guided calibration procedure"),
    "export": ("elastocal.commands.export", "turn an MCAP log into robot.toml and CSV tables"),
    "repair": ("elastocal.commands.repair", "a readable copy of a killed log, with a summary"),
    "import": ("elastocal.commands.import_", "turn tracker exports plus the joint log into the static table"),
    "geometry": ("elastocal.commands.geometry", "compensator geometry from a joint-2 marker sweep"),
    "compensate": ("elastocal.commands.compensate", "compensated joint trajectory for a planned path"),
    "plan": ("elastocal.commands.plan", "choose calibration poses and loads (design of experiments)"),
    "check": ("elastocal.commands.check", "check whether the current calibration still holds"),
    "history": ("elastocal.commands.history", "show calibrations and checks of a cell"),
    "schedule": ("elastocal.commands.schedule", "install a periodic calibration check"),
    "view": ("elastocal.commands.view", "show the cell in 3-D: poses, markers, errors magnified (local page)"),
    "fleet": ("elastocal.commands.fleet", "identify, diagnose or check many logs at once (Dask), record, drift"),
    "validate": ("elastocal.commands.validate", "a calibration against data it was not fitted on"),
    "robot": ("elastocal.commands.robot", "write the calibrated robot description (robot.toml, URDF)"),
    "stream": ("elastocal.commands.stream", "online compensation: stream corrections to the controller (EGM, RSI)"),
}


#: where each command is documented (shown at the end of its --help)
COMMAND_DOCS: dict[str, str] = {
    "demo": "docs/demo.md", "sim": "docs/devices.md (simulated cells), README.md (Simulated data)",
    "validate": "docs/absolute.md (Validate and check)", "robot": "docs/absolute.md (The calibrated robot)",
    "fleet": "docs/fleet.md",
    "identify": "docs/identification.md", "diagnose": "docs/diagnose.md", "report": "docs/diagnose.md",
    "devices": "docs/devices.md", "calibrate": "docs/calibrate.md", "export": "docs/log-format.md", "repair": "docs/log-format.md",
    "geometry": "docs/compensator.md", "compensate": "docs/compensation.md", "plan": "docs/plan.md",
    "check": "docs/check.md", "history": "docs/history.md", "schedule": "docs/check.md",
    "view": "docs/view.md", "import": "docs/import.md", "stream": "docs/stream.md",
}


#: commands that stream from devices (real or simulated in this process): they run with a short
#: interpreter switch interval, so that the SYNC producer and the receive threads get the
#: interpreter lock within a fraction of a 1 ms cycle (Python's default lets a busy thread
#: keep it for 5 ms); benchmarks/bench_devices.py measures the difference
STREAMING_COMMANDS = frozenset({"demo", "sim", "devices", "calibrate", "check", "stream"})
STREAMING_SWITCH_INTERVAL_S = 2e-4


#: third-party libraries whose log records would reach stderr through logging's last resort
#: (pymodbus "Connection to ... failed", canopen "Transfer aborted ..."): a command reports
#: their faults itself, as one line, so their records are held back while it runs
QUIET_LOGGERS = ("pymodbus", "canopen", "can")


def _quiet_libraries() -> dict[str, int]:
    """Raise the third-party loggers above CRITICAL; returns their previous levels."""
    previous = {}
    for name in QUIET_LOGGERS:
        logger = logging.getLogger(name)
        previous[name] = logger.level
        logger.setLevel(logging.CRITICAL + 1)
    return previous


def _restore_libraries(previous: dict[str, int]) -> None:
    for name, level in previous.items():
        logging.getLogger(name).setLevel(level)


def one_line(value: object) -> str:
    """An error message as one line: line breaks and other control characters a message
    quotes from the input (a header cell with a newline in it) are shown escaped."""
    text = str(value)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # usage errors: one line, exit 2
        self.exit(2, f"elastocal: {message}\n")


def _available() -> dict[str, tuple[str, str]]:
    found = {}
    for name, (module, text) in COMMANDS.items():
        if importlib.util.find_spec(module) is not None:
            found[name] = (module, text)
    return found


def build_parser(only: str | None = None) -> tuple[argparse.ArgumentParser, dict[str, object]]:
    """The parser; only the command module of ``only`` is imported (none if None: the top-level
    ``--help`` and ``--version`` need the names and one-line helps of the table alone, so they
    import none of the heavy libraries -- pinocchio, scipy, matplotlib, the drivers)."""
    parser = _Parser(prog="elastocal", description="Elastostatic calibration of industrial robot cells.")
    parser.add_argument("--version", action="version", version=f"elastocal {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    modules: dict[str, object] = {}
    for name, (module_name, text) in _available().items():
        docs = COMMAND_DOCS.get(name, "README.md (Workflows)")
        p = sub.add_parser(name, help=text, description=text,
                           epilog=f"Documentation: {docs} in the elastocal repository; words like noise floor "
                                  "or ΔBIC: README.md, Glossary.")
        if name == only:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            modules[name] = module
    return parser, modules


def _refuse_empty_values(parser, args) -> None:
    """A file, folder or value given as an empty string is bad input, never "not given"
    (``--out ""`` would otherwise write nothing and exit 0)."""
    for key, value in vars(args).items():
        if value == "" and key != "check_args":       # schedule's --check-args: "" is "no more arguments"
            flag = key if key in ("log", "path", "points") else "--" + key.replace("_", "-")
            raise InputError("is empty; give a value", source=flag)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)
    parser, modules = build_parser(first if first in COMMANDS else None)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    previous_interval = sys.getswitchinterval()
    if args.command in STREAMING_COMMANDS:
        sys.setswitchinterval(min(previous_interval, STREAMING_SWITCH_INTERVAL_S))
    previous_levels = _quiet_libraries()
    args.notes = []
    try:
        _refuse_empty_values(parser, args)
        from elastocal.commands._heartbeat import Heartbeat

        with Heartbeat(args.command, serves=getattr(args, "action", None) == "serve"):   # a word while it works
            code = int(modules[args.command].run(args) or 0)
        for text in args.notes:  # after the output, and only when the command did not fail on an error
            print(text, file=sys.stderr)
        return code
    except InputError as exc:
        # the library names its arguments; the command line says its flags
        exc = exc.on_command_line(getattr(modules[args.command], "ARGUMENT_FLAGS", None))
        print(f"elastocal {args.command}: {one_line(exc)}", file=sys.stderr)
        return 2
    except DeviceError as exc:
        print(f"elastocal {args.command}: {type(exc).__name__}: {one_line(exc)}", file=sys.stderr)
        return 1
    except ElastocalError as exc:
        print(f"elastocal {args.command}: {one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"elastocal {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader of our output went away (`elastocal … | head`): stop quietly, and
        # point stdout at /dev/null so that Python's flush at exit does not fail again
        with contextlib.suppress(OSError, ValueError, AttributeError):   # stdout without a file descriptor
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return 1
    except OSError as exc:
        # last resort: a file the command could not read or write (commands check their
        # files first; this catches what slips through) -- one line naming it, no traceback
        what = exc.strerror or str(exc) or type(exc).__name__
        if exc.filename is not None:
            print(f"elastocal {args.command}: {one_line(exc.filename)}: {one_line(what)}", file=sys.stderr)
            return 2
        print(f"elastocal {args.command}: {type(exc).__name__}: {what}", file=sys.stderr)
        return 1
    finally:
        _restore_libraries(previous_levels)
        sys.setswitchinterval(previous_interval)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
