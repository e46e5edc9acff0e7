"""The workbench's pictures of a stored calibration (issue 30 part 4): ``GET
/api/calibrations/{id}/trust-map.png`` (the report's trust map of a version, cached per version and
width, over the camera's image when the server has one) and ``.../drift.png`` (its checks over time)."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, records

from eyetohand.server.app import create_app

PAIRS = records(PAPER / "calibration_points.csv")
CHECK = records(PAPER / "check_points.csv")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    assert data[:8] == PNG_MAGIC, data[:16]
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(tmp_path / "data")) as c:
        yield c


def create(client, name="cal", **kw) -> dict:
    body = {"name": name, "pairs": PAIRS, "check": CHECK, "model": "homography", "optimizer": "lm", **kw}
    r = client.post("/api/calibrations", json=body)
    assert r.status_code == 201, r.text
    return r.json()


def test_trust_map_png_is_cached_per_version_and_width(client):
    from urllib.parse import unquote

    cid = create(client)["id"]
    t0 = time.perf_counter()
    r = client.get(f"/api/calibrations/{cid}/trust-map.png?width=640")
    first_s = time.perf_counter() - t0
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    assert png_size(r.content)[0] == 640
    assert r.headers["X-Cache"] == "miss" and r.headers["X-Version"] == "1"
    assert unquote(r.headers["X-Trust-Background"]).startswith("none: the server has no camera")
    caption = unquote(r.headers["X-Caption"])
    assert "sigma_mm" in caption and "The star marks" in caption, caption

    t0 = time.perf_counter()
    again = client.get(f"/api/calibrations/{cid}/trust-map.png?width=640&version=1")
    hit_s = time.perf_counter() - t0
    assert again.headers["X-Cache"] == "hit" and again.content == r.content
    assert hit_s < first_s / 5, (hit_s, first_s)

    wide = client.get(f"/api/calibrations/{cid}/trust-map.png?width=1200")
    assert wide.headers["X-Cache"] == "miss" and png_size(wide.content)[0] == 1200

    # a new version is another picture; the old one is still served from the cache
    pairs = [p for p in PAIRS if p["id"] != PAIRS[0]["id"]]
    body = {"pairs": pairs, "check": CHECK, "model": "homography", "optimizer": "lm"}
    assert client.post(f"/api/calibrations/{cid}/versions", json=body).status_code == 201
    v2 = client.get(f"/api/calibrations/{cid}/trust-map.png?width=640")
    assert v2.headers["X-Version"] == "2" and v2.headers["X-Cache"] == "miss"
    assert v2.content != r.content
    assert (
        client.get(f"/api/calibrations/{cid}/trust-map.png?width=640&version=1").headers["X-Cache"] == "hit"
    )


def test_trust_map_refusals_name_the_field(client):
    cid = create(client)["id"]
    r = client.get(f"/api/calibrations/{cid}/trust-map.png?width=10")
    assert r.status_code == 422 and "width" in r.text
    assert client.get(f"/api/calibrations/{cid}/trust-map.png?version=7").status_code == 404
    assert client.get("/api/calibrations/999/trust-map.png").status_code == 404


class _Camera:
    """A CameraView stand-in: ``still()`` as the collection's camera view answers it."""

    def __init__(self, img):
        self.img = img
        self.calls = 0

    def still(self):
        self.calls += 1
        return self.img, "live" if self.img is not None else "no image yet"


def test_trust_map_over_the_camera_image(tmp_path):
    from urllib.parse import unquote

    from eyetohand import calibrate, load_pairs

    cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False)
    hull = cal.region.hull_px
    w, h = int(hull[:, 0].max() * 1.2), int(hull[:, 1].max() * 1.2)  # a frame the region fits in
    img = np.zeros((h, w, 3), np.uint8)
    img[:, : w // 2] = 200  # left half bright: the map's pixels differ from a map without it
    app = create_app(tmp_path / "data")
    with TestClient(app) as client:
        cid = create(client)["id"]
        app.state.collect = cam = _Camera(None)  # the camera has no image yet: drawn, not kept
        r = client.get(f"/api/calibrations/{cid}/trust-map.png")
        assert unquote(r.headers["X-Trust-Background"]) == "none: no image yet"
        r2 = client.get(f"/api/calibrations/{cid}/trust-map.png")
        assert r2.headers["X-Cache"] == "miss" and cam.calls == 2
        cam.img = img
        over = client.get(f"/api/calibrations/{cid}/trust-map.png")
        assert unquote(over.headers["X-Trust-Background"]) == "the camera's live"
        assert over.status_code == 200 and over.content != r.content
        assert png_size(over.content)[0] == 800
        assert client.get(f"/api/calibrations/{cid}/trust-map.png").headers["X-Cache"] == "hit"
        assert cam.calls == 3


def verify(client, cid, pairs, tol):
    r = client.post(f"/api/calibrations/{cid}/verify", json={"pairs": pairs, "tolerance_mm": tol})
    assert r.status_code == 200, r.text
    return r.json()


def test_drift_png(client, tmp_path):
    cid = create(client)["id"]
    r = client.get(f"/api/calibrations/{cid}/drift.png")
    assert r.status_code == 404 and "no checks yet" in r.json()["error"]
    fresh = PAIRS[::2]
    verify(client, cid, fresh, 1.0)
    verify(client, cid, [dict(p, x=p["x"] + 0.5) for p in fresh], 1.0)
    r = client.get(f"/api/calibrations/{cid}/drift.png?width=900")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png" and r.headers["X-Checks"] == "2"
    assert png_size(r.content)[0] == 900
    # a limit of the caller's: another picture
    other = client.get(f"/api/calibrations/{cid}/drift.png?width=900&limit_mm=0.3")
    assert other.status_code == 200 and other.content != r.content
    assert client.get(f"/api/calibrations/{cid}/drift.png?limit_mm=0").status_code == 422


def test_drift_png_joins_the_collections_checks(tmp_path):
    import json

    app = create_app(tmp_path / "data")
    with TestClient(app) as client:
        cid = create(client, "cell")["id"]

        class Collector:
            def history_path(self, name):
                return tmp_path / f"{name}.checks.jsonl"

        class View:
            collector = Collector()

        app.state.collect = View()
        lines = [
            {"utc": "2024-05-01T10:00:00.000+00:00", "name": "cell", "version": 1, "error_mm": 0.04},
            {"utc": "2024-05-02T10:00:00.000+00:00", "name": "cell", "version": 1, "error_mm": 0.05},
        ]
        (tmp_path / "cell.checks.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
        r = client.get(f"/api/calibrations/{cid}/drift.png")
        assert r.status_code == 200 and r.headers["X-Checks"] == "2"
        verify(client, cid, PAIRS[::2], 1.0)
        assert client.get(f"/api/calibrations/{cid}/drift.png").headers["X-Checks"] == "3"


def test_a_trust_map_being_drawn_blocks_no_other_request(client):
    import threading

    cid = create(client)["id"]
    done = {}

    def draw():
        t0 = time.perf_counter()
        done["status"] = client.get(f"/api/calibrations/{cid}/trust-map.png?width=1000").status_code
        done["s"] = time.perf_counter() - t0

    th = threading.Thread(target=draw)
    th.start()
    time.sleep(0.3)  # the render has started on the thread pool
    t0 = time.perf_counter()
    assert client.get("/api/health").status_code == 200
    health_s = time.perf_counter() - t0
    th.join(60)
    assert done["status"] == 200
    assert health_s < 0.25 * done["s"], (health_s, done["s"])
