"""The compare report in a real browser: headless Chromium renders it from disk with no network,
every embedded image decodes, nothing fails to load, and the page is not blank.

Needs the Debian packages ``chromium`` and ``chromium-driver`` and the ``selenium`` Python package:
missing ones fail the test under CI (``CI=true``) and skip it elsewhere. The full-page screenshot
is kept at ``$DQSKIN_SCREENSHOT`` (default ``<tmp>/report_screenshot.png``) for a person to look at.
"""

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dqskin.report.compare import run_compare

ASSETS = Path(__file__).resolve().parents[1] / "assets"
IN_CI = os.environ.get("CI", "").lower() == "true"


def _require(ok, what):
    if not ok:
        if IN_CI:
            pytest.fail(f"{what} is missing (required in CI: apt-get install chromium "
                        "chromium-driver; pip install selenium)")
        pytest.skip(f"{what} not installed")


def _tool(name):
    path = shutil.which(name) or (f"/usr/bin/{name}" if os.access(f"/usr/bin/{name}", os.X_OK)
                                  else None)
    _require(path, name)
    return path


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    run_compare(ASSETS / "twist_cylinder.usda", out, methods=("lbs", "dqs", "blend"),
                frames=[0, 12, 24], width=96, supersample=1, progress=False, device="cpu")
    return out / "report.html"


def _flags(profile):
    return ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--disable-dev-shm-usage", f"--user-data-dir={profile}"]


def test_screenshot(report, tmp_path):
    chromium = _tool("chromium")
    shot = tmp_path / "report.png"
    subprocess.run([chromium, *_flags(tmp_path / "profile"), f"--screenshot={shot}",
                    "--window-size=1400,3000", "--hide-scrollbars", report.as_uri()],
                   check=True, capture_output=True, timeout=120)
    img = np.asarray(Image.open(shot).convert("RGB"), dtype=np.float64)
    assert img.shape[:2] == (3000, 1400)
    # Not blank: text, tables and renders leave many non-white pixels with varied colours.
    ink = np.any(img < 200, axis=2)
    assert ink.mean() > 0.02
    assert len(np.unique(img.reshape(-1, 3)[ink.reshape(-1)], axis=0)) > 50
    keep = Path(os.environ.get("DQSKIN_SCREENSHOT",
                               Path(tempfile.gettempdir()) / "report_screenshot.png"))
    shutil.copyfile(shot, keep)
    print(f"report screenshot: {keep}")


def test_images_decode_and_nothing_fails(report, tmp_path):
    chromium, chromedriver = _tool("chromium"), _tool("chromedriver")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        _require(False, "selenium")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in _flags(tmp_path / "profile"):
        options.add_argument(flag)
    options.add_argument("--window-size=1400,3000")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(chromedriver), options=options)
    try:
        driver.set_page_load_timeout(60)
        driver.get(report.as_uri())
        assert driver.execute_script("return document.readyState") == "complete"
        images = driver.execute_script(
            "return Array.from(document.images).map(i => [i.currentSrc.slice(0, 22), "
            "i.complete, i.naturalWidth, i.naturalHeight])")
        # frame plots, close-up, sweeps, and 3 views for each worst frame
        assert len(images) >= 6
        for src, complete, w, h in images:
            assert src == "data:image/png;base64,"
            assert complete and w > 0 and h > 0
        assert driver.execute_script(
            "return Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)")
        # Nothing was fetched but the page itself.
        fetched = driver.execute_script(
            "return performance.getEntriesByType('resource').map(e => e.name)")
        assert [u for u in fetched if not u.startswith("data:")] == []
        errors = [e for e in driver.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
        assert errors == []
        assert "Skinning comparison" in driver.title + driver.page_source
    finally:
        driver.quit()
