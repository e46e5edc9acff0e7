"""The workbench's signatures in a real browser (Debian's Chromium, headless) against a real server
(issue 40, k40's signing): the history lists who signed each version and when; under
``--require-signed`` the version in force says it waits for a signature in the server's own words (the
same words the mapping route refuses with); a "sign" button, shown only when the server has a signing
key, signs with the page's token: an operator's token gets the 403 in the server's words, a signer's
signs, and the page then maps with the version."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import pytest
from conftest import chromium_page
from helpers import keep_screenshot, workbench_thread
from test_diff import FLAT, moved_cell

from eyetohand import calibrate
from eyetohand.core import Role, TokenTable
from eyetohand.server.audit import acting_as
from eyetohand.server.signatures import SigningPolicy
from eyetohand.server.storage import Store
from eyetohand.sim import simulate

KEY = b"s" * 32
TOKENS = {"otto": "operator-token-1", "sam": "signer-token-1"}
ROLES = {"otto": Role.OPERATOR, "sam": Role.SIGNER}


def _cal_json(cell, seed: int) -> tuple[dict, list]:
    sim = simulate(cell, "grid:5x5", seed=seed)
    cal = calibrate(sim.pairs, model="homography", check=sim.check, loo=False)
    return json.loads(cal.to_json()), sim.pairs.to_records()


def _post(url: str, token: str, body: dict | None = None) -> tuple[int, dict]:
    """The server's answer to a POST, read by the standard library (not the page)."""
    data = json.dumps(body).encode() if body is not None else None
    headers = {"Authorization": f"Bearer {token}", "X-Requested-With": "test"}
    if data is not None:
        headers["Content-Type"] = "application/json"
    req = urllib.request.Request(url, data=data, headers=headers, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def _version_rows(page) -> dict[int, dict]:
    """The history's rows by version: the signature cell's text and the row's buttons."""
    rows = page.evaluate(
        "() => Object.fromEntries([...document.querySelectorAll('#versions-table tbody tr')].map(tr => "
        "[Number(tr.children[0].textContent), {signature: tr.children[8].textContent, "
        "buttons: [...tr.children[9].querySelectorAll('button')].map(b => b.textContent)}]))"
    )
    return {int(k): v for k, v in rows.items()}


def _use_token(page, token: str) -> None:
    page.fill("#token", token)
    page.dispatch_event("#token", "change")


@pytest.mark.long
def test_signing_in_the_workbench(tmp_path):
    data = tmp_path / "data"
    store = Store(data, create=True)
    with acting_as("alice"):
        doc1, pairs = _cal_json(FLAT, 91)
        rec = store.create("line 3", {}, doc1, pairs, None, note="commissioned")
    with acting_as("sam"):  # version 1 signed by the signer with the server's key
        SigningPolicy(KEY).sign(store, store.version(rec.id, 1))
    with acting_as("bob"):
        store.add_version(rec.id, {}, *_cal_json(moved_cell(FLAT), 93), None, "after the bump")
    store.close()
    u_px, v_px = pairs[0]["u"], pairs[0]["v"]
    table = TokenTable(TOKENS, ROLES)
    with (
        workbench_thread(data, token=table, sign_key=KEY, require_signed=True) as url,
        chromium_page(1400, 1000, allowed_console=r"status of (401|403|409)") as page,
    ):
        # what the server itself answers (read with urllib, not through the page)
        code, waits = _post(
            f"{url}/api/calibrations/{rec.id}/image-to-robot", TOKENS["otto"], {"points": [[u_px, v_px]]}
        )
        assert code == 409 and "version 2 waits for a signature" in waits["error"], waits
        code, refused = _post(f"{url}/api/calibrations/{rec.id}/versions/2/sign", TOKENS["otto"])
        assert code == 403 and "needs role signer" in refused["error"], refused

        page.goto(url)
        _use_token(page, TOKENS["otto"])
        page.wait_for_selector("#saved-table tbody tr")
        page.locator("#saved-table button", has_text="history").first.click()
        page.wait_for_function("() => document.querySelectorAll('#versions-table tbody tr').length === 2")
        rows = _version_rows(page)
        assert rows[2]["signature"] == waits["error"], rows  # the version in force: the server's words
        assert rows[1]["signature"].startswith("signed by sam, 20"), rows
        assert "sign" in rows[2]["buttons"] and "sign" not in rows[1]["buttons"], rows
        shot = tmp_path / "signing_history.png"
        page.locator("#versions-block").screenshot(path=str(shot))
        keep_screenshot(shot)

        # the map form refuses with the same words
        page.select_option("#map-source", f"cal:{rec.id}")
        page.fill("#map-u", str(u_px))
        page.fill("#map-v", str(v_px))
        page.click("#map-go")
        page.wait_for_selector("#map-err:not([hidden])")
        assert page.text_content("#map-err") == waits["error"]

        # an operator's token: the server's 403, in its words, and nothing signed
        page.locator("#versions-table tbody tr", has_text="after the bump").locator(
            "button", has_text="sign"
        ).click()
        page.wait_for_selector("#versions-err:not([hidden])")
        assert page.text_content("#versions-err") == refused["error"]
        assert _version_rows(page)[2]["signature"] == waits["error"]

        # the signer's token signs; the history reloads; the page maps with the version
        _use_token(page, TOKENS["sam"])
        page.wait_for_function("() => document.querySelector('#token').value !== ''")
        page.locator("#versions-table tbody tr", has_text="after the bump").locator(
            "button", has_text="sign"
        ).click()
        page.wait_for_function(
            "() => [...document.querySelectorAll('#versions-table tbody tr')]"
            ".some(tr => tr.children[0].textContent === '2'"
            " && tr.children[8].textContent.startsWith('signed by sam'))"
        )
        rows = _version_rows(page)
        assert rows[2]["buttons"] == ["open"] and rows[1]["buttons"] == ["open", "roll back to this"], rows
        assert page.is_hidden("#versions-err")
        page.click("#map-go")
        page.wait_for_function("() => document.querySelector('#map-out').textContent.startsWith('x ')")
        assert page.is_hidden("#map-err")
        code, mapped = _post(
            f"{url}/api/calibrations/{rec.id}/image-to-robot", TOKENS["otto"], {"points": [[u_px, v_px]]}
        )
        assert code == 200, mapped
        assert page.text_content("#map-out").startswith(f"x {mapped['points'][0][0]:.4f} mm")
        page.wait_for_function("() => document.querySelectorAll('#audit-table tbody tr').length >= 4")
        top = page.evaluate(
            "() => [...document.querySelector('#audit-table tbody tr').children].map(c => c.textContent)"
        )
        assert top[1:3] == ["sam", "sign"], top
        assert page.problems == [], page.problems

    # a server without a signing key (nor --require-signed): no sign button, no waiting words
    with (
        workbench_thread(data, token=table) as url,
        chromium_page(1400, 1000, allowed_console=r"status of 401") as page,
    ):
        page.goto(url)
        _use_token(page, TOKENS["sam"])
        page.wait_for_selector("#saved-table tbody tr")
        # the list reloaded unchanged (the token given again) keeps its rows and their ticks: a rebuild
        # between a click's press and release lost the click (CI: the history never opened)
        page.check("#saved-table input.pick")
        mark = "() => { for (const s of ['#saved-table tbody tr', '#save-target option'])"
        mark += " document.querySelector(s).dataset.mark = 'kept'; }"
        page.evaluate(mark)
        _use_token(page, TOKENS["sam"])  # the reload ran once the save target's options are new
        page.wait_for_function("() => !document.querySelector('#save-target option').dataset.mark")
        assert page.evaluate("() => document.querySelector('#saved-table tbody tr').dataset.mark") == "kept"
        assert page.is_checked("#saved-table input.pick")
        page.locator("#saved-table button", has_text="history").first.click()
        page.wait_for_function("() => document.querySelectorAll('#versions-table tbody tr').length === 2")
        rows = _version_rows(page)
        assert all("sign" not in r["buttons"] for r in rows.values()), rows
        assert rows[2]["signature"].startswith("signed by sam, 20"), rows
        assert page.problems == [], page.problems
