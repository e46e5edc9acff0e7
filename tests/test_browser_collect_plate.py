"""A robot's live plate session on the collection page, in a real browser (Debian's Chromium, headless)
against a real server process (issue 37, p37's CAL PLATE / CAL TOUCH / CAL END): ``serve --camera
sim:…`` shows a rendered chessboard (``SIM PLATE``, as a person lays the plate down); the robot's line
opens the session and touches corners with the simulation's readings. The page must show the image the
collection kept with A–D drawn at the corners the server found (the reply's pixels), which of them the
robot touched, update as it touches another, follow a second placement (the plate raised and tilted:
its own image and corners) and show the fit of both after CAL END."""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest
from conftest import chromium_page
from helpers import ROBOTS, SMALL_CELL_TOML, ServeProcess, keep_screenshot

from eyetohand.sim.cell import load_cell
from eyetohand.sim.plate import simulate_plate
from eyetohand.vision import PlateSpec

sys.path.insert(0, str(ROBOTS))
from robot_client import TcpLink  # noqa: E402

SPEC = "chessboard:9x6:15"
PLATE_SEED = 1


@pytest.fixture
def serve(tmp_path):
    cell = tmp_path / "cell.toml"
    cell.write_text(SMALL_CELL_TOML)
    srv = ServeProcess(tmp_path / "data", "--camera", f"sim:{cell}?seed=5", "--calibration", "cell1")
    try:
        yield srv, cell
    finally:
        srv.stop()


def _corner_marks(page) -> dict[str, dict]:
    """The SVG's corner marks by label: class, centre (its own image pixels) and text."""
    marks = page.evaluate(
        "() => [...document.querySelectorAll('#plate-svg g.corner')].map(g => ({label: g.dataset.label, "
        "cls: g.getAttribute('class'), u: Number(g.querySelector('circle').getAttribute('cx')), "
        "v: Number(g.querySelector('circle').getAttribute('cy')), "
        "text: g.querySelector('text').textContent}))"
    )
    return {m["label"]: m for m in marks}


@pytest.mark.long
def test_the_collection_page_shows_the_robots_plate_session(serve, tmp_path):
    from playwright.sync_api import expect

    srv, cell = serve
    spec = PlateSpec.parse(SPEC)
    sim = simulate_plate(load_cell(cell), spec, seed=PLATE_SEED, render=False, n_check=10)
    world_mm = sim.placement.to_robot(spec.points_mm())
    labels = spec.corner_labels()
    rng = np.random.default_rng(11)
    link = TcpLink("127.0.0.1", srv.tcp_port)

    def touch(label: str, world: np.ndarray = world_mm) -> tuple[float, float]:
        xyz = world[labels[label]] + rng.normal(0, 0.05, 3)
        reply = link.send(f"CAL TOUCH {label},{xyz[0]:.4f},{xyz[1]:.4f},{xyz[2]:.4f}")
        assert reply.startswith("OK "), reply
        _, u, v = reply.removeprefix("OK ").split(",")
        return float(u), float(v)

    with chromium_page(1300, 1000) as page:
        page.goto(srv.url + "/collect")
        expect(page.locator("#c-state")).to_have_text("none")
        assert page.is_hidden("#plate-block")

        assert link.send(f"SIM PLATE {SPEC},{PLATE_SEED}").startswith("OK 54")
        assert link.send(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
        touched = {k: touch(k) for k in ("A", "C")}

        expect(page.locator("#plate-count")).to_have_text(
            "placement 1 · 2 of 4 corners touched", timeout=10_000
        )
        expect(page.locator("#plate-spec")).to_have_text(SPEC)
        page.wait_for_function(
            "() => { const i = document.querySelector('#plate-svg image');"
            " return i && (i.getAttribute('href') || '').startsWith('blob:'); }"
        )
        assert page.get_attribute("#plate-svg", "viewBox") == "0 0 640 512"
        marks = _corner_marks(page)
        assert sorted(marks) == list("ABCD")
        # the marks sit on the pixels the server answered for the touched corners, and within a pixel
        # of the simulation's truth for every corner
        for k, (u, v) in touched.items():
            assert abs(marks[k]["u"] - u) < 1e-3 and abs(marks[k]["v"] - v) < 1e-3, (k, marks[k], u, v)
        for k, i in labels.items():
            assert np.hypot(marks[k]["u"] - sim.true_uv_px[i, 0], marks[k]["v"] - sim.true_uv_px[i, 1]) < 1.0
        assert [marks[k]["cls"] for k in "ABCD"] == [
            "corner touched",
            "corner todo",
            "corner touched",
            "corner todo",
        ], marks
        assert marks["A"]["text"] == "A ✓" and marks["B"]["text"] == "B"
        rows = page.evaluate(
            "() => [...document.querySelectorAll('#plate-corners tbody tr')]"
            ".map(tr => tr.children[4].textContent)"
        )
        shot = tmp_path / "collect_plate.png"
        page.locator("#plate-block").screenshot(path=str(shot))
        keep_screenshot(shot)
        assert rows[0].startswith("#1 at ") and rows[1] == "not yet" and rows[2].startswith("#2 at "), rows
        # the image the page shows is the kept one: its size as the status says
        size = page.evaluate(
            "async () => { const i = document.querySelector('#plate-svg image');"
            " const b = await (await fetch(i.getAttribute('href'))).blob();"
            " const bm = await createImageBitmap(b); return [bm.width, bm.height]; }"
        )
        assert size[0] * 512 == size[1] * 640, size

        touch("B")
        touch("D")
        expect(page.locator("#plate-count")).to_have_text(
            "placement 1 · 4 of 4 corners touched", timeout=10_000
        )
        assert all(m["cls"] == "corner touched" for m in _corner_marks(page).values())

        # a second placement (the plate 40 mm higher, tilted 4 deg): its own image and corners, no touch yet
        first_href = page.get_attribute("#plate-svg image", "href")
        sim2 = simulate_plate(load_cell(cell), spec, seed=PLATE_SEED, render=False, z_mm=40.0, tilt_deg=4.0)
        assert link.send(f"SIM PLATE {SPEC},{PLATE_SEED},40,4").startswith("OK 54")
        assert link.send(f"CAL PLATE {SPEC},cell1,2") == "OK 54,A,B,C,D"
        expect(page.locator("#plate-count")).to_have_text(
            "placement 2 · 0 of 4 corners touched", timeout=10_000
        )
        page.wait_for_function(
            "(old) => (document.querySelector('#plate-svg image').getAttribute('href') || old) !== old",
            arg=first_href,
        )
        marks = _corner_marks(page)
        assert all(m["cls"] == "corner todo" for m in marks.values()), marks
        for k, i in labels.items():
            assert (
                np.hypot(marks[k]["u"] - sim2.true_uv_px[i, 0], marks[k]["v"] - sim2.true_uv_px[i, 1]) < 1.0
            )
        world2 = sim2.placement.to_robot(spec.points_mm())
        touch("A", world2)
        expect(page.locator("#plate-count")).to_have_text(
            "placement 2 · 1 of 4 corners touched", timeout=10_000
        )
        for k in "BCD":
            touch(k, world2)

        end = link.send("CAL END")
        assert end.startswith("OK camera,8,"), end
        model, n, rms, worst = end.removeprefix("OK ").split(",")
        expect(page.locator("#fit")).to_have_text(
            re.compile(
                rf"^{re.escape(model)}: 8 touches, touch rms {float(rms):.4f} mm, max {float(worst):.4f} mm"
            ),
            timeout=10_000,
        )
        assert page.problems == [], page.problems
    link.close()
