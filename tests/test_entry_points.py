"""Backends from other packages: the adapter of docs/devices.md, installed as a package
(a dist-info with entry_points.txt on a sys.path entry, as pip leaves it in site-packages;
importlib.metadata discovers both the same way), opened from cell.toml."""

import json
import os
import pathlib
import re
import subprocess
import sys
import textwrap

import pytest

from elastocal.drivers import open_drive, open_tracker, plugin_entry_points
from elastocal.drivers.config import parse_cell_config
from elastocal.errors import InputError

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs" / "devices.md"

DRIVE_ADAPTER = '''
import time
from elastocal.drivers.base import Drive
from elastocal.drivers.samples import DeviceInfo, DriveSample
from elastocal.errors import InputError


class ConstantDrive(Drive):
    """drive+constant://?current_a=1.5: a drive that always reads the same (a test adapter)."""

    def __init__(self, config, *, links=None):
        super().__init__(config.url, joint=config.joint, timeout_s=config.timeout_s, retries=config.retries)
        self.current_a = config.url.float_param("current_a", 1.0, source="drive.url")

    def _identify(self):
        return DeviceInfo(kind="drive", url=self.url.text, vendor="example", model="constant")

    def _read(self):
        return DriveSample(time.monotonic_ns(), self.joint, 0.25, self.current_a)

    def _stream(self, rate_hz):
        raise InputError("drive+constant does not stream")

    def _close(self):
        pass
'''


def install(site: pathlib.Path, name: str, modules: dict, entry_points: str) -> None:
    """What pip leaves in site-packages: the modules and a dist-info with METADATA and entry_points.txt."""
    for module, code in modules.items():
        (site / f"{module}.py").write_text(code)
    info = site / f"{name.replace('-', '_')}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points))


def docs_adapter() -> tuple[str, str]:
    """The adapter module and its entry point, as docs/devices.md shows them."""
    text = DOCS.read_text()
    code = re.search(r"```python\n# elastocal_replay.py\n(.*?)```", text, re.S).group(1)
    entry = re.search(r'\[project.entry-points."elastocal.trackers"\]\n"([^"]+)" = "([^"]+)"', text)
    return code, f"[elastocal.trackers]\n{entry.group(1)} = {entry.group(2)}\n"


@pytest.fixture
def site(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    code, entry = docs_adapter()
    install(site, "elastocal-replay", {"elastocal_replay": code}, entry)
    install(site, "elastocal-constant-drive", {"elastocal_constant_drive": DRIVE_ADAPTER},
            "[elastocal.drives]\ndrive+constant = elastocal_constant_drive:ConstantDrive\n")
    monkeypatch.syspath_prepend(str(site))
    return site


def cell_toml(tmp_path, tracker_url, drive_url=None) -> pathlib.Path:
    points = tmp_path / "points.csv"
    points.write_text("marker,x,y,z\nR1,1.5,0.25,0.75\nR2,1.6,0.2,0.7\nR1,1.5,0.25,0.76\n")
    drive = f'\n[[drive]]\njoint = 1\nurl = "{drive_url}"\n' if drive_url else ""
    path = tmp_path / "cell.toml"
    path.write_text(f'[cell]\nrobot = "hh150"\n{drive}\n[tracker]\nurl = "{tracker_url}"\nmarkers = ["R1", "R2"]\n')
    return path


def test_the_docs_adapter_is_opened_from_cell_toml(site, tmp_path):
    assert sorted(plugin_entry_points("tracker")) == ["tracker+replay"]
    path = cell_toml(tmp_path, f"tracker+replay://{tmp_path}/points.csv", "drive+constant://?current_a=2.5")
    config = parse_cell_config(path.read_text(), source=str(path), base_dir=tmp_path)
    tracker = open_tracker(config.tracker)
    try:
        assert type(tracker).__module__ == "elastocal_replay"
        assert tracker.identify().model == "replay"
        assert tracker.measure().tracker_p_marker == (1.5, 0.25, 0.75)
        tracker.select("R2")
        assert tracker.measure().tracker_p_marker == (1.6, 0.2, 0.7)
        tracker.select("R1")
        assert tracker.measure().tracker_p_marker == (1.5, 0.25, 0.76)
        with pytest.raises(Exception, match="no recorded point of R1 left"):
            tracker.measure()
    finally:
        tracker.close()
    drive = open_drive(config.drive(1))
    assert drive.read().current_a == 2.5 and type(drive).__name__ == "ConstantDrive"


def test_the_adapter_through_the_cli_in_a_fresh_interpreter(site, tmp_path):
    path = cell_toml(tmp_path, f"tracker+replay://{tmp_path}/points.csv")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-m", "elastocal", "devices", "--cell", str(path), "--identify-only",
                          "--json"], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    devices = json.loads(out.stdout)["devices"]
    assert [(d["kind"], d["vendor"], d["model"], d["details"]["points"]) for d in devices] == [
        ("tracker", "example", "replay", "3")]


def test_adapter_errors_are_one_line_input_errors(site, tmp_path):
    with pytest.raises(InputError, match=r"unknown device scheme 'tracker\+nosuch'.*tracker\+replay, tracker\+serial"):
        parse_cell_config('[cell]\nrobot = "hh150"\n[tracker]\nurl = "tracker+nosuch://x"\nmarkers = ["R1"]\n')
    # a tracker scheme is not a drive scheme
    with pytest.raises(InputError, match="tracker\\+replay:// cannot be used here"):
        parse_cell_config('[cell]\nrobot = "hh150"\n[[drive]]\njoint = 1\nurl = "tracker+replay:///p"\n')
    config = parse_cell_config(cell_toml(tmp_path, "tracker+replay:///no/such/file.csv").read_text())
    with pytest.raises(InputError, match="tracker\\+replay cannot read /no/such/file.csv"):
        open_tracker(config.tracker)
    # two packages claiming one scheme; an adapter that does not import; one that is not a Tracker
    install(site, "other-replay", {"other_replay": "class ReplayTracker: pass\n"},
            "[elastocal.trackers]\ntracker+replay = other_replay:ReplayTracker\n"
            "tracker+broken = no_such_module:Tracker\ntracker+wrong = other_replay:ReplayTracker\n")
    with pytest.raises(InputError, match="registered as a tracker backend by several installed packages: "
                                         "package elastocal-replay .*package other-replay"):
        open_tracker(config.tracker)
    for scheme, why in (("tracker+broken", "cannot be loaded: ModuleNotFoundError"),
                        ("tracker+wrong", "is not a subclass of elastocal.drivers.base.Tracker")):
        c = parse_cell_config(cell_toml(tmp_path, f"{scheme}:///p").read_text())
        with pytest.raises(InputError, match=f"{re.escape(scheme)}:// of package other-replay .*{why}"):
            open_tracker(c.tracker)
