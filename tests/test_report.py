"""The report page: it renders, is self-contained, holds the plots side by side
before and after adding the effect, and names the verdict (no browser needed)."""

import html.parser
import json
import re

import pytest

from elastocal.cli import main
from elastocal.diagnose.static import diagnose_static
from elastocal.diagnose.runs import diagnose_runs
from elastocal.report.html import render_report
from elastocal.formats.robot_toml import bundled_robot
from elastocal.sims.cell import HH150_STIFFNESS, CellTruth
from elastocal.sims.runs import FrictionPlan, default_run_truth, simulate_runs
from elastocal.sims.static import simulate_static

ROBOT = bundled_robot()
VOID = {"meta", "br", "img", "hr", "input", "link", "col", "area", "base", "wbr", "source"}


class _Page(html.parser.HTMLParser):
    """Checks nesting and collects what a test needs."""

    def __init__(self):
        super().__init__()
        self.stack = []
        self.errors = []
        self.svgs = 0
        self.ids = {}
        self.text_by_id = {}
        self.h3 = []
        self._capture = None
        self._h3 = False
        self.urls = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for key in ("src", "href", "xlink:href", "action"):
            if key in a and not a[key].startswith("#"):
                self.urls.append(a[key])
        if tag == "svg":
            self.svgs += 1
        if "id" in a:
            self.ids[a["id"]] = self.ids.get(a["id"], 0) + 1
            if a["id"] == "verdict":
                self._capture = "verdict"
                self.text_by_id["verdict"] = ""
        if tag == "h3":
            self._h3 = True
            self.h3.append("")
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}> with open {self.stack[-3:]}")
            return
        self.stack.pop()
        if tag == "div" and self._capture == "verdict":
            self._capture = None
        if tag == "h3":
            self._h3 = False

    def handle_data(self, data):
        if self._capture:
            self.text_by_id[self._capture] += data
        if self._h3:
            self.h3[-1] += data


def _parse(text: str) -> _Page:
    page = _Page()
    page.feed(text)
    page.close()
    return page


@pytest.fixture(scope="module")
def hidden_page():
    table = simulate_static(ROBOT, CellTruth().with_hidden("link_compliance"), seed=5)
    diag = diagnose_static(ROBOT, table)
    return diag, render_report(ROBOT, diag, inputs=["static.csv"], command="elastocal identify ...")


def test_page_renders_well_formed_and_self_contained(hidden_page):
    _, text = hidden_page
    assert text.startswith("<!DOCTYPE html>")
    page = _parse(text)
    assert page.errors == [] and page.stack == []
    assert page.urls == []                               # no src/href to anything outside the page
    assert "<script" not in text and "<link" not in text and "<img" not in text
    # no URL anywhere except XML namespace declarations of the inline SVGs
    without_ns = re.sub(r'xmlns(:\w+)?="[^"]*"', "", text)
    assert not re.search(r"(https?:|ftp:|file:)//", without_ns)
    dup = {k: v for k, v in page.ids.items() if v > 1}
    assert dup == {}, "ids must stay unique across the inline SVGs"


def test_page_names_the_verdict_and_holds_the_plots_before_and_after(hidden_page):
    diag, text = hidden_page
    assert diag.verdict == "link_compliance"
    page = _parse(text)
    assert "link_compliance" in page.text_by_id["verdict"]
    assert "misses something" in page.text_by_id["verdict"]
    for title in ("Measured and predicted deflection per pose", "Residual per pose against the noise floor",
                  "Residual against q2", "Residual against time", "Residual against the load",
                  "Residual by marker", "Residual by load state"):
        assert title in page.h3
    assert page.svgs == 7 + 2          # and the absolute section's two (report/absolute.py)
    # every plot has the model and the model with the effect side by side
    assert text.count(">model: joint_stiffness</text>") == 7
    assert text.count(">model + link_compliance</text>") == 7
    assert 'id="candidates"' in text and "ΔBIC" in text
    assert "cl2x" in text                      # parameters of the augmented fit


def test_page_on_complete_data_says_no_missing_effect():
    diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth(), seed=6))
    text = render_report(ROBOT, diag)
    page = _parse(text)
    assert page.errors == []
    assert "no missing effect found" in page.text_by_id["verdict"]
    assert "model +" not in text and page.svgs == 7 + 2   # and the absolute section's two


def test_page_with_run_data_shows_the_uv_vu_current_differences():
    runs = simulate_runs(ROBOT, default_run_truth(CellTruth()), seed=3, sweeps=None,
                         friction=FrictionPlan(samples=80))
    rdiag = diagnose_runs(ROBOT, runs, model=("coulomb_friction",), stiffness=HH150_STIFFNESS)
    diag = diagnose_static(ROBOT, simulate_static(ROBOT, CellTruth(), seed=7))
    text = render_report(ROBOT, diag, rdiag)
    page = _parse(text)
    assert page.errors == []
    assert "UV/VU current differences (friction torque) and the model" in page.h3
    assert page.svgs == 8 + 2          # and the absolute section's two
    assert f"+ {rdiag.verdict}" in text and rdiag.verdict == "load_dependent_friction"


@pytest.mark.heavy
def test_report_command_writes_the_page(tmp_path, capsys):
    d = tmp_path / "sim"
    assert main(["sim", "static", "--hidden", "thermal_drift", "--seed", "2", "--out", str(d)]) == 0
    out = tmp_path / "report.html"
    capsys.readouterr()
    rc = main(["report", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
               "--out", str(out), "--json"])
    assert rc == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj == {"out": str(out), "verdict": "thermal_drift", "bytes": len(out.read_bytes())}
    page = _parse(out.read_text(encoding="utf-8"))
    assert "thermal_drift" in page.text_by_id["verdict"] and page.svgs == 7 + 2
    # --add shows another candidate beside the model; an effect the data cannot show is refused
    rc = main(["report", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
               "--out", str(out), "--add", "backlash", "--force"])
    assert rc == 0 and "model + backlash" in out.read_text(encoding="utf-8")
    capsys.readouterr()
    rc = main(["report", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
               "--out", str(out), "--add", "gravity", "--force"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "gravity cancels" in err


def test_text_from_the_user_is_escaped():
    """The page is f-strings, not a template engine that escapes by default (docs/architecture.md):
    every text from outside goes through html.escape, so a file name with markup stays text."""
    from dataclasses import replace

    page = render_report(replace(ROBOT, name="<b>HH</b>"), None, inputs=["a&b<script>.csv"])
    assert "<script" not in page and "<b>HH" not in page
    assert "&lt;b&gt;HH&lt;/b&gt;" in page and "a&amp;b&lt;script&gt;.csv" in page
