"""The report page in a real browser: Debian's headless Chromium driven by Selenium.

A tiny report (synthetic 32x32 EXRs: MC and two methods at 4 and 16 spp, a reference, an
alpha map; nothing rendered) is opened through file://. Checked: no console errors, every
<img> and canvas loaded and drawn, the page's tone map equals jaxden.report.tonemap, the A/B
slider, the B dropdown, the exposure and a wheel zoom change what is drawn (zoom in every
view of the scene together), and a screenshot is not blank.

Needs ``selenium`` (the test extra) and ``apt-get install chromium chromium-driver``; skipped
with the reason otherwise.
"""

from __future__ import annotations

import base64
import io
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from jaxden.io.exr import write_image

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
pytestmark = pytest.mark.skipif(
    not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()),
    reason="needs Debian's chromium and chromium-driver (apt-get install -y chromium "
           "chromium-driver)")
webdriver = pytest.importorskip("selenium.webdriver",
                                reason="needs selenium (pip install 'jaxden[test]')")
pytest.importorskip("PIL.Image", reason="needs Pillow (a matplotlib dependency)")
SIZE = 32


def write_tiny_results(root: Path) -> Path:
    """scene/reference.exr, scene/spp{4,16}[.blur|.mix].exr, scene/spp16.mix.alpha.exr."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    reference = np.stack([0.1 + 0.9 * x, 0.1 + 0.6 * y, 0.2 + 0.3 * x * y], -1)
    reference[8:14, 8:20] = 5.0
    folder = root / "tiny"
    folder.mkdir(parents=True)
    write_image(folder / "reference.exr", reference)
    for spp in (4, 16):
        noise = rng.normal(size=reference.shape) * reference / np.sqrt(spp)
        write_image(folder / f"spp{spp}.exr", reference + noise)
        write_image(folder / f"spp{spp}.blur.exr", 0.9 * reference + 0.1 * noise)
        write_image(folder / f"spp{spp}.mix.exr", reference + 0.4 * noise)
    write_image(folder / "spp16.mix.alpha.exr", np.clip(x, 0, 1)[..., None])
    return folder


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    from jaxden.report import build_report

    root = tmp_path_factory.mktemp("browser")
    write_tiny_results(root)
    return build_report(root, root / "report.html")


@pytest.fixture(scope="module")
def driver(report):
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--window-size=1280,1800", "--force-device-scale-factor=1",
                 "--disable-extensions", "--no-first-run"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    browser = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        browser.get(report.resolve().as_uri())
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            state = browser.execute_script("return document.documentElement.dataset.ready")
            if state:
                break
            time.sleep(0.05)
        assert state == "true", browser.find_element("css selector", ".status").text
        yield browser
    finally:
        browser.quit()


def decode_png(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGBA"))


def canvas_pixels(driver, selector: str, index: int = 0) -> np.ndarray:
    """The RGBA pixels (H, W, 4) drawn in the ``index``-th canvas matching ``selector``
    (passed as a PNG: much faster than a JSON array of every byte)."""
    url = driver.execute_script(
        "return document.querySelectorAll(arguments[0])[arguments[1]].toDataURL('image/png')",
        selector, index)
    return decode_png(base64.b64decode(url.split(",", 1)[1]))


COMPARE = 'canvas[data-role="compare"]'
PANEL = 'canvas[data-layer="image"][data-method="mix"]'


def test_no_console_errors(driver):
    severe = [entry for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]
    assert not severe, severe


def test_every_image_and_canvas_is_loaded_and_drawn(driver):
    images = driver.execute_script(
        "return Array.from(document.images).map(i => [i.complete, i.naturalWidth, "
        "i.naturalHeight, i.alt])")
    assert images and all(done and w > 0 and h > 0 for done, w, h, _ in images), images
    canvases = driver.execute_script(
        "return Array.from(document.querySelectorAll('canvas')).map(c => [c.width, c.height])")
    # compare + 4 images + 3 relse + 3 FLIP + 1 alpha, and 3 colour bars
    assert len(canvases) == 15 and all(w > 0 and h > 0 for w, h in canvases)
    for index in range(len(canvases)):
        pixels = canvas_pixels(driver, "canvas", index)
        assert pixels[..., :3].std() > 0, f"canvas {index} is blank"


def test_page_tone_map_equals_pythons(driver, report):
    from jaxden.io.exr import read_image
    from jaxden.report.tonemap import auto_stops, tonemap

    reference = read_image(report.parent / "tiny" / "reference.exr")
    stops = driver.execute_script("return jaxdenReport.views[0].state.stops")
    assert stops == auto_stops(reference)
    page = np.asarray(driver.execute_script("return jaxdenReport.pixels(0, 'reference')"))
    page = page.reshape(SIZE, SIZE, 4)
    expected = tonemap(reference.astype(np.float16).astype(np.float32), stops)
    assert np.abs(page[..., :3].astype(int) - expected).max() <= 1
    assert (page[..., 3] == 255).all()


def test_the_slider_moves_the_split(driver):
    from selenium.webdriver.common.keys import Keys

    before = canvas_pixels(driver, COMPARE)
    shot_before = driver.find_element("css selector", COMPARE).screenshot_as_png
    slider = driver.find_element("css selector", 'input[data-control="split"]')
    slider.send_keys(Keys.HOME)  # split at the left edge: all B
    after = canvas_pixels(driver, COMPARE)
    assert driver.execute_script("return jaxdenReport.views[0].state.split") == 0
    assert not np.array_equal(before, after)
    assert driver.find_element("css selector", COMPARE).screenshot_as_png != shot_before
    slider.send_keys(Keys.END)  # all A
    assert not np.array_equal(after, canvas_pixels(driver, COMPARE))


def test_dropdowns_exposure_and_zoom_redraw(driver):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
    from selenium.webdriver.support.ui import Select

    before = canvas_pixels(driver, COMPARE)
    Select(driver.find_element("css selector", 'select[data-control="a"]')
           ).select_by_value("reference")  # the slider is at the right end: all A
    assert not np.array_equal(before, canvas_pixels(driver, COMPARE))
    assert driver.find_element("css selector", '[data-out="a"]').text == "A: reference"

    panel = canvas_pixels(driver, PANEL)
    driver.execute_script("const s = document.querySelector('input[data-control=\"stops\"]');"
                          "s.value = Number(s.value) - 2; s.dispatchEvent(new Event('input'));")
    darker = canvas_pixels(driver, PANEL)
    assert darker[..., :3].mean() < panel[..., :3].mean()

    other = canvas_pixels(driver, 'canvas[data-layer="flip"][data-method="mc"]')
    element = driver.find_element("css selector", PANEL)
    ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(element), 0, -400
                                            ).perform()
    assert driver.execute_script("return jaxdenReport.views[0].zoom") > 1.5
    assert not np.array_equal(darker, canvas_pixels(driver, PANEL))
    # the same zoom in another view of the scene
    assert not np.array_equal(other,
                              canvas_pixels(driver, 'canvas[data-layer="flip"][data-method="mc"]'))


def test_screenshot_is_not_blank(driver, tmp_path):
    png = driver.get_screenshot_as_png()
    (tmp_path / "report.png").write_bytes(png)
    pixels = decode_png(png)[..., :3].astype(np.float64)
    assert pixels.shape[0] > 500 and pixels.shape[1] > 500
    assert pixels.var() > 0
