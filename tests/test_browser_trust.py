"""The workbench's pictures in a real browser (Playwright driving Debian's Chromium; issue 30 part 4):
the trust map of the calibration shown in "Result" (a saved one, when opened or just saved) and the
drift of its checks in the history view. Screenshots kept in ``out/``. It fails — never skips — when
Chromium is missing.
"""

from __future__ import annotations

import httpx
import pytest
from conftest import chromium_page
from helpers import PAPER, keep_screenshot, records, workbench_thread

PAIRS = records(PAPER / "calibration_points.csv")
CHECK = records(PAPER / "check_points.csv")
TOKEN = "s3cret-token"

# the <img>'s decoded size and whether it is painted (an image that failed to load has no natural size)
IMG_JS = """(sel) => { const i = document.querySelector(sel);
  return [i.complete, i.naturalWidth, i.naturalHeight, i.getBoundingClientRect().width]; }"""


@pytest.fixture
def server(tmp_path, request):
    token = getattr(request, "param", None)
    with workbench_thread(tmp_path / "data", token) as url:
        yield url, token


def stored(base: str, token: str | None, checks: bool) -> int:
    """A calibration "cell" with two versions and, when ``checks``, three verifications (the last of
    version 2); its id."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    with httpx.Client(base_url=base, headers=headers, timeout=60) as c:
        body = {"pairs": PAIRS, "check": CHECK, "model": "homography", "optimizer": "lm"}
        r = c.post("/api/calibrations", json={"name": "cell", **body})
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        fresh = PAIRS[::2]
        if checks:
            for pairs in (fresh, [dict(p, x=p["x"] + 0.5) for p in fresh]):
                r = c.post(f"/api/calibrations/{cid}/verify", json={"pairs": pairs, "tolerance_mm": 0.3})
                assert r.status_code == 200, r.text
        refit = {**body, "pairs": [p for p in PAIRS if p["id"] != PAIRS[0]["id"]]}
        r = c.post(f"/api/calibrations/{cid}/versions", json=refit, headers={"X-Requested-With": "t"})
        assert r.status_code == 201, r.text
        if checks:
            inside = fresh[1:]  # pair 0 (left out of version 2) is outside its region
            r = c.post(f"/api/calibrations/{cid}/verify", json={"pairs": inside, "tolerance_mm": 0.3})
            assert r.status_code == 200, r.text
    return cid


def backdate(data_dir, cid: int) -> None:
    """Spread the checks of ``cid`` over days, as a cell's would be (the test makes them within a
    second): the verifications on May 1, 3 and 6, version 2 made on May 4."""
    import json
    import sqlite3

    from eyetohand.server.storage import DB_NAME

    days = ["2024-05-01T08:00:00.000+00:00", "2024-05-03T08:00:00.000+00:00", "2024-05-06T08:00:00.000+00:00"]
    with sqlite3.connect(data_dir / DB_NAME) as db:
        db.execute("DROP TRIGGER versions_immutable")  # forging history: the store's trigger refuses it
        rows = db.execute(
            "SELECT rowid, entry_json FROM verifications WHERE calibration_id = ? ORDER BY rowid", (cid,)
        )
        for (rowid, entry), day in zip(rows.fetchall(), days, strict=True):
            entry = json.dumps({**json.loads(entry), "utc": day[:19] + "+00:00"})
            db.execute(
                "UPDATE verifications SET utc = ?, entry_json = ? WHERE rowid = ?", (day, entry, rowid)
            )
        for version, made in ((1, "2024-04-30T12:00:00.000+00:00"), (2, "2024-05-04T12:00:00.000+00:00")):
            db.execute(
                "UPDATE versions SET created_utc = ? WHERE calibration_id = ? AND version = ?",
                (made, cid, version),
            )


@pytest.mark.long
def test_trust_map_in_result_and_drift_in_history(server, tmp_path):
    from playwright.sync_api import expect

    base, _ = server
    backdate(tmp_path / "data", stored(base, None, checks=True))
    with chromium_page(1280, 900, allowed_console=r"status of (409|422)") as page:
        page.goto(base + "/")
        expect(page.locator("#saved-table tbody tr")).to_have_count(1)
        row = page.locator("#saved-table tbody tr").first
        row.locator("button", has_text="open").click()
        expect(page.locator("#sec-result")).to_be_visible()
        expect(page.locator("#trust-fig")).to_be_visible(timeout=30_000)
        expect(page.locator("#trust-state")).to_have_text("“cell” v2")
        expect(page.locator("#trust-legend")).to_contain_text("σ (sigma_mm): the predicted RMS distance")
        complete, nat_w, nat_h, shown_w = page.evaluate(IMG_JS, "#trust-map")
        assert complete and nat_w == 800 and nat_h == 600 and 700 < shown_w <= 800, (nat_w, nat_h, shown_w)
        assert "The star marks where one more training pair helps most" in page.get_attribute(
            "#trust-map", "alt"
        )
        shot = tmp_path / "trust_map_result.png"
        page.locator("#trust-block").screenshot(path=str(shot))
        keep_screenshot(shot)

        # an earlier version from the history: its own trust map
        row.locator("button", has_text="history").click()
        expect(page.locator("#versions-block")).to_be_visible()
        page.locator("#versions-table tbody tr", has_text="1").last.locator("button", has_text="open").click()
        expect(page.locator("#trust-state")).to_have_text("“cell” v1", timeout=30_000)

        # the history view: the versions, the checks and their drift
        expect(page.locator("#checks-block")).to_be_visible()
        expect(page.locator("#checks-table tbody tr")).to_have_count(3)
        expect(page.locator("#drift-fig")).to_be_visible(timeout=30_000)
        assert page.get_attribute("#drift-img", "data-checks") == "3"
        expect(page.locator("#checks-table tbody tr").first).to_contain_text("2024-05-01 08:00:00")
        complete, nat_w, nat_h, shown_w = page.evaluate(IMG_JS, "#drift-img")
        assert complete and nat_w == 800 and nat_h > 300 and shown_w > 700, (nat_w, nat_h, shown_w)
        shot = tmp_path / "drift_history.png"
        page.locator("#checks-block").screenshot(path=str(shot))
        keep_screenshot(shot)

        # an unsaved fit has no trust map until it is saved
        page.set_input_files("#pairs-file", str(PAPER / "calibration_points.csv"))
        expect(page.locator("#pairs-count")).to_contain_text("16 pairs")
        page.evaluate("() => { document.querySelector('#job-status').textContent = 'clicked'; }")
        page.click("#run")
        expect(page.locator("#job-status")).to_have_text("done", timeout=60_000)
        expect(page.locator("#trust-state")).to_have_text("save the fit to see its trust map")
        expect(page.locator("#trust-fig")).to_be_hidden()
        page.fill("#save-name", "fresh")
        page.click("#save-new")
        expect(page.locator("#trust-state")).to_have_text("“fresh” v1", timeout=30_000)
        expect(page.locator("#trust-fig")).to_be_visible()
        # a calibration without checks: the history view asks for no drift (no 404 in the console)
        page.locator("#saved-table tbody tr", has_text="fresh").locator("button", has_text="history").click()
        expect(page.locator("#checks-name")).to_contain_text("none yet")
        expect(page.locator("#drift-fig")).to_be_hidden()
        assert not page.problems, page.problems


@pytest.mark.parametrize("server", [TOKEN], indirect=True)
def test_pictures_are_fetched_with_the_token(server):
    from playwright.sync_api import expect

    base, token = server
    stored(base, token, checks=True)
    with chromium_page(1280, 900, allowed_console=r"status of 401") as page:
        page.goto(base + "/")
        expect(page.locator("#token-box")).to_be_visible()
        page.fill("#token", token)
        page.locator("#token").dispatch_event("change")
        expect(page.locator("#saved-table tbody tr")).to_have_count(1)
        row = page.locator("#saved-table tbody tr").first
        row.locator("button", has_text="open").click()
        expect(page.locator("#trust-fig")).to_be_visible(timeout=30_000)
        assert page.evaluate(IMG_JS, "#trust-map")[1] == 800
        row.locator("button", has_text="checks").click()
        expect(page.locator("#drift-fig")).to_be_visible(timeout=30_000)
        assert page.evaluate(IMG_JS, "#drift-img")[1] == 800
        assert not page.problems, page.problems
