"""The workbench's collection view in a real browser (Playwright + Debian's Chromium, headless).

The real server process runs with the virtual cell as its camera (`serve --tcp … --camera sim:…`); the
virtual robot (examples/robots/robot_client.py) runs a 3×3 plan over TCP while the page is open. The
page must show the live image refreshing, the plan's poses turning done, the recorded points with
their detections, a point dropped from the page (and re-collected: CAL NEXT offers its pose again),
and the fit after CAL END. It fails — never skips — when Chromium is missing.
"""

from __future__ import annotations

import re
import sys

import httpx
import pytest
from conftest import chromium_page
from helpers import ROBOTS, ServeProcess, keep_screenshot, view_centre_mm

sys.path.insert(0, str(ROBOTS))
from robot_client import TcpLink, VirtualRobot  # noqa: E402

CELL = """[camera]
width_px = 640
height_px = 512
pixel_size_um = 13.8
"""
Z = 150.0


@pytest.fixture
def serve(tmp_path):
    cell = tmp_path / "cell.toml"
    cell.write_text(CELL)
    srv = ServeProcess(tmp_path / "data", "--camera", f"sim:{cell}?seed=1", "--calibration", "bench")
    from eyetohand.sim.cell import load_cell
    from eyetohand.sim.simulate import true_camera

    cx, cy, _ = view_centre_mm(true_camera(load_cell(cell)), Z)
    rect = (cx - 25, cy - 25, cx + 25, cy + 25)
    yield {"url": srv.url, "tcp": srv.tcp_port, "rect": rect}
    srv.stop()


@pytest.fixture
def page():
    with chromium_page(1300, 1000) as pg:
        yield pg


def frame_number(page) -> int:
    v = page.locator("#frame").get_attribute("data-frame") or "0"
    return int(v or 0)


@pytest.mark.long
def test_collection_view_follows_the_robot(serve, page, tmp_path):
    from playwright.sync_api import expect

    url, rect = serve["url"], serve["rect"]
    page.goto(url + "/")
    page.click("a[href='/collect']")  # the one link from the workbench
    expect(page).to_have_url(re.compile(r"/collect$"))
    expect(page.locator("#c-state")).to_have_text("none")
    # the live image refreshes at least every second (before any robot pose: a message image)
    expect(page.locator("#frame")).to_have_attribute("data-frame", re.compile(r"\d+"), timeout=10_000)
    first = frame_number(page)
    page.wait_for_timeout(2500)
    assert frame_number(page) >= first + 2
    # before the first POINT: what to do, in words (not the sim camera's Python error)
    expect(page.locator("#frame-source")).to_have_text(
        "no image yet: the simulated camera shows the target once the robot has moved "
        "(CAL NEXT, then the first POINT)"
    )
    assert "set_robot_pose" not in page.content()

    link = TcpLink("127.0.0.1", serve["tcp"], timeout_s=60)
    robot = VirtualRobot(link.send)
    out = robot.run_plan("bench", "grid:3x3", rect, Z, stop_after=4, end=False)
    assert len(out["points"]) == 4
    expect(page.locator("#c-state")).to_have_text("collecting")
    expect(page.locator("#points tbody tr")).to_have_count(4)
    expect(page.locator("#plan-count")).to_have_text("4 of 9 poses done")
    # the live image now shows the target at the robot's last pose, detected (sim: a fresh grab)
    png = httpx.get(url + "/api/camera/frame.png", timeout=30)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.headers["x-frame-source"] == "live" and png.headers["x-frame-size"] == "640x512"
    assert png.content[:8] == b"\x89PNG\r\n\x1a\n"
    # the page shows a JPEG sized to its view, not the full-resolution PNG
    expect(page.locator("#frame-source")).to_have_text("")
    shown = page.evaluate(
        """() => { const i = document.querySelector('#frame');
        return [i.naturalWidth, i.clientWidth * devicePixelRatio, Number(i.dataset.bytes)]; }"""
    )
    assert shown[1] <= shown[0] < shown[1] + 64 or shown[0] == 640, shown  # never enlarged past 640
    assert shown[2] <= 300_000, shown
    jpg = httpx.get(url + "/api/camera/frame.jpg?width=320", timeout=30)
    assert jpg.headers["content-type"] == "image/jpeg" and jpg.content[:2] == b"\xff\xd8"
    import cv2
    import numpy as np

    small = cv2.imdecode(np.frombuffer(jpg.content, np.uint8), cv2.IMREAD_COLOR)
    assert small.shape[:2] == (256, 320), small.shape
    assert httpx.get(url + "/api/camera/frame.jpg?width=10").status_code == 422
    n0 = frame_number(page)
    page.wait_for_timeout(2500)
    assert frame_number(page) >= n0 + 2
    (tmp_path / "collect-live.png").write_bytes(page.locator("#frame").screenshot())

    # drop point 2 from the page: left out of the fit, its pose offered again by CAL NEXT
    row2 = page.locator("#points tbody tr[data-n='2']")
    row2.locator("button.drop").click()
    expect(row2).to_have_class("dropped")
    expect(page.locator("#points-count")).to_have_text("3 in the fit, 1 dropped")
    st = httpx.get(url + "/api/collect/status").json()
    assert [p["dropped"] for p in st["points"]] == [False, True, False, False]
    assert httpx.post(url + "/api/collect/points/99/drop").status_code == 403  # as a cross-site form could
    xrw = {"X-Requested-With": "t"}
    assert httpx.post(url + "/api/collect/points/99/drop", headers=xrw).status_code == 404

    out = robot.run_plan("bench", "grid:3x3", rect, Z)  # the robot program again: resumes
    link.close()
    assert len(out["points"]) == 6 and out["errors"] == []  # 5 left + the dropped pose again
    assert out["end"].startswith("OK ") and out["end"].split(",")[1] == "9"
    expect(page.locator("#c-state")).to_have_text("calibrated", timeout=10_000)
    expect(page.locator("#points tbody tr")).to_have_count(10)
    expect(page.locator("#plan-count")).to_have_text("9 of 9 poses done")
    expect(page.locator("#fit")).to_contain_text("9 points, leave-one-out rms")
    # each recorded point shows its detection
    cells = page.locator("#points tbody tr[data-n='1'] td").all_inner_texts()
    assert float(cells[6]) > 5 and 0 < float(cells[7]) and re.match(r"^\d+\.\d{4}$", cells[4])
    # the stored calibration is a version in the server's database
    cals = httpx.get(url + "/api/calibrations").json()
    assert [c["name"] for c in cals] == ["bench"] and cals[0]["current_version"] == 1

    shot = tmp_path / "collect.png"
    page.screenshot(path=str(shot), full_page=True)
    assert shot.stat().st_size > 20_000
    keep_screenshot(shot)
    keep_screenshot(tmp_path / "collect-live.png")
    assert not page.problems, page.problems
