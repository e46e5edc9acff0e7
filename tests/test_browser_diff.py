"""The workbench's version comparison in a real browser (Debian's Chromium, headless): a calibration
with two stored versions — the second from a cell whose camera moved — compared through the control
in the history block; the verdict line is the API's and its map loads."""

from __future__ import annotations

import json

import pytest
from conftest import chromium_page
from helpers import workbench_thread
from test_diff import FLAT, moved_cell

from eyetohand import calibrate
from eyetohand.server.storage import Store
from eyetohand.sim import simulate


def _cal_json(cell, seed: int) -> dict:
    sim = simulate(cell, "grid:5x5", seed=seed)
    return json.loads(calibrate(sim.pairs, model="homography", check=sim.check, loo=False).to_json())


@pytest.mark.long
def test_compare_two_versions_in_the_workbench(tmp_path):
    data = tmp_path / "data"
    store = Store(data, create=True)
    rec = store.create("line 3", {}, _cal_json(FLAT, 91), [], None)
    store.add_version(rec.id, {}, _cal_json(moved_cell(FLAT), 93), [], None, "after the bump")
    store.close()
    with workbench_thread(data) as url, chromium_page(1400, 1000) as page:
        page.goto(url)
        page.locator("#saved-table button", has_text="history").first.click()
        page.wait_for_selector("#diff-go")
        assert page.input_value("#diff-a") == "1" and page.input_value("#diff-b") == "2"
        page.click("#diff-go")
        page.wait_for_selector("#diff-fig:not([hidden])", timeout=60_000)
        text = page.inner_text("#diff-verdict")
        assert text.startswith("moved:"), text
        assert "rms" in text and "median ratio" in text
        assert page.evaluate("() => document.querySelector('#diff-img').naturalWidth") > 100
        # the same version against itself: nothing moved
        page.select_option("#diff-a", "2")
        page.click("#diff-go")
        page.wait_for_function(
            "() => !document.querySelector('#diff-verdict').hidden"
            " || !document.querySelector('#diff-err').hidden",
            timeout=60_000,
        )
        assert page.inner_text("#diff-verdict").startswith("consistent:")
        assert page.is_hidden("#diff-err")
