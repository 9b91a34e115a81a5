"""The interactive HTML report: self-contained, and drawn by a real headless browser.

The browser test drives the system's chromium through chromedriver (Debian packages
``chromium`` and ``chromium-driver``, installed by ``.ci/run``) with selenium: the page must
load from a file with no network, log no console errors, and show a 3D view that is not
blank. Outside CI it is skipped when no browser is installed.
"""

import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from plenoptrack.errors import SettingsError
from plenoptrack.report import REPORT_DIV_ID, report_figure, report_html, summary_rows
from plenoptrack.track import TrackSettings, track_particles


@pytest.fixture(scope="module")
def tracks():
    rng = np.random.default_rng(0)
    rows = []
    for k in range(12):
        start = rng.uniform(-10, 10, 3)
        v = rng.normal(0, 0.6, 3)
        for f in range(8):
            rows.append((f, *(start + v * f + rng.normal(0, [0.02, 0.02, 0.1])), 0.5 + 0.1 * k))
    p = pd.DataFrame(rows, columns=["frame", "x", "y", "z", "diameter"]).assign(
        sigma_x=0.02, sigma_y=0.02, sigma_z=0.1)
    return track_particles(p, TrackSettings(search_range_mm=(1.5, 2.0))).tracks


def test_html_is_self_contained_with_hover_and_summary(tracks):
    html = report_html(tracks, color_by="speed", title="twelve <tracks>")
    assert html.startswith("<!DOCTYPE html>")
    assert "<title>twelve &lt;tracks&gt;</title>" in html
    # plotly.js is embedded: no script or stylesheet is loaded from anywhere
    assert not re.findall(r"<script[^>]+src=", html)
    assert not re.findall(r"<link[^>]+href=\"http", html)
    assert "Plotly.newPlot" in html and len(html) > 1_000_000
    assert f'id="{REPORT_DIV_ID}"' in html
    assert "speed (mm\\u002fframe): " in html and "track: " in html   # JSON escapes "/"
    assert "<td>tracks</td><td>12</td>" in html


def test_figure_traces(tracks):
    fig = report_figure(tracks, color_by="depth")
    markers, lines = fig.data
    assert len(markers.x) == len(tracks)
    # one line per track, separated by None
    assert sum(v is None for v in lines.x) == tracks["particle"].nunique()
    np.testing.assert_allclose(np.asarray(markers.marker.color, float), tracks["z"])
    # y (sensor rows, downwards) is the vertical axis, reversed
    assert fig.layout.scene.zaxis.autorange == "reversed"
    particles_only = report_figure(tracks[["frame", "x", "y", "z"]])
    assert len(particles_only.data) == 1
    with pytest.raises(SettingsError, match="speed"):
        report_figure(tracks[["frame", "x", "y", "z"]], color_by="speed")
    rows = dict(summary_rows(tracks))
    assert rows["tracks"] == "12" and rows["frames"] == "8"


def _browser():
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not (chromium and driver):
        if os.environ.get("CI"):
            pytest.fail("chromium and chromedriver must be installed in CI (see .ci/run)")
        pytest.skip("no chromium/chromedriver installed (apt-get install chromium chromium-driver)")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        if os.environ.get("CI"):
            raise
        pytest.skip("selenium is not installed (pip install -e '.[test]')")
    opts = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                "--window-size=1200,900", "--disable-dev-shm-usage"):
        opts.add_argument(arg)
    opts.binary_location = chromium
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(driver), options=opts)


def test_report_in_a_headless_browser(tracks, tmp_path):
    from PIL import Image

    page = tmp_path / "report.html"
    page.write_text(report_html(tracks, color_by="speed"), encoding="utf-8")
    browser = _browser()
    try:
        browser.get(page.as_uri())
        ready = None
        for _ in range(300):
            ready = browser.find_element("tag name", "body").get_attribute("data-plot-ready")
            if ready:
                break
            time.sleep(0.2)
        assert ready == "1", "plotly did not draw the 3D view"
        time.sleep(1.0)
        log = browser.get_log("browser")
        view = browser.find_element("id", REPORT_DIV_ID)
        shot = tmp_path / "view.png"
        view.screenshot(str(shot))
    finally:
        browser.quit()
    # no page errors and nothing the page itself logged as a warning or an error
    errors = [e for e in log if e["level"] == "SEVERE"
              or e.get("source") in ("javascript", "console-api") and e["level"] != "INFO"]
    assert not errors, errors
    image = np.asarray(Image.open(shot).convert("RGB"), dtype=float)
    assert image.shape[0] > 300 and image.shape[1] > 500
    # not blank: many colours, and saturated (coloured) marker pixels
    colours = len(np.unique(image.reshape(-1, 3), axis=0))
    saturation = image.max(axis=2) - image.min(axis=2)
    assert colours > 200
    assert (saturation > 80).mean() > 0.005
    keep = os.environ.get("PLENOPTRACK_SCREENSHOT")      # to look at it
    if keep:
        Path(keep).write_bytes(shot.read_bytes())
