"""The report's layout in headless Chromium: the side-by-side group tables (q1..q6 bins,
load sizes, ...) stay inside their column and no cell's text spills out (element boxes
from the DOM, not pixels)."""

import os
import shutil

import pytest

from elastocal.cli import main

playwright = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM) and not os.environ.get("CI"):
    pytest.skip("no chromium (apt-get install chromium)", allow_module_level=True)
ARGS = ["--no-sandbox", "--no-first-run", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--disable-quic"]

BOXES = """() => {
  const box = e => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; };
  const pairs = [...document.querySelectorAll('.pair')].filter(p => p.querySelectorAll('table').length >= 8);
  return pairs.map(p => [...p.children].map(col => ({
      col: box(col), overflow: col.scrollWidth - col.clientWidth,
      tables: [...col.querySelectorAll('table')].map(box),
      cells: [...col.querySelectorAll('th,td')].filter(c => c.scrollWidth > c.clientWidth + 1).length,
      n: col.querySelectorAll('table').length})));
}"""


@pytest.fixture(scope="module")
def report_page(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    data = tmp / "d"
    assert main(["sim", "static", "--hidden", "link_compliance", "--seed", "3", "--poses", "8", "--out",
                 str(data)]) == 0
    page = tmp / "report.html"
    assert main(["report", "--robot", str(data / "robot.toml"), "--static", str(data / "static.csv"),
                 "--out", str(page)]) == 0
    return page


@pytest.mark.parametrize("width", [1280, 900])
def test_group_tables_stay_in_their_column(report_page, tmp_path, width):
    page = report_page
    with playwright.sync_playwright() as pw:
        # its crash reporter's folder (~/.config/chromium) goes to the test's folder, not the user's
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS,
                                     env={**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "config"),
                                          "XDG_CACHE_HOME": str(tmp_path / "cache")})
        try:
            tab = browser.new_page(viewport={"width": width, "height": 900})
            tab.goto(page.as_uri())
            pairs = tab.evaluate(BOXES)
            tab.screenshot(path=str(tmp_path / "report.png"), full_page=True)
        finally:
            browser.close()
    assert pairs and all(len(cols) == 2 for cols in pairs)       # before and after, side by side
    for cols in pairs:
        for c in cols:
            assert c["n"] >= 8                                   # marker, load, q1..q6, load size
            assert c["overflow"] <= 0 and c["cells"] == 0, c
            left, top, right, bottom = c["col"]
            for t in c["tables"]:
                assert t[0] >= left - 0.5 and t[2] <= right + 0.5, (t, c["col"])
        a, b = cols[0]["col"], cols[1]["col"]
        side_by_side = a[2] <= b[0] + 0.5
        stacked = a[3] <= b[1] + 0.5
        assert side_by_side or stacked, (a, b)                  # the columns never overlap
