"""The workbench's audit trail of one calibration in a real browser (Debian's Chromium, headless): the
history block lists who changed it, when and why, newest first, and a rollback made on the page is
there at once under the page's user."""

from __future__ import annotations

import json

from conftest import chromium_page
from helpers import workbench_thread
from test_diff import FLAT, moved_cell

from eyetohand import calibrate
from eyetohand.server.audit import acting_as
from eyetohand.server.storage import Store
from eyetohand.sim import simulate


def _cal_json(cell, seed: int) -> tuple[dict, list]:
    sim = simulate(cell, "grid:5x5", seed=seed)
    cal = calibrate(sim.pairs, model="homography", check=sim.check, loo=False)
    return json.loads(cal.to_json()), sim.pairs.to_records()


def _rows(page) -> list[list[str]]:
    return page.evaluate(
        "() => [...document.querySelectorAll('#audit-table tbody tr')]"
        ".map(tr => [...tr.children].map(c => c.textContent))"
    )


def test_the_history_shows_who_changed_the_calibration(tmp_path):
    data = tmp_path / "data"
    store = Store(data, create=True)
    with acting_as("alice"):
        rec = store.create("line 3", {}, *_cal_json(FLAT, 91), None, note="commissioned")
    with acting_as("bob"):
        store.add_version(rec.id, {}, *_cal_json(moved_cell(FLAT), 93), None, "after the bump")
    store.close()
    with workbench_thread(data) as url, chromium_page(1400, 1000) as page:
        page.goto(url)
        page.locator("#saved-table button", has_text="history").first.click()
        page.wait_for_function("() => document.querySelectorAll('#audit-table tbody tr').length >= 2")
        rows = _rows(page)
        # newest first: bob's new version (1 -> 2), then alice's creation (-> 1)
        assert [r[1:5] for r in rows] == [["bob", "new version", "1", "2"], ["alice", "create", "", "1"]], (
            rows
        )
        assert rows[0][5] == "after the bump" and rows[1][5] == "commissioned"
        page.locator("#versions-table button", has_text="roll back to this").first.click()
        page.wait_for_function("() => document.querySelectorAll('#audit-table tbody tr').length >= 3")
        top = _rows(page)[0]
        assert top[1:5] == ["local", "rollback", "2", "3"], top
        assert page.is_hidden("#audit-err")
