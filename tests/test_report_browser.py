"""The compare report in a real browser: headless Chromium renders it from disk with no network,
every embedded image decodes, nothing fails to load, and the page is not blank; the animated
viewer (software WebGL) draws a non-blank canvas, decodes exactly the skinned points, advances
frames, toggles the heat map and logs no error.

Needs the Debian packages ``chromium`` and ``chromium-driver`` and the ``selenium`` Python package:
missing ones fail the test under CI (``CI=true``) and skip it elsewhere. The full-page screenshot
is kept at ``$DQSKIN_SCREENSHOT`` (default ``<tmp>/report_screenshot.png``) for a person to look at,
the viewer's at ``<tmp>/viewer_screenshot.png`` (``$DQSKIN_VIEWER_SCREENSHOT``).
"""

import base64
import io
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import dqskin
from dqskin.report.compare import run_compare
from dqskin.report.viewer import decode

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
    # --enable-unsafe-swiftshader: WebGL on the CPU (SwiftShader) without a GPU
    return ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--disable-dev-shm-usage", "--enable-unsafe-swiftshader", f"--user-data-dir={profile}"]


def _problems(log):
    """Console entries that are errors or warnings, less SwiftShader's performance notes on
    reading pixels back (the test's own canvas reads)."""
    return [e for e in log if e["level"] in ("SEVERE", "WARNING")
            and "GL Driver Message (OpenGL, Performance" not in e["message"]]


def _driver(tmp_path, size="1400,3000"):
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
    options.add_argument(f"--window-size={size}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(chromedriver), options=options)


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
    driver = _driver(tmp_path)
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
        assert _problems(driver.get_log("browser")) == []
        assert "Skinning comparison" in driver.title + driver.page_source
    finally:
        driver.quit()


def _canvas(driver):
    """The viewer's canvas as an (H, W, 3) float array (its drawing buffer is preserved)."""
    url = driver.execute_script("return window.dqskinViewer.canvas.toDataURL('image/png')")
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)


def _wait(driver, script, timeout=60):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for: {script}")


def _embedded(report):
    text = report.read_text(encoding="utf-8")
    config = json.loads(re.search(r'id="dqv-config">(.*?)</script>', text, re.S).group(1))
    blob = base64.b64decode(re.search(r'id="dqv-data">(.*?)</script>', text, re.S).group(1))
    return config, blob


def test_viewer_plays_in_webgl(report, tmp_path):
    driver = _driver(tmp_path, "1400,1000")
    try:
        driver.set_page_load_timeout(60)
        driver.get(report.as_uri())
        state = _wait(driver, "const v = window.dqskinViewer; "
                              "return v && (v.ready || v.error) && [v.ready, v.error]")
        assert state == [True, None]
        api = "window.dqskinViewer"
        config, blob = _embedded(report)
        frames = driver.execute_script(f"return {api}.frameCount")
        assert frames == len(config["times"]) == 25  # every frame of the twist rig

        # The browser decodes what was skinned: the scene skinned independently of the report
        # (skeleton space, bind points), within half a quantization step.
        scene = dqskin.load(ASSETS / "twist_cylinder.usda")
        meta = config["meta"]
        driver.execute_script(f"{api}.setFrame(20)")
        for m, method in enumerate(meta["methods"]):
            skinned = scene.skin([config["times"][20]], method, device="cpu", space="skeleton",
                                 blend_shapes=False).points[scene.meshes[0].name][0]
            shown = np.array(driver.execute_script(f"return {api}.positions({m})")).reshape(-1, 3)
            np.testing.assert_allclose(shown, skinned, atol=0.51 * meta["step"] + 1e-6)
        np.testing.assert_allclose(decode(meta, blob)["heat"].max(), meta["heat_max"])

        # Non-blank: many pixels differ from the background, in each method's colour.
        driver.execute_script(f"{api}.setFrame(0)")
        time.sleep(0.3)
        first = _canvas(driver)
        background = np.array([250.0, 250.0, 250.0])
        ink = np.abs(first - background).max(axis=2) > 24
        assert ink.mean() > 0.03
        for color in config["colors"]:  # lit, so compare hues: the dominant channel matches
            rgb = np.array([int(color[i:i + 2], 16) for i in (1, 3, 5)], dtype=np.float64)
            hue = first[ink] / np.maximum(first[ink].sum(axis=1, keepdims=True), 1)
            target = rgb / rgb.sum()
            assert (np.abs(hue - target).max(axis=1) < 0.08).mean() > 0.05, color

        # Frames advance: playback moves the frame index, and the twisted frame looks different.
        driver.execute_script(f"{api}.setPlaying(true)")
        _wait(driver, f"return {api}.frame() !== 0", timeout=20)
        driver.execute_script(f"{api}.setFrame({frames - 1})")
        time.sleep(0.3)
        assert driver.execute_script(f"return {api}.frame()") == frames - 1
        last = _canvas(driver)
        assert np.abs(last - first).max(axis=2).mean() > 1.0

        # The heat map toggles: colours change to the colour map and back.
        driver.execute_script(f"{api}.setHeat(true)")
        time.sleep(0.3)
        assert driver.execute_script(f"return {api}.heat()") is True
        heat = _canvas(driver)
        assert np.abs(heat - last).max(axis=2).mean() > 1.0
        driver.execute_script(f"{api}.setHeat(false)")
        time.sleep(0.3)
        np.testing.assert_allclose(_canvas(driver), last, atol=2)

        # The worst frame is one click away.
        button = driver.find_element("css selector", "#dqv-worst button")
        button.click()
        assert driver.execute_script(f"return {api}.frame()") == driver.execute_script(
            f"return {api}.worstFrame(0)")

        driver.execute_script(f"{api}.setHeat(true); {api}.setRest(true)")
        driver.execute_script("document.getElementById('dqskin-viewer').scrollIntoView()")
        time.sleep(0.3)
        shot = tmp_path / "viewer.png"
        driver.save_screenshot(str(shot))
        keep = Path(os.environ.get("DQSKIN_VIEWER_SCREENSHOT",
                                   Path(tempfile.gettempdir()) / "viewer_screenshot.png"))
        shutil.copyfile(shot, keep)
        print(f"viewer screenshot: {keep}")
        assert _problems(driver.get_log("browser")) == []
    finally:
        driver.quit()


