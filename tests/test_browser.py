"""The workbench page in a real browser: Playwright driving Debian's Chromium (headless).

The server runs in a thread on a free loopback port. The test loads the paper's pairs through the
page's file inputs, runs the paper preset and checks what an engineer would look at: the live
convergence curve, the residual tables (mm), the residual vectors and a mapped point. It fails —
never skips — when Chromium is missing (`make test` installs it).
"""

from __future__ import annotations

import re
import shutil
import socket
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "examples" / "paper"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server(tmp_path, request):
    import uvicorn

    from eyetohand.server.app import LOOPBACK_HOSTS, create_app

    port = free_port()
    token = getattr(request, "param", None)
    app = create_app(tmp_path / "data", token=token, allowed_hosts=LOOPBACK_HOSTS)
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=srv.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 20
    while not srv.started:
        assert time.monotonic() < deadline, "server did not start"
        assert th.is_alive(), "server thread died"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    srv.should_exit = True
    th.join(timeout=15)


@pytest.fixture
def page():
    if not Path(CHROMIUM).exists():
        pytest.fail("Chromium is not installed: run `apt-get install -y chromium` (make test does)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
        pg = browser.new_page(viewport={"width": 1400, "height": 1000})
        problems: list[str] = []
        pg.on("pageerror", lambda e: problems.append(f"page error: {e}"))

        def on_console(m):  # the 4xx answers the test provokes on purpose are not problems
            if m.type == "error" and not re.search(r"status of (409|422)", m.text):
                problems.append(f"console {m.type}: {m.text}")

        pg.on("console", on_console)
        pg.problems = problems
        yield pg
        browser.close()


def test_paper_preset_in_the_workbench(server, page, tmp_path):
    from playwright.sync_api import expect

    page.goto(server + "/")
    expect(page.locator("#server-status")).to_contain_text("server v")

    # a bad paste is reported where it happened: under the text box, with line and field
    page.fill("#pairs-text", "u,v,x,y\n1,2,3,abc\n")
    page.click("#pairs-load")
    expect(page.locator("#pairs-err")).to_be_visible()
    expect(page.locator("#pairs-err")).to_contain_text("line 2, field 'y'")

    page.set_input_files("#pairs-file", str(PAPER / "calibration_points.csv"))
    expect(page.locator("#pairs-count")).to_contain_text("16 pairs from calibration_points.csv")
    expect(page.locator("#pairs-err")).to_be_hidden()
    page.set_input_files("#check-file", str(PAPER / "check_points.csv"))
    expect(page.locator("#check-count")).to_contain_text("9 pairs from check_points.csv")

    page.select_option("#preset", "paper")
    assert page.input_value("#model") == "paper"
    assert page.input_value("#optimizer") == "hybrid-pso"
    assert page.input_value("#particles") == "200" and page.input_value("#iterations") == "150"

    page.click("#run")
    # progress is visible while it runs, then the result
    expect(page.locator("#job-status")).to_have_text("done", timeout=90_000)
    assert page.get_attribute("#curve", "data-points") == "150"
    expect(page.locator("#job-iter")).to_have_text("150 of 150")
    expect(page.locator("#job-best")).to_contain_text(" mm")

    # residual tables (mm) and the vectors over the image
    expect(page.locator("#check-table tbody tr")).to_have_count(9)
    expect(page.locator("#train-table tbody tr")).to_have_count(16)
    expect(page.locator("#vectors g.pt-train circle")).to_have_count(16)
    expect(page.locator("#vectors g.pt-check circle")).to_have_count(9)
    expect(page.locator("#vectors line")).to_have_count(25)
    rows = page.locator("#stats-table tbody tr")
    expect(rows).to_have_count(3)  # fit, leave-one-out, check
    check_row = rows.filter(has_text="check points").inner_text()
    rms = float(check_row.split("\t")[2])
    assert 0.01 < rms < 0.06, check_row  # the paper's Table 4 level (hybrid PSO), mm
    head = page.locator("#check-table thead").inner_text()
    assert "|e| mm" in head and "u px" in head

    # save it under a name, then map a typed point with it
    page.fill("#save-name", "paper preset")
    page.click("#save-new")
    expect(page.locator("#save-state")).to_contain_text("saved as “paper preset”")
    expect(page.locator("#saved-table tbody tr")).to_have_count(1)
    page.select_option("#map-source", "cal:1")
    page.fill("#map-u", "600")
    page.fill("#map-v", "900")
    page.click("#map-go")
    expect(page.locator("#map-out")).to_have_text(re.compile(r"x -?\d+\.\d{4} mm, y -?\d+\.\d{4} mm, z"))

    # a field error lands next to the field
    page.fill("#save-name", "paper preset")
    page.click("#save-new")
    expect(page.locator("#save-err")).to_contain_text("exists already")
    expect(page.locator('#sec-save .field-err[data-field="name"]')).to_contain_text("exists already")

    # exclude a pair, refit, keep it as version 2 and see the history
    page.locator('#train-table tr[data-id="3"] input[type=checkbox]').uncheck()
    expect(page.locator("#refit-hint")).to_contain_text("3")
    page.click("#refit")
    expect(page.locator("#stats-table tbody tr")).to_have_count(4, timeout=90_000)  # + excluded pairs
    expect(page.locator("#job-status")).to_have_text("done")
    expect(page.locator('#train-table tr[data-id="3"]')).to_have_class(re.compile("excluded"))
    page.fill("#save-note", "without pair 3")
    page.click("#save-version")
    expect(page.locator("#save-state")).to_contain_text("version 2")
    page.locator("#saved-table button", has_text="history").click()
    expect(page.locator("#versions-table tbody tr")).to_have_count(2)
    expect(page.locator("#versions-table tbody tr").first).to_contain_text("without pair 3")

    shot = tmp_path / "workbench.png"
    page.screenshot(path=str(shot), full_page=True)
    assert shot.stat().st_size > 20_000
    out = ROOT / "out"
    if out.is_dir():  # keep a copy to look at when the folder exists
        shutil.copy(shot, out / "workbench.png")
    assert not page.problems, page.problems


@pytest.mark.parametrize("server", ["s3cret-token"], indirect=True)
def test_token_is_asked_for_and_used(server, page):
    from playwright.sync_api import expect

    page.problems.clear()
    page.goto(server + "/")
    expect(page.locator("#token-box")).to_be_visible()
    expect(page.locator("#global-err")).to_contain_text("token")
    page.fill("#token", "s3cret-token")
    page.locator("#token").dispatch_event("change")
    expect(page.locator("#server-status")).to_contain_text("server v")
    expect(page.locator("#global-err")).to_be_hidden()
    assert page.locator("#model option").count() >= 5
