"""The workbench's plate flow in a real browser (Debian's Chromium, headless) against a real server
(uvicorn in a thread): a rendered plate image (sim.simulate_plate) uploaded, a wrong spec shown with the
library's words and the corners it saw, the A-D labels, the robot's readings typed in, a click snapped
to a corner and one refused (the fit's words), the fit with check points, its expected-accuracy line,
and the save as a stored calibration that maps like the truth. A point-pair fit shows the line too."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from conftest import chromium_page
from helpers import workbench_thread

from eyetohand import calibrate
from eyetohand.core import pairs_from_text
from eyetohand.sim import simulate, simulate_plate

SPEC = "chessboard:9x6:15"
ANSWERED = r"status of 422"  # the refusals this test provokes (shown on the page, in the API's words)
SLOW = 120_000  # ms: a detection on a 2448 x 2048 image takes seconds on a loaded 2-core machine


def _click_image_px(page, u: float, v: float) -> None:
    """Click the plate canvas where image pixel (u, v) is drawn (at the page's own scale)."""
    canvas = page.locator("#plate-canvas")
    canvas.scroll_into_view_if_needed()
    box = canvas.bounding_box()
    w = page.evaluate("() => document.querySelector('#plate-canvas').width")
    k = box["width"] / w / (2448 / w)  # CSS px per image px: canvas px per image px x CSS px per canvas px
    canvas.click(position={"x": (u + 0.5) * k, "y": (v + 0.5) * k})


def _wait_state(page, text: str) -> None:
    page.wait_for_function(
        "t => document.querySelector('#plate-state').textContent.includes(t)", arg=text, timeout=SLOW
    )


@pytest.mark.long
def test_plate_flow_upload_touch_fit_save(tmp_path):
    sim = simulate_plate(spec=SPEC, seed=7, touch_noise_mm=0.05)
    img = tmp_path / "plate.png"
    cv2.imwrite(str(img), sim.image)
    (tmp_path / "check.csv").write_text(sim.check_csv)
    world = sim.placement.to_robot(sim.spec.points_mm())  # the truth: every corner in the robot frame
    touched = pairs_from_text(sim.touches_csv, "touches.csv")  # A-D: the robot's readings (0.05 mm noise)
    check = pairs_from_text(sim.check_csv, "check.csv")

    with (
        workbench_thread(tmp_path / "data") as url,
        chromium_page(1400, 1000, allowed_console=ANSWERED) as page,
    ):
        page.goto(url)
        page.wait_for_selector("#server-status:has-text('server v')")
        assert "inner corners" in page.inner_text("#plate-help")  # the spec's one-line help
        # a spec with another count: the library's words, and the 54 corners it saw drawn
        page.fill("#plate-spec", "chessboard:8x6:15")
        page.set_input_files("#plate-files", str(img))
        page.wait_for_selector("#plate-err:not([hidden])", timeout=SLOW)
        err = page.inner_text("#plate-err")
        assert err.startswith("plate.png: plate chessboard:8x6:15 not found: saw a chessboard of 9x6"), err
        assert page.get_attribute("#plate-canvas", "data-seen") == "54"
        assert page.is_disabled("#plate-fit")
        # the right spec: found, A-D labelled, the table's rows on those corners
        page.fill("#plate-spec", SPEC)
        page.click("#plate-detect")
        _wait_state(page, "54 corners found")
        assert page.is_hidden("#plate-err")
        assert page.get_attribute("#plate-canvas", "data-labels") == "A r0c0,B r0c8,C r5c8,D r5c0"
        rows = page.locator("#plate-touches tbody tr")
        assert rows.count() == 4
        assert [rows.nth(i).locator("td").nth(3).inner_text() for i in range(4)] == [
            "r0c0",
            "r0c8",
            "r5c8",
            "r5c0",
        ]
        for i in range(4):
            for k, c in enumerate("xyz"):
                rows.nth(i).locator(f"input.t{c}").fill(f"{touched.xyz_mm[i, k]:.3f}")
        # a fifth touch: a click between corners is refused in the fit's words, then one beside r1c4 snaps
        # (off both diagonals, so that a touch off the plane is named below)
        page.click("#plate-add")
        assert rows.count() == 5 and rows.nth(4).locator("input.tid").input_value() == "E"
        g = sim.true_uv_px
        mid = (g[0] + g[1] + g[9] + g[10]) / 4  # the middle of the first square
        _click_image_px(page, *mid)
        page.wait_for_selector("#plate-err:not([hidden])")
        err = page.inner_text("#plate-err")
        assert err.startswith("touch E (line 6): (u, v) = (") and "(snap radius 10.0 px)" in err, err
        assert rows.nth(4).locator("td").nth(3).inner_text() == "click it"
        _click_image_px(page, g[13, 0] + 3, g[13, 1] - 2)
        _wait_state(page, "touch E: corner r1c4")
        assert page.is_hidden("#plate-err")
        assert rows.nth(4).locator("td").nth(3).inner_text() == "r1c4"
        for k, c in enumerate("xyz"):
            rows.nth(4).locator(f"input.t{c}").fill(f"{world[13, k] + 0.03:.3f}")
        # a touch 6 mm off the plate's plane: the fit refuses it, naming the touch and its CSV line
        rows.nth(3).locator("input.tz").fill(f"{touched.xyz_mm[3, 2] + 6:.3f}")
        page.click("#plate-fit")
        page.wait_for_selector("#plate-fit-err:not([hidden])", timeout=SLOW)
        err = page.inner_text("#plate-fit-err")
        assert re.match(r"touch D \(line 5\) is 5\.\d\d mm off the plane of the other touches", err), err
        assert page.is_hidden("#sec-result")
        rows.nth(3).locator("input.tz").fill(f"{touched.xyz_mm[3, 2]:.3f}")
        # fit with check points: the result section, its expected-accuracy line, the check statistics
        page.set_input_files("#plate-check", str(tmp_path / "check.csv"))
        page.wait_for_selector("#plate-check-count:has-text('20 check points')")
        page.click("#plate-fit")
        page.wait_for_selector("#sec-result:not([hidden])", timeout=SLOW)
        assert page.is_hidden("#plate-fit-err"), page.inner_text("#plate-fit-err")
        line = page.inner_text("#result-accuracy")
        assert line.startswith("expected accuracy at the check points: RMS "), line
        assert "the plate's placement by the touches" in line and "measured check RMS" in line
        assert "model homography-radial" in page.inner_text("#result-title")
        stats = page.locator("#stats-table tbody tr")
        check_row = [
            stats.nth(i).inner_text() for i in range(stats.count()) if "check" in stats.nth(i).inner_text()
        ]
        assert check_row and float(check_row[0].split("\t")[2]) < 0.3, check_row  # RMS mm
        assert "5 touches" in page.inner_text("#plate-fit-state") or "touches fit RMS" in page.inner_text(
            "#plate-fit-state"
        )
        # save as a stored calibration (the store's version, as the other fits), then map with it
        page.fill("#save-name", "cell 1 plate")
        page.click("#save-new")
        page.wait_for_selector("#save-state:has-text('saved as')", timeout=SLOW)
        page.wait_for_selector("#saved-table tbody tr")  # the list reloaded after the save
        assert page.locator("#saved-table tbody tr").count() == 1
        u, v = check.uv_px[0]
        page.select_option("#map-source", label="cell 1 plate (id 1, v1)")
        page.fill("#map-u", f"{u}")
        page.fill("#map-v", f"{v}")
        page.click("#map-go")
        page.wait_for_selector("#map-out:not(.empty)")
        got = page.inner_text("#map-out")
        x, y = (float(got.split(" ")[i]) for i in (1, 4))
        assert np.hypot(x - check.xyz_mm[0, 0], y - check.xyz_mm[0, 1]) < 0.3, got
        assert page.problems == []


@pytest.mark.long
def test_a_point_pair_fit_shows_its_expected_accuracy(tmp_path):
    sim = simulate(plan="grid:5x5", seed=3, n_check=10)
    (tmp_path / "pairs.csv").write_text(sim.pairs.to_csv_text())
    (tmp_path / "check.csv").write_text(sim.check.to_csv_text())
    with workbench_thread(tmp_path / "data") as url, chromium_page(1400, 1000) as page:
        page.goto(url)
        page.wait_for_selector("#server-status:has-text('server v')")
        page.set_input_files("#pairs-file", str(tmp_path / "pairs.csv"))
        page.set_input_files("#check-file", str(tmp_path / "check.csv"))
        page.wait_for_selector("#check-count.ok")
        page.click("#run")
        page.wait_for_selector("#sec-result:not([hidden])", timeout=SLOW)
        line = page.inner_text("#result-accuracy")
        assert line.startswith("expected accuracy at the check points: RMS "), line
        assert "touches" not in line and "measured check RMS" in line
        assert page.problems == []


def test_importing_a_file_keeps_its_bytes(tmp_path):
    """A calibration file imported on the page goes to the server as written: through JSON.parse and
    JSON.stringify its 0.0 entries (a homography's matrices have them) became 0 and the file's content
    hash no longer matched ("the file's content does not match content_sha256")."""
    sim = simulate(plan="grid:5x5", seed=3, n_check=10)
    text = calibrate(sim.pairs, model="homography", loo=False).to_json()
    assert re.search(r"[^0-9.e-]0\.0[,\]]", text)  # an integral float the browser would rewrite
    (tmp_path / "line 2.json").write_text(text)
    with workbench_thread(tmp_path / "data") as url, chromium_page(1400, 1000) as page:
        page.goto(url)
        page.wait_for_selector("#server-status:has-text('server v')")
        page.set_input_files("#import-file", str(tmp_path / "line 2.json"))
        page.click("#import-btn")
        page.wait_for_selector("#saved-table tbody tr", timeout=SLOW)
        assert page.is_hidden("#saved-err"), page.inner_text("#saved-err")
        assert page.inner_text("#saved-table tbody tr td.name") == "line 2"
        assert page.problems == []


@pytest.mark.long
def test_two_placements_each_touched_on_its_own_image(tmp_path):
    """Two images of one plate (on the table, z 0; on a 60 mm block, yawed): the second image's touches
    are clicked on it (the view switched), the fit uses both placements (model camera: several heights)."""
    from eyetohand.sim import Cell

    cell = Cell.default().with_values(camera={"tilt_deg": 6.0, "yaw_deg": 20.0})
    sims = [
        simulate_plate(cell, SPEC, z_mm=z, yaw_deg=yaw, tilt_deg=0.4, seed=40 + k, touch_noise_mm=0.05)
        for k, (z, yaw) in enumerate(((0.0, 10.0), (60.0, -15.0)))
    ]
    for k, s in enumerate(sims):
        cv2.imwrite(str(tmp_path / f"p{k + 1}.png"), s.image)
    touched = [pairs_from_text(s.touches_csv, "t.csv") for s in sims]
    with (
        workbench_thread(tmp_path / "data") as url,
        chromium_page(1400, 1000, allowed_console=ANSWERED) as page,
    ):
        page.goto(url)
        page.wait_for_selector("#server-status:has-text('server v')")
        page.set_input_files("#plate-files", [str(tmp_path / "p1.png"), str(tmp_path / "p2.png")])
        page.wait_for_selector("#plate-count:has-text('2 images, plate found in 2')", timeout=SLOW)
        rows = page.locator("#plate-touches tbody tr")
        assert rows.count() == 4  # A-D of the first image
        for i in range(4):
            assert rows.nth(i).locator("td").nth(2).inner_text() == "1: p1.png"
            for k, c in enumerate("xyz"):
                rows.nth(i).locator(f"input.t{c}").fill(f"{touched[0].xyz_mm[i, k]:.3f}")
        page.select_option("#plate-view", "1")
        _wait_state(page, "p2.png: 54 corners found")
        assert page.get_attribute("#plate-canvas", "data-labels") == "A r0c0,B r0c8,C r5c8,D r5c0"
        with page.expect_download(timeout=SLOW) as dl:  # the image as --annotate draws it
            page.click("#plate-annotated")
        assert dl.value.suggested_filename == "p2-annotated.png"
        drawn = cv2.imread(dl.value.path())
        assert drawn.shape == sims[1].image.shape + (3,)
        assert (drawn[..., 0] != drawn[..., 2]).sum() > 1000  # coloured: the grid and the A-D labels drawn
        for i in range(4):  # the second image's A-D: a new row each, clicked on its corner
            page.click("#plate-add")
            u, v = touched[1].uv_px[i]
            _click_image_px(page, u + 2, v + 1)
            _wait_state(page, f"touch {'EFGH'[i]}: corner {['r0c0', 'r0c8', 'r5c8', 'r5c0'][i]}")
            row = rows.nth(4 + i)
            assert row.locator("td").nth(2).inner_text() == "2: p2.png"
            for k, c in enumerate("xyz"):
                row.locator(f"input.t{c}").fill(f"{touched[1].xyz_mm[i, k]:.3f}")
        page.click("#plate-fit")
        page.wait_for_selector("#sec-result:not([hidden])", timeout=SLOW)
        assert "model camera" in page.inner_text("#result-title")
        assert "108 pairs" in page.inner_text("#result-title")
        state = page.inner_text("#plate-fit-state")
        assert "image 1: touches fit RMS" in state and "image 2: touches fit RMS" in state, state
        assert page.inner_text("#result-accuracy").startswith("expected accuracy at the training pixels")
        assert page.problems == []
