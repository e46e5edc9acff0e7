"""The plant page (/plant) in a real browser (Playwright driving Debian's Chromium): it lists the
store's calibrations with their version in force and last check, makes an earlier version current with
the ETag it showed (If-Match), and refuses — in words on the page — when someone changed the
calibration meanwhile. Fails, never skips, when Chromium is missing."""

from __future__ import annotations

import httpx
import pytest
from conftest import chromium_page
from helpers import PAPER, keep_screenshot, records, workbench_thread

PAIRS = records(PAPER / "calibration_points.csv")


@pytest.mark.long
def test_plant_page_makes_a_version_current_with_if_match(tmp_path, paper_pairs):
    from eyetohand import calibrate
    from eyetohand.core import PointPairs

    pairs, _ = paper_pairs
    shifted = PointPairs(pairs.uv_px, pairs.xyz_mm + [5.0, 0.0, 0.0], pairs.ids)
    cals = [calibrate(p, model="homography", optimizer="lm", loo=False).to_dict() for p in (pairs, shifted)]
    with workbench_thread(tmp_path / "data") as url, httpx.Client(base_url=url, timeout=30) as c:
        for cal in cals:
            c.post("/api/calibrations/import", json={"name": "press 4", "calibration": cal})
        r = c.post("/api/calibrations/1/verify", json={"pairs": PAIRS[::2], "tolerance_mm": 1.0})
        assert r.status_code == 200
        with chromium_page(1280, 800, allowed_console=r"status of 412") as page:
            page.goto(url + "/plant")
            page.wait_for_selector("#plant tr")
            row = page.locator("#plant tr").first
            assert "press 4" in row.inner_text() and "version 2" in row.inner_text()
            assert "failed (v2)" in row.inner_text()  # the shifted version checked against unshifted pairs
            row.locator("input").fill("1")
            row.locator("button").click()
            page.wait_for_function("document.querySelector('#plant tr').innerText.includes('version 3')")
            page.wait_for_function("document.querySelector('#audit').innerText.includes('rollback')")
            assert c.get("/api/calibrations/1").json()["current_version"] == 3
            # someone else changes it while the page still holds the old ETag (its 5 s refresh stopped)
            page.evaluate("() => { for (let i = 1; i < 10000; i++) clearInterval(i); }")
            c.post("/api/calibrations/import", json={"name": "press 4", "calibration": cals[1]})
            row.locator("input").fill("2")
            row.locator("button").click()
            page.wait_for_selector("#global-err:not([hidden])")
            assert "If-Match" in page.inner_text("#global-err")
            # one calibration's trail, as the workbench's link opens it
            c.post("/api/calibrations/import", json={"name": "welder 2", "calibration": cals[0]})
            page.goto(url + "/plant?calibration=2")
            page.wait_for_function("document.querySelector('#audit').innerText.includes('welder 2')")
            assert "press 4" not in page.inner_text("#audit") and "(calibration 2)" in page.inner_text(
                "#audit-of"
            )
            shot = tmp_path / "plant.png"
            page.screenshot(path=str(shot), full_page=True)
            keep_screenshot(shot)
            assert page.problems == []
        assert (
            c.get("/api/calibrations/1").json()["current_version"] == 4
        )  # the refused click changed nothing
