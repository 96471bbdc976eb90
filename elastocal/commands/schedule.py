"""`elastocal schedule install`: run the calibration check periodically (docs/check.md).

    elastocal schedule install --every 7d --cell cell.toml [--unit-dir DIR] [--check-args "--sim --yes"]
    elastocal schedule install --every 1d --cell cell.toml --crontab

Writes a systemd service (one ``elastocal check`` run) and a timer, or prints
a crontab line. It never runs systemctl: it prints the commands that enable
the timer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import re
import shlex
import sys
from dataclasses import dataclass

from elastocal.errors import InputError

WEEKDAYS = ("Mon", "Tue", "Wed", "Thu", "Fri", "Sat", "Sun")
_UNITS_S = {"m": 60, "min": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


@dataclass(frozen=True)
class Every:
    """A period: ``count`` of ``unit`` (m, h, d or w)."""

    count: int
    unit: str

    @property
    def seconds(self) -> int:
        return self.count * _UNITS_S[self.unit]

    @property
    def systemd(self) -> str:
        return f"{self.count}{'min' if self.unit == 'm' else self.unit}"


def parse_every(text: str) -> Every:
    """``30m``, ``6h``, ``1d``, ``7d``, ``2w``."""
    m = re.fullmatch(r"\s*(\d+)\s*(m|min|h|d|w)\s*", text)
    if not m or int(m.group(1)) < 1:
        raise InputError(f"expected a period such as 30m, 6h, 1d, 7d or 2w, got {text!r}", source="--every")
    unit = "m" if m.group(2) in ("m", "min") else m.group(2)
    every = Every(int(m.group(1)), unit)
    if every.seconds < 600:
        raise InputError("a check moves the robot: run it at most every 10 minutes", source="--every")
    return every


def parse_at(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d{1,2}):(\d{2})", text.strip())
    if not m or int(m.group(1)) > 23 or int(m.group(2)) > 59:
        raise InputError(f"expected HH:MM, got {text!r}", source="--at")
    return int(m.group(1)), int(m.group(2))


def on_calendar(every: Every, at: tuple[int, int], weekday: str) -> str | None:
    """The systemd OnCalendar expression for the period, None when a calendar
    cannot express it exactly (then a monotonic timer is used)."""
    hh, mm = at
    s = every.seconds
    if s < 3600 and 3600 % s == 0:
        return f"*-*-* *:00/{s // 60}:00"
    if s < 86400 and s % 3600 == 0 and 86400 % s == 0:
        return f"*-*-* 00/{s // 3600}:{mm:02d}:00"
    if s == 86400:
        return f"*-*-* {hh:02d}:{mm:02d}:00"
    if s == 7 * 86400:
        return f"{weekday} *-*-* {hh:02d}:{mm:02d}:00"
    return None


def crontab_schedule(every: Every, at: tuple[int, int], weekday: str) -> str:
    hh, mm = at
    s = every.seconds
    if s < 3600 and 3600 % s == 0:
        return f"*/{s // 60} * * * *"
    if s == 3600:
        return f"{mm} * * * *"
    if s < 86400 and s % 3600 == 0 and 86400 % s == 0:
        return f"{mm} */{s // 3600} * * *"
    if s == 86400:
        return f"{mm} {hh} * * *"
    if s == 7 * 86400:
        return f"{mm} {hh} * * {(WEEKDAYS.index(weekday) + 1) % 7}"
    raise InputError(f"cron cannot run something every {every.systemd} exactly; use the systemd timer "
                     "(without --crontab)", source="--every")


def _systemd_quote(arg: str) -> str:
    """One ExecStart word: quoted when needed, ``%`` escaped (systemd specifiers)."""
    arg = arg.replace("%", "%%")
    if re.search(r"[\s\"'\\;$]", arg) or not arg:
        return '"' + arg.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return arg


def parse_check_args(cell: pathlib.Path, extra: list[str]) -> argparse.Namespace:
    """``elastocal check --cell CELL EXTRA...`` parsed by the check command's own
    parser, so that a scheduled check fails now rather than at every run."""
    from elastocal.commands import check

    class _Raising(argparse.ArgumentParser):
        def error(self, message: str) -> None:  # one line naming the flag, not argparse's usage and exit
            raise InputError(f"`elastocal check` would refuse them: {message}", source="--check-args")

    parser = _Raising(prog="elastocal check", add_help=False)
    check.add_arguments(parser)
    try:
        return parser.parse_args(["--cell", str(cell), *extra])
    except SystemExit:  # --help and the like
        raise InputError("not arguments a scheduled check can run with", source="--check-args") from None


def check_command(python: str, cell: pathlib.Path, extra: list[str]) -> list[str]:
    return [python, "-m", "elastocal", "check", "--cell", str(cell), *extra]


def service_unit(cell_name: str, command: list[str], working_dir: pathlib.Path) -> str:
    exec_start = " ".join(_systemd_quote(a) for a in command)
    return "\n".join([
        "# written by `elastocal schedule install`",
        "[Unit]",
        f"Description=elastocal: check the calibration of {cell_name}",
        "",
        "[Service]",
        "Type=oneshot",
        f"WorkingDirectory={_systemd_quote(str(working_dir))}",
        "# exit 0: the calibration holds; exit 3: recalibrate (the unit shows as failed;",
        "# the verdict and its reason are in the cell's history and in the journal)",
        f"ExecStart={exec_start}",
        "",
    ])


def timer_unit(name: str, cell_name: str, every: Every, calendar: str | None) -> str:
    lines = ["# written by `elastocal schedule install`", "[Unit]",
             f"Description=elastocal: calibration check of {cell_name} every {every.systemd}", "", "[Timer]"]
    if calendar is not None:
        lines += [f"OnCalendar={calendar}", "Persistent=true"]
    else:
        lines += [f"OnActiveSec={every.systemd}", f"OnUnitActiveSec={every.systemd}"]
    lines += ["AccuracySec=1min", f"Unit={name}.service", "", "[Install]", "WantedBy=timers.target", ""]
    return "\n".join(lines)


def user_unit_dir() -> pathlib.Path:
    return pathlib.Path.home() / ".config" / "systemd" / "user"


SYSTEM_UNIT_DIR = pathlib.Path("/etc/systemd/system")


def enable_commands(unit_dir: pathlib.Path, name: str) -> tuple[list[str], bool]:
    """The systemctl commands that enable the timer written into ``unit_dir``, and whether they are
    the user's. A folder outside systemd's search path is linked (``systemctl link``) by its
    absolute path: ``enable NAME.timer`` alone would not find the units there."""
    where = unit_dir.resolve()
    if where == user_unit_dir().resolve():
        return ["systemctl --user daemon-reload", f"systemctl --user enable --now {name}.timer"], True
    if where == SYSTEM_UNIT_DIR:
        return ["systemctl daemon-reload", f"systemctl enable --now {name}.timer"], False
    service, timer = (shlex.quote(str(where / f"{name}{ext}")) for ext in (".service", ".timer"))
    return [f"systemctl --user link {service}", f"systemctl --user enable --now {timer}"], True


def _write_atomic(files: dict[pathlib.Path, str]) -> None:
    temps = {}
    try:
        for path, text in files.items():
            temps[path] = path.with_name(f".{path.name}.elastocal-partial")
            temps[path].write_text(text, encoding="utf-8")
        for path, temp in temps.items():
            os.replace(temp, path)
    finally:
        for temp in temps.values():
            with contextlib.suppress(OSError):
                temp.unlink()


def unattended_check(check_args: argparse.Namespace, config, db: pathlib.Path | None) -> str | None:
    """Refuse a schedule whose check can test nothing without a person: a timer runs it with no
    terminal, so the check poses are read unloaded and only the steps that need no person run
    (docs/check.md, Unattended checks). Returns a note when the plan or calibration cannot be
    known yet (nothing recorded)."""
    from elastocal.commands.check import _calibration, baseline_log
    from elastocal.formats.plan import load_plan, parse_plan
    from elastocal.model.effects import having

    if not check_args.calibration and (db is None or not db.exists()):
        return (f"no calibration recorded yet in {db}: whether the check can run unattended is not known; "
                "`elastocal check --cell ... --unattended` tells once one is recorded")
    cal, cal_id, plan_text = _calibration(check_args, db)
    if check_args.plan:
        plan = load_plan(check_args.plan)
    elif plan_text is not None:
        plan = parse_plan(plan_text, source="the plan stored with the calibration")
    elif config.plan is not None:
        plan = load_plan(config.plan)
    else:
        return "no check plan found yet: whether the check can run unattended is not known"
    if plan.check is None:
        raise InputError("the plan has no [check] section: a scheduled check could not run", source=plan.source)
    friction_run = plan.check.friction is not None and any(
        cal.has(f"fc{j}") for j in range(1, len(config.load_robot().joints) + 1))
    # the check poses read unloaded: compared with the calibration's own log (history add --log), or
    # with its geometry when it holds one
    positions = bool(plan.check.poses) and (baseline_log(db, cal_id) is not None
                                            or bool(having("geometry", cal.model)))
    if friction_run or positions:
        return None
    raise InputError("the scheduled check would exit 2 every time: without a person it reads the check poses "
                     "unloaded and runs the friction path, and nothing here compares them with the calibration "
                     "(no log of the calibration in the history, no geometry in it, no friction run or no "
                     "friction in it); record the calibration with its log (`elastocal history add --log`), "
                     "or (a simulated cell) pass --check-args=\"--yes\"", source=plan.source)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="{install}")
    sub.required = True
    parser = sub.add_parser("install", help="write the systemd units (or print a crontab line)",
                            description="write a systemd service and timer (or print a crontab line) that run "
                                        "`elastocal check --cell CELL` on a schedule")
    parser.add_argument("--every", required=True, help="period: 30m, 6h, 1d, 7d, 2w")
    parser.add_argument("--cell", required=True, help="cell.toml of the cell to check")
    parser.add_argument("--at", default="06:00", help="time of day for daily and weekly checks (default 06:00)")
    parser.add_argument("--on", default="Mon", choices=WEEKDAYS, help="weekday of weekly checks (default Mon)")
    parser.add_argument("--name", default="elastocal-check", help="unit name (default elastocal-check)")
    parser.add_argument("--unit-dir", help="where to write the units (default ~/.config/systemd/user)")
    parser.add_argument("--check-args", default="", help="more arguments for `elastocal check`, one string "
                                                         "(e.g. \"--sim --yes\")")
    parser.add_argument("--crontab", action="store_true", help="print a crontab line instead of writing units")
    parser.add_argument("--force", action="store_true", help="overwrite existing units")
    parser.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from elastocal.drivers.config import load_cell_config

    every = parse_every(args.every)
    at = parse_at(args.at)
    if not re.fullmatch(r"[A-Za-z0-9_.@-]+", args.name):
        raise InputError("unit names use letters, digits and _.@- only", source="--name")
    cell_path = pathlib.Path(args.cell).resolve()
    config = load_cell_config(cell_path)
    try:
        extra = shlex.split(args.check_args)
    except ValueError as exc:
        raise InputError(f"cannot split: {exc}", source="--check-args") from None
    if "--cell" in extra or any(a.startswith("--cell=") for a in extra):
        raise InputError("--cell is given by `schedule --cell`", source="--check-args")
    check_args = parse_check_args(cell_path, extra)
    db = pathlib.Path(check_args.history) if check_args.history else config.history
    if not check_args.calibration and db is None:
        raise InputError(f"the scheduled check would have no calibration to check: {args.cell} names no history "
                         "(`history = \"history.sqlite\"` in its [cell] table) and the arguments give no "
                         "--calibration", source="--check-args")
    attended = check_args.yes           # a simulated cell's prompts answered: every step runs
    note = None if attended else unattended_check(check_args, config, db)
    if note:
        from elastocal.commands._outputs import note as queue_note

        queue_note(args, f"note: {note}")
    command = check_command(sys.executable, cell_path, extra)
    if args.crontab:
        line = f"{crontab_schedule(every, at, args.on)} cd {shlex.quote(str(cell_path.parent))} && " \
               + " ".join(shlex.quote(a) for a in command)
        if args.json:
            print(json.dumps({"crontab": line}))
        else:
            print(f"# add this line with `crontab -e` (check of {config.name} every {every.systemd}):")
            print(line)
        return 0
    unit_dir = pathlib.Path(args.unit_dir) if args.unit_dir else user_unit_dir()
    service = unit_dir / f"{args.name}.service"
    timer = unit_dir / f"{args.name}.timer"
    for path in (service, timer):
        if path.exists() and not args.force:
            raise InputError("already exists; choose another --name or --unit-dir, or --force to overwrite it",
                             source=str(path))
    calendar = on_calendar(every, at, args.on)
    try:
        unit_dir.mkdir(parents=True, exist_ok=True)
        # both units or neither: each written to a temporary sibling, then renamed into place
        _write_atomic({service: service_unit(config.name, command, cell_path.parent),
                       timer: timer_unit(args.name, config.name, every, calendar)})
    except OSError as exc:
        raise InputError(f"cannot write: {exc.strerror}", source=str(unit_dir)) from None
    enable, user = enable_commands(unit_dir, args.name)
    if args.json:
        print(json.dumps({"service": str(service), "timer": str(timer), "on_calendar": calendar,
                          "every_s": every.seconds, "command": command, "enable": enable}))
        return 0
    print(f"wrote {service}\nwrote {timer}")
    print(f"the timer runs `elastocal check` of {config.name} every {every.systemd}"
          + (f" ({calendar})" if calendar else " (counted from the last run)") + "; enable it with:")
    for c in enable:
        print(f"  {c}")
    if user:
        print("  loginctl enable-linger   # so user timers run while nobody is logged in")
    return 0
