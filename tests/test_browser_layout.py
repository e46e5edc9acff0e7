"""The workbench on a plant-floor PC, in a real browser (Playwright driving Debian's Chromium).

- ``/docs``: Swagger UI renders FastAPI's OpenAPI 3.1 document (operations listed, no "Unable to render");
- the saved-calibrations table at 1280×800 and on a 10" touch panel (1024×600): every link and button
  of every row is inside the page's width and is the element a click at its centre lands on;
- long operations show their progress with an estimate of the time left.

Geometric assertions, not reference screenshots: the screenshots are kept in ``out/`` to look at.
It fails — never skips — when Chromium is missing.
"""

from __future__ import annotations

import re

import pytest
from conftest import chromium_page
from helpers import keep_screenshot, workbench_thread


@pytest.fixture
def server(tmp_path):
    with workbench_thread(tmp_path / "data") as url:
        yield url


@pytest.mark.long
def test_api_docs_render_in_the_browser(server, tmp_path):
    from playwright.sync_api import expect

    with chromium_page(1280, 800) as page:
        page.goto(server + "/docs")
        ops = page.locator(".opblock")
        expect(ops.first).to_be_visible(timeout=20_000)
        assert ops.count() > 10, ops.count()
        assert "Unable to render" not in page.content()
        assert page.locator(
            ".opblock-summary-path", has_text="/api/calibrations/{cal_id}/image-to-robot"
        ).count()
        shot = tmp_path / "api_docs.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot)
        assert not page.problems, page.problems


def _store_calibrations(url: str, names: list[str]) -> None:
    """Calibrations fitted on the paper's pairs, stored through the API (the table the page lists)."""
    import httpx
    from helpers import PAPER

    from eyetohand import load_pairs

    pairs = load_pairs(PAPER / "calibration_points.csv")
    check = load_pairs(PAPER / "check_points.csv")

    def rows(p):
        return [
            {"id": i, "u": a[0], "v": a[1], "x": b[0], "y": b[1], "z": b[2]}
            for i, a, b in zip(p.ids, p.uv_px, p.xyz_mm, strict=True)
        ]

    for name in names:
        body = {"name": name, "pairs": rows(pairs), "check": rows(check), "model": "homography"}
        r = httpx.post(url + "/api/calibrations", json=body, timeout=60)
        assert r.status_code == 201, r.text


# every link and button of the saved table: its box, whether it lies inside the window's width, and whether
# a click at its centre lands on it (nothing over it, not clipped by the table's scroll box)
REACHABLE_JS = """() => [...document.querySelectorAll('#saved-table tbody a, #saved-table tbody button')]
.map((e) => {
  // scroll the page to it vertically only: a link found by scrolling the table's box sideways is one
  // an operator does not see
  document.querySelectorAll('.scroll').forEach((s) => { s.scrollLeft = 0; });
  const r0 = e.getBoundingClientRect();
  window.scrollBy(0, r0.top - window.innerHeight / 2);
  const r = e.getBoundingClientRect();
  const x = r.left + r.width / 2, y = r.top + r.height / 2;
  const hit = document.elementFromPoint(x, y);
  return {text: e.textContent, left: r.left, right: r.right, top: r.top, bottom: r.bottom,
          width: r.width, height: r.height, on: hit === e || e.contains(hit),
          vw: document.documentElement.clientWidth, vh: document.documentElement.clientHeight};
})"""


@pytest.mark.parametrize("size", [(1280, 800), (1024, 600)], ids=["1280x800", "touch-1024x600"])
def test_saved_calibrations_reachable(server, tmp_path, size):
    from playwright.sync_api import expect

    _store_calibrations(server, ["cell 3 camera, line A", "bench"])
    w, h = size
    with chromium_page(w, h) as page:
        page.goto(server + "/")
        expect(page.locator("#saved-table tbody tr")).to_have_count(2)
        page.locator("#sec-saved").scroll_into_view_if_needed()
        shot = tmp_path / f"saved_{w}x{h}.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot)
        boxes = page.evaluate(REACHABLE_JS)
        assert len(boxes) == 2 * 5, boxes  # open, history, checks, export JSON, delete per row
        for b in boxes:
            assert 0 <= b["left"] and b["right"] <= b["vw"], b  # inside the window, no sideways scroll
            assert 0 <= b["top"] and b["bottom"] <= b["vh"], b
            assert b["on"], b  # the click lands on it
            assert b["height"] >= 24 and b["width"] >= 24, b  # a finger can hit it on a touch panel
        widths = page.evaluate(
            "() => [document.documentElement.scrollWidth, document.documentElement.clientWidth]"
        )
        assert widths[0] <= widths[1], widths
        # clicking one works: the history opens
        page.locator("#saved-table tbody tr").first.locator("button", has_text="history").click()
        expect(page.locator("#versions-block")).to_be_visible()
        assert not page.problems, page.problems


@pytest.mark.long
def test_long_operations_show_the_time_left(server, tmp_path):
    """A PSO fit and a comparison: a progress bar and an estimate of the time left while they run."""
    from helpers import PAPER
    from playwright.sync_api import expect

    with chromium_page(1024, 600) as page:
        page.goto(server + "/")
        expect(page.locator("#server-status")).to_contain_text("server v")
        page.set_input_files("#pairs-file", str(PAPER / "calibration_points.csv"))
        page.set_input_files("#check-file", str(PAPER / "check_points.csv"))
        expect(page.locator("#check-count")).to_contain_text("9 pairs")
        page.select_option("#model", "paper")
        page.select_option("#optimizer", "hybrid-pso")
        page.fill("#particles", "1000")  # about 3 s on a 2-core machine: the page polls every 150 ms
        page.fill("#iterations", "500")
        page.click("#run")
        eta = page.locator("#job-eta")
        expect(eta).to_have_text(
            re.compile(r"^about \d+ s \(iterations: (?!500\b)\d+ of 500\)$"), timeout=60_000
        )
        expect(page.locator("#job-progress")).to_be_visible()
        value = page.evaluate("() => document.querySelector('#job-progress').value")
        assert 0 < value <= 500, value
        page.locator("#sec-progress").scroll_into_view_if_needed()
        shot = tmp_path / "progress_pso.png"
        page.screenshot(path=str(shot))
        keep_screenshot(shot)
        expect(page.locator("#job-status")).to_have_text("done", timeout=120_000)
        expect(page.locator("#job-progress")).to_be_hidden()
        expect(eta).to_have_text("–")

        page.click("#compare-go")
        expect(page.locator("#compare-state")).to_have_text(
            re.compile(r"time left (about \d+ s|estimating…) \(fits: \d+ of \d+\)"), timeout=60_000
        )
        expect(page.locator("#compare-table")).to_be_visible(timeout=180_000)
        expect(page.locator("#compare-state")).to_have_text(re.compile(r"^done \(\d+\.\d s\)$"))
        assert not page.problems, page.problems
