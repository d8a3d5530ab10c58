"""The compare report page in a real browser (headless Chromium through Selenium): every image decodes, no console
error, the flip control switches the image shown, the verdict agrees with report.json."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from layerbvh_mitsuba.cli import main
from layerbvh_mitsuba.repo import ROOT, SCENES

CHROMIUM, DRIVER = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")


@pytest.fixture(scope="module")
def browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (scripts/bootstrap.sh "
                                    "installs it with the test extra)")
    if not (CHROMIUM and DRIVER):
        pytest.skip("chromium and chromedriver are not installed (scripts/bootstrap.sh installs Debian's chromium and "
                    "chromium-driver when run as root; install them to run this test)")
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service
    opts = Options()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,2300"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    d = webdriver.Chrome(service=Service(DRIVER), options=opts)
    yield d
    d.quit()


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    out = tmp_path_factory.mktemp("page") / "cmp"
    assert main(["compare", str(SCENES / "bunny_box.xml"), "--res", "64", "64", "--spp", "4", "--out", str(out),
                 "--no-progress"]) == 0
    return out


def test_page_in_a_browser(browser, page):
    browser.get((page / "index.html").as_uri())
    images = browser.execute_script("return Array.from(document.images).map(i => [i.getAttribute('src'), "
                                    "i.complete, i.naturalWidth])")
    assert images and all(done and width > 0 for _, done, width in images), images
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors

    view = browser.find_element("id", "view")
    shown = (lambda: browser.execute_script(
        "const c = document.getElementById('view'); return [c.dataset.showing, "
        "Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data.slice(0, 4096))]"))
    before, pixels_stock = shown()
    view.click()
    after, pixels_ours = shown()
    assert (before, after) == ("stock", "ours"), "a click flips from stock to ours"
    assert browser.find_element("id", "showing").text == "ours"
    # Same-seed images differ by float noise only, so the canvas is redrawn from the other image:
    # compare what the page says it draws with the data it holds.
    stock_first = browser.execute_script("window.layerbvhSetMode('stock'); return document.getElementById('view')"
                                         ".getContext('2d').getImageData(0, 0, 1, 1).data.join(',')")
    assert stock_first == ",".join(map(str, pixels_stock[:4]))
    browser.find_element("css selector", "button[data-mode='split']").click()
    assert view.get_attribute("data-showing") == "split"

    rep = json.loads((page / "report.json").read_text())
    verdict = browser.find_element("id", "verdict")
    passed = verdict.get_attribute("data-passed") == "true"
    assert passed == rep["verdict"]["passed"]
    assert verdict.text.startswith("matches stock" if passed else "differs from stock")
    if os.environ.get("LAYERBVH_UPDATE_DOCS"):  # the README's screenshot (scripts/ docs refresh)
        browser.save_screenshot(str(ROOT / "docs" / "report_page.png"))


def test_flip_draws_the_other_image(browser, tmp_path):
    """A flip must redraw the canvas from the other image, not only change its label: with ours
    visibly brighter than stock (x1.5, below white), every drawn pixel must get brighter on the
    flip to ours and come back on the flip to stock."""
    import numpy as np

    from layerbvh_mitsuba.ab.report import write_report
    h, w = 24, 32
    stock = np.dstack([np.tile(np.linspace(0.05, 0.5, w, dtype=np.float32), (h, 1))] * 3)
    out = tmp_path / "rep"
    write_report(out, stock, stock * 1.5, {"scene": "synthetic.xml", "spp": 1, "resolution": [w, h]})
    browser.get((out / "index.html").as_uri())
    drawn = (lambda: np.array(browser.execute_script(
        "const c = document.getElementById('view'); return Array.from(c.getContext('2d')"
        ".getImageData(0, 0, c.width, c.height).data)")).reshape(-1, 4)[:, :3])
    view = browser.find_element("id", "view")
    first = drawn()
    view.click()
    assert view.get_attribute("data-showing") == "ours"
    flipped = drawn()
    assert (flipped > first).mean() > 0.99, "the flip to ours drew the brighter image"
    view.click()
    assert np.array_equal(drawn(), first), "and back to stock"


def test_summary_page_of_the_pytest_plugin(browser, tmp_path):
    """The pytest plugin's summary (DIR/index.html) in a browser: a row per check, the failing
    one linked to its compare page, whose thumbnail decodes."""
    import numpy as np

    from layerbvh_mitsuba.pytest_plugin import summary_html
    from layerbvh_mitsuba.ab.report import write_report
    stock = np.full((16, 16, 3), 0.3, np.float32)
    write_report(tmp_path / "t_fail", stock, stock * 1.5, {"scene": "s.xml", "spp": 1, "resolution": [16, 16]})
    base = {"scene": "s.xml", "traversal": "auto", "stock_s": 0.1, "stock_cached": False, "ours_s": 0.2}
    records = [{**base, "test": "t.py::test_ok", "label": "same paths", "passed": True, "summary": "same seed",
                "page": None},
               {**base, "test": "t.py::test_fail", "label": "differs beyond noise", "passed": False,
                "summary": "16 of 1024 pixels differ", "page": "t_fail/index.html"}]
    (tmp_path / "index.html").write_text(summary_html(records))
    browser.get((tmp_path / "index.html").as_uri())
    rows = browser.execute_script("return Array.from(document.querySelectorAll('#checks tr')).slice(1)"
                                  ".map(r => [r.className, r.cells[0].textContent])")
    assert rows == [["pass", "t.py::test_ok"], ["fail", "t.py::test_fail"]]
    images = browser.execute_script("return Array.from(document.images).map(i => [i.complete, i.naturalWidth])")
    assert images == [[True, 16]]
    assert browser.find_element("css selector", "h1").text == "layerbvh checks: 1 passed, 1 failed"


def test_a_share_of_the_time_split_below_zero_is_not_shown_as_a_time():
    """The split's shares are differences of two timings (on media scenes our loop with Embree ran
    as fast as stock: "loop -0.09 s" was printed)."""
    from layerbvh_mitsuba.ab.page import split_share
    assert split_share(0.25) == "0.25 s"
    assert split_share(-0.09) == "~0 s (-0.09 s: within timing noise)"
