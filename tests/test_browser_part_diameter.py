"""The part's diameter in the workbench's mapping form, in a real browser (Debian's Chromium, headless)
against a real server (issue 40, d40): a calibration that maps circle centres (fitted with a target
diameter) shows a "part diameter (mm)" field; without it the server's refusal is shown in its words and
the field is marked; with it the page answers what the library answers for that part; a calibration of
image points as detected shows no such field and maps as before. A simulated 25° cell: 20 mm targets
rendered and detected for the fit, a 12 mm part rendered and detected at use."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import numpy as np
import pytest
from conftest import chromium_page
from helpers import workbench_thread
from synth import detect_rendered, limit_view, plane_grid

from eyetohand import PointPairs
from eyetohand.calibration import FitRequest, calibrate_request
from eyetohand.server.storage import Store

SIZE = (1920, 1200)
TARGET_MM = 20.0
PART_MM = 12.0


def _map(url: str, cal_id: int, body: dict) -> tuple[int, dict]:
    """The server's own answer (the standard library's HTTP, not the page)."""
    req = urllib.request.Request(
        f"{url}/api/calibrations/{cal_id}/image-to-robot",
        data=json.dumps(body).encode(),
        headers={"Content-Type": "application/json"},
        method="POST",
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def _map_on_page(page, u_px: float, v_px: float, diameter: str | None = None) -> None:
    page.fill("#map-u", repr(u_px))
    page.fill("#map-v", repr(v_px))
    if diameter is not None:
        page.fill("#map-diameter", diameter)
    page.evaluate("() => { document.querySelector('#map-out').textContent = ''; }")
    page.click("#map-go")
    page.wait_for_function(
        "() => !document.querySelector('#map-err').hidden || document.querySelector('#map-out').textContent"
    )


@pytest.mark.long
def test_the_mapping_form_takes_the_parts_diameter(tmp_path):
    cam = limit_view(25.0, 800.0, SIZE)
    train = plane_grid(cam, 5, 0.1, 0.9)
    pairs = PointPairs.from_arrays(detect_rendered(cam, train, TARGET_MM, np.random.default_rng(40)), train)

    def fit(diameter):
        req = FitRequest.from_names("homography", image_size=SIZE, loo=False, target_diameter_mm=diameter)
        return calibrate_request(req, pairs)

    circles, points = fit(TARGET_MM), fit(None)
    # a 12 mm part near a corner of the view, where the tilt's bias is largest
    part = plane_grid(cam, 4, 0.2, 0.8)[:1]
    uv = detect_rendered(cam, part, PART_MM, np.random.default_rng(41))
    u_px, v_px = float(uv[0, 0]), float(uv[0, 1])
    want = circles.map(uv, part_diameter_mm=PART_MM).xyz_mm[0]
    assert abs(want[0] - part[0, 0]) < 0.02 and abs(want[1] - part[0, 1]) < 0.02, (want, part)

    data = tmp_path / "data"
    store = Store(data, create=True)
    rc = store.create("circles", {}, circles.to_dict(), pairs.to_records(), None, note="targets 20 mm")
    rp = store.create("points", {}, points.to_dict(), pairs.to_records(), None, note="as detected")
    store.close()

    with (
        workbench_thread(data) as url,
        chromium_page(1400, 1000, allowed_console=r"status of 422") as page,
    ):
        # what the page reads: the list's and the summary's circle_diameter_mm
        with urllib.request.urlopen(f"{url}/api/calibrations", timeout=30) as r:
            listed = {c["id"]: c["circle_diameter_mm"] for c in json.loads(r.read())}
        assert listed == {rc.id: TARGET_MM, rp.id: None}, listed
        for cal_id, d in ((rc.id, TARGET_MM), (rp.id, None)):
            with urllib.request.urlopen(f"{url}/api/calibrations/{cal_id}", timeout=30) as r:
                assert json.loads(r.read())["summary"]["circle_diameter_mm"] == d
        code, refused = _map(url, rc.id, {"points": [[u_px, v_px]]})
        assert code == 422 and refused["field"] == "points[0].part_diameter_mm", refused
        assert "give part_diameter_mm" in refused["error"], refused
        code, mapped = _map(url, rc.id, {"points": [[u_px, v_px]], "part_diameter_mm": PART_MM})
        assert code == 200 and np.allclose(mapped["points"][0], want, atol=1e-9), (mapped, want)

        page.goto(url)
        page.wait_for_selector("#saved-table tbody tr")
        page.select_option("#map-source", f"cal:{rc.id}")
        assert page.is_visible("#map-diameter")
        assert page.text_content("#map-diameter-hint") == "it maps the centres of 20 mm circles"

        # no diameter: the server's refusal, in its words, the field marked
        _map_on_page(page, u_px, v_px)
        assert page.text_content("#map-err") == refused["error"]
        assert "bad" in (page.get_attribute("#map-diameter", "class") or "")
        assert page.text_content("#map-out") == "x – mm, y – mm, z – mm"

        # the part's diameter: the library's answer for that part
        _map_on_page(page, u_px, v_px, "12")
        assert page.is_hidden("#map-err"), page.text_content("#map-err")
        assert page.text_content("#map-out").startswith(f"x {want[0]:.4f} mm, y {want[1]:.4f} mm")
        assert "bad" not in (page.get_attribute("#map-diameter", "class") or "")

        # a negative diameter: the server's words for the field
        _map_on_page(page, u_px, v_px, "-1")
        code, negative = _map(url, rc.id, {"points": [[u_px, v_px]], "part_diameter_mm": -1})
        assert code == 422 and page.text_content("#map-err") == negative["error"], negative

        # an as-detected calibration: no field, mapped as before (the typed diameter is not sent)
        page.select_option("#map-source", f"cal:{rp.id}")
        assert page.is_hidden("#map-diameter-box")
        _map_on_page(page, u_px, v_px)
        plain = points.map(uv).xyz_mm[0]
        assert page.is_hidden("#map-err"), page.text_content("#map-err")
        assert page.text_content("#map-out").startswith(f"x {plain[0]:.4f} mm, y {plain[1]:.4f} mm")
        assert page.problems == [], page.problems
