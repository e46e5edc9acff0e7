"""The workbench on a plant-floor PC, in a real browser (Playwright driving Debian's Chromium).

- ``/docs``: Swagger UI renders FastAPI's OpenAPI 3.1 document (operations listed, no "Unable to render");
- the saved-calibrations table at 1280×800 and on a 10" touch panel (1024×600): every link and button
  of every row is inside the page's width and is the element a click at its centre lands on;
- long operations show their progress with an estimate of the time left.

Geometric assertions, not reference screenshots: the screenshots are kept in ``out/`` to look at.
It fails — never skips — when Chromium is missing.
"""

from __future__ import annotations

import threading
import time

import pytest
from conftest import chromium_page
from helpers import keep_screenshot


@pytest.fixture
def server(tmp_path):
    import uvicorn
    from helpers import free_port

    from eyetohand.server.app import LOOPBACK_HOSTS, create_app

    port = free_port()
    app = create_app(tmp_path / "data", allowed_hosts=LOOPBACK_HOSTS)
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