def _share(image, color):
    """Share of the non-background pixels of ``image`` in the hue of ``color`` (#rrggbb)."""
    ink = np.abs(image - 250.0).max(axis=2) > 24
    if not ink.any():
        return 0.0
    rgb = np.array([int(color[i:i + 2], 16) for i in (1, 3, 5)], dtype=np.float64)
    hue = image[ink] / np.maximum(image[ink].sum(axis=1, keepdims=True), 1)
    return float((np.abs(hue - rgb / rgb.sum()).max(axis=1) < 0.08).mean())


def test_viewer_show_hide_and_ab_flip(report, tmp_path):
    """Each method's box hides and shows it (the others close ranks); A/B draws one of two
    methods at a time in the same place, and flip (button or key F) swaps them."""
    driver = _driver(tmp_path, "1400,1000")
    try:
        driver.set_page_load_timeout(60)
        driver.get(report.as_uri())
        assert _wait(driver, "const v = window.dqskinViewer; "
                             "return v && (v.ready || v.error) && [v.ready, v.error]") == [True,
                                                                                          None]
        api = "window.dqskinViewer"
        config, _ = _embedded(report)
        red, blue, purple = config["colors"]  # lbs, dqs, blend
        driver.execute_script(f"{api}.setFrame(20)")
        time.sleep(0.3)
        assert all(_share(_canvas(driver), c) > 0.05 for c in (red, blue, purple))

        # hide DQS by its box in the legend
        driver.find_element("css selector", '#dqv-methods input[data-method="1"]').click()
        time.sleep(0.3)
        assert driver.execute_script(f"return {api}.visible()") == [True, False, True]
        assert driver.execute_script(f"return {api}.shown()") == [0, 2]
        img = _canvas(driver)
        assert _share(img, blue) < 0.01 and _share(img, red) > 0.05 and _share(img, purple) > 0.05
        lbs_x, blend_x = (driver.execute_script(f"return {api}.offset({m})")[0] for m in (0, 2))
        assert lbs_x == pytest.approx(-blend_x) and lbs_x < 0  # the two left close ranks
        driver.execute_script(f"{api}.setVisible(1, true)")

        # A/B between LBS and DQS: one at a time, same place
        driver.execute_script(f"{api}.setAB(true, 0, 1)")
        time.sleep(0.3)
        assert driver.execute_script(f"return {api}.shown()") == [0]
        a = _canvas(driver)
        assert _share(a, red) > 0.3 and _share(a, blue) < 0.01 and _share(a, purple) < 0.01
        driver.find_element("id", "dqv-flip").click()
        time.sleep(0.3)
        assert driver.execute_script(f"return {api}.shown()") == [1]
        b = _canvas(driver)
        assert _share(b, blue) > 0.3 and _share(b, red) < 0.01
        assert driver.execute_script(f"return {api}.offset(0)") == \
            driver.execute_script(f"return {api}.offset(1)") == [0, 0, 0]
        ink_a, ink_b = (np.abs(x - 250.0).max(axis=2) > 24 for x in (a, b))
        assert (ink_a & ink_b).sum() > 0.8 * min(ink_a.sum(), ink_b.sum())  # the same place
        driver.find_element("css selector", "body").send_keys("f")
        time.sleep(0.2)
        assert driver.execute_script(f"return {api}.shown()") == [0]
        driver.execute_script(f"{api}.setAB(false)")
        assert driver.execute_script(f"return {api}.shown()") == [0, 1, 2]
        assert _problems(driver.get_log("browser")) == []
    finally:
        driver.quit()
