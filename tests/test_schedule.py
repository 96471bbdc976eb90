"""`elastocal schedule install`: the systemd units and crontab lines it writes
(never runs systemctl)."""

import json
import re
import shutil
import subprocess
import sys

import pytest

from elastocal.cli import main
from elastocal.commands.schedule import Every, on_calendar, parse_every


@pytest.fixture()
def cell(tmp_path):
    path = tmp_path / "my cell 100%" / "cell.toml"
    path.parent.mkdir()
    path.write_text('[cell]\nname = "press line 3"\nrobot = "hh150"\nhistory = "history.sqlite"\n')
    return path


def units(unit_dir):
    return ((unit_dir / "elastocal-check.service").read_text(), (unit_dir / "elastocal-check.timer").read_text())


def test_weekly_units(cell, tmp_path, capsys):
    unit_dir = tmp_path / "units"
    assert main(["schedule", "install", "--every", "7d", "--cell", str(cell), "--unit-dir", str(unit_dir),
                 "--check-args", "--sim --yes"]) == 0
    out = capsys.readouterr().out
    service, timer = units(unit_dir)
    assert "[Service]\nType=oneshot\n" in service
    exec_start = next(line for line in service.splitlines() if line.startswith("ExecStart="))
    # the cell path has a space and a '%': quoted, and '%' escaped from systemd's specifiers
    cell_word = '"' + str(cell).replace("%", "%%") + '"'
    assert exec_start == f"ExecStart={sys.executable} -m elastocal check --cell {cell_word} --sim --yes"
    assert f'WorkingDirectory="{str(cell.parent).replace("%", "%%")}"' in service
    assert "Description=elastocal: check the calibration of press line 3" in service
    assert "OnCalendar=Mon *-*-* 06:00:00\nPersistent=true\n" in timer
    assert "Unit=elastocal-check.service" in timer and "[Install]\nWantedBy=timers.target" in timer
    # a folder outside systemd's search path: the units are linked by their absolute paths
    assert f"systemctl --user link {unit_dir.resolve() / 'elastocal-check.service'}" in out
    assert f"systemctl --user enable --now {unit_dir.resolve() / 'elastocal-check.timer'}" in out
    if shutil.which("systemd-analyze"):
        spec = re.search(r"OnCalendar=(.*)", timer).group(1)
        assert subprocess.run(["systemd-analyze", "calendar", spec], capture_output=True).returncode == 0
    # written once; a second time needs --force
    assert main(["schedule", "install", "--every", "7d", "--cell", str(cell), "--unit-dir", str(unit_dir)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["schedule", "install", "--every", "1d", "--at", "05:30", "--cell", str(cell), "--unit-dir",
                 str(unit_dir), "--force", "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["on_calendar"] == "*-*-* 05:30:00" and obj["every_s"] == 86400
    assert obj["command"][-2:] == ["--cell", str(cell)]


def test_periods_without_a_calendar_count_from_the_last_run(cell, tmp_path, capsys):
    unit_dir = tmp_path / "u"
    assert main(["schedule", "install", "--every", "5d", "--cell", str(cell), "--unit-dir", str(unit_dir)]) == 0
    _, timer = units(unit_dir)
    assert "OnCalendar" not in timer and "Persistent" not in timer
    assert "OnActiveSec=5d\nOnUnitActiveSec=5d\n" in timer
    assert on_calendar(Every(6, "h"), (6, 0), "Mon") == "*-*-* 00/6:00:00"
    assert on_calendar(Every(30, "m"), (6, 0), "Mon") == "*-*-* *:00/30:00"
    assert on_calendar(Every(1, "w"), (7, 15), "Fri") == "Fri *-*-* 07:15:00"
    assert on_calendar(Every(5, "h"), (6, 0), "Mon") is None
    assert parse_every("2w").seconds == 14 * 86400


def test_crontab_line(cell, capsys):
    assert main(["schedule", "install", "--every", "1d", "--cell", str(cell), "--crontab", "--json"]) == 0
    line = json.loads(capsys.readouterr().out)["crontab"]
    assert line.startswith("0 6 * * * cd ")
    assert f"-m elastocal check --cell '{cell}'" in line
    assert main(["schedule", "install", "--every", "7d", "--on", "Sun", "--cell", str(cell), "--crontab"]) == 0
    assert "\n0 6 * * 0 cd " in capsys.readouterr().out
    assert main(["schedule", "install", "--every", "5d", "--cell", str(cell), "--crontab"]) == 2
    assert "cron cannot" in capsys.readouterr().err


@pytest.mark.parametrize("every, message", [("weekly", "expected a period"), ("0d", "expected a period"),
                                            ("5m", "at most every 10 minutes")])
def test_bad_periods_are_one_line_errors(cell, tmp_path, capsys, every, message):
    assert main(["schedule", "install", "--every", every, "--cell", str(cell), "--unit-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and not (tmp_path / "elastocal-check.timer").exists()
