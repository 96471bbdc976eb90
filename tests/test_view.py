"""`elastocal view` in headless Chromium (WebGL through SwiftShader): the page shows the
robot at its poses and the error vectors, the before/after toggle recolours the poses,
the candidate table is beside it, and the command's own errors are one line."""

import io
import os
import shutil
import time

import numpy as np
import pytest

from elastocal.cli import build_parser, main

pytest.importorskip("viser")
playwright = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM) and not os.environ.get("CI"):
    pytest.skip("no chromium (apt-get install chromium)", allow_module_level=True)

#: Chromium as root, headless, no network of its own, WebGL without a GPU through SwiftShader
CHROMIUM_ARGS = ["--no-sandbox", "--no-first-run", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-quic", "--use-gl=angle", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("view") / "d"
    assert main(["sim", "static", "--hidden", "link_compliance", "--seed", "1", "--poses", "8", "--out",
                 str(out)]) == 0
    return out


def view_args(*argv):
    parser, _ = build_parser("view")
    args = parser.parse_args(["view", *argv])
    args.notes = []
    return args


def colour_pixels(png: bytes, rgb, tol=40) -> int:
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return int(np.sum(np.all(np.abs(img - np.array(rgb)) <= tol, axis=2)))


def wait_for_scene(page, timeout_s=60.0):
    """The viser client draws into a canvas once the scene arrives: wait until the canvas
    shows the robot (pixels of a pose colour), then a little more for the rest."""
    from elastocal.report.view import ratio_colours

    colours = [tuple(int(v) for v in c) for c in ratio_colours(np.array([1.0, 2.0, 5.0]))]
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        png = page.screenshot()
        if sum(colour_pixels(png, c, 20) for c in colours) > 500:
            time.sleep(1.0)
            return page.screenshot()
        time.sleep(0.5)
    raise AssertionError("the 3-D scene did not appear")


def test_view_in_headless_chromium_shows_the_robot_the_errors_and_the_toggle(dataset, tmp_path):
    from elastocal.commands.view import ERROR_RGB, ViewPage, build_view
    from elastocal.report.view import ratio_colours

    view = build_view(view_args("--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv")))
    assert [m.title for m in view.models] == ["model: joint_stiffness", "model + link_compliance"]
    before, after = view.models
    # the hidden effect leaves the default model far above the floor at most poses, the added one at it
    assert np.nanmedian(before.pose_ratio) > 2.0 and np.nanmax(after.pose_ratio) < 2.0
    red, amber, green = (tuple(int(v) for v in c) for c in ratio_colours(np.array([5.0, 2.0, 1.0])))
    page = ViewPage(view, port=0, magnify_errors=1000.0, pose="all")     # every pose: pixels enough to count
    try:
        assert page.server.get_host() == "127.0.0.1"
        with playwright.sync_playwright() as pw:
            # its crash reporter's folder (~/.config/chromium) goes to the test's folder, not the user's
            browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS,
                                         env={**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "config"),
                                              "XDG_CACHE_HOME": str(tmp_path / "cache")})
            try:
                tab = browser.new_page(viewport={"width": 1400, "height": 900})
                tab.goto(page.url)
                renderer = tab.evaluate("() => { const g = document.createElement('canvas').getContext('webgl2');"
                                        " return g ? g.getParameter(g.RENDERER) : null; }")
                assert renderer, "no WebGL in headless Chromium"
                shot = wait_for_scene(tab)
                (tmp_path / "before.png").write_bytes(shot)
                # the robot in the poses' colours (mostly red: the model misses an effect) and the error vectors
                n_red, n_green = colour_pixels(shot, red, 20), colour_pixels(shot, green, 20)
                assert n_red > 1000 and n_red > n_green
                assert colour_pixels(shot, ERROR_RGB, 50) > 150
                text = tab.inner_text("body")
                assert "link_compliance (verdict)" in text and "ΔBIC" in text
                assert "errors ×1000" in text and "Deflections ×100" in text
                # the toggle: the model with the diagnosed effect colours the poses green
                page.gui_model.value = after.title
                time.sleep(2.0)
                shot_after = tab.screenshot()
                (tmp_path / "after.png").write_bytes(shot_after)
                a_red, a_green = colour_pixels(shot_after, red, 20), colour_pixels(shot_after, green, 20)
                assert a_green > 1000 and a_red < 0.1 * n_red
                # its errors are at the noise floor: far fewer magenta pixels
                assert colour_pixels(shot_after, ERROR_RGB, 50) < 0.5 * colour_pixels(shot, ERROR_RGB, 50)
            finally:
                browser.close()
    finally:
        page.stop()


def test_view_refuses_bad_input_in_one_line(dataset, capsys):
    assert main(["view", "--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv"),
                 "--port", "70000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--port" in err[0]
    assert main(["view", "--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv"),
                 "--add", "nonsense"]) == 2
    assert "--add" in capsys.readouterr().err


def test_nominal_and_calibrated_geometry_toggle(tmp_path):
    """A calibration with kinematic_errors: the page draws the robot with the nominal or the
    calibrated geometry (difference magnified), and the calibration's prediction is a model."""
    from elastocal.commands.view import ViewPage, build_view
    from elastocal.report.view import geometry_skeletons

    d = tmp_path / "abs"
    assert main(["sim", "static", "--hidden", "kinematic_errors", "--seed", "2", "--poses", "8", "--out", str(d)]) == 0
    assert main(["identify", "--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"), "--model",
                 "joint_stiffness,kinematic_errors,tracker_frame", "--out", str(d / "cal.json")]) == 0
    view = build_view(view_args("--robot", str(d / "robot.toml"), "--static", str(d / "static.csv"),
                                "--calibration", str(d / "cal.json")))
    assert view.skeletons_calibrated is not None and view.models[-1].title.startswith("calibration")
    shift = np.linalg.norm(view.skeletons_calibrated - view.skeletons, axis=2)
    assert shift[:, 0].max() == 0.0 and 1e-4 < shift.max() < 1e-2        # the base stays, the arm moves by mm
    np.testing.assert_allclose(geometry_skeletons(view, True, 100.0) - view.skeletons,
                               100.0 * (view.skeletons_calibrated - view.skeletons))
    page = ViewPage(view, port=0)
    try:
        page.gui_geometry.value = "calibrated"
        deadline = time.monotonic() + 10
        while page.geometry != "calibrated" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert page.geometry == "calibrated" and "largest joint-origin shift" in page.gui_scale.content
    finally:
        page.stop()


def test_view_of_a_log_is_the_view_of_its_tables(dataset):
    """`elastocal view LOG.mcap`: the page of a log shows what the page of the tables it holds shows
    (the README's inputs: a log, or tables)."""
    from elastocal.commands.view import build_view

    from_log = build_view(view_args(str(dataset / "log.mcap")))
    from_tables = build_view(view_args("--robot", str(dataset / "robot.toml"), "--static", str(dataset / "static.csv")))
    assert from_log.pose_ids == from_tables.pose_ids and from_log.markers == from_tables.markers
    np.testing.assert_allclose(from_log.measured, from_tables.measured, rtol=0, atol=1e-12)
    np.testing.assert_allclose(from_log.skeletons, from_tables.skeletons, rtol=0, atol=1e-12)
    assert [m.title for m in from_log.models] == [m.title for m in from_tables.models]
    for a, b in zip(from_log.models, from_tables.models):
        np.testing.assert_allclose(a.pose_ratio, b.pose_ratio, rtol=1e-6)
