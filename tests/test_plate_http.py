"""POST /api/plate/calibrate: a plate image and touches over HTTP, stored and mapped like any calibration;
refusals are 422 naming the field in the CLI's words."""

from __future__ import annotations

import base64

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from eyetohand.calibration import Calibration
from eyetohand.core import pairs_from_text
from eyetohand.server.app import create_app
from eyetohand.sim import simulate_plate

SPEC = "chessboard:9x6:15"


@pytest.fixture(scope="module")
def sim():
    return simulate_plate(spec=SPEC, seed=7, touch_noise_mm=0.05)


@pytest.fixture()
def client(tmp_path):
    with TestClient(create_app(tmp_path / "data")) as c:
        yield c


def _file(name: str, data: bytes) -> dict:
    return {"name": name, "data_base64": base64.b64encode(data).decode()}


def _body(sim, **over) -> dict:
    ok, png = cv2.imencode(".png", sim.image)
    assert ok
    body = {
        "plate": SPEC,
        "images": [_file("plate.png", png.tobytes())],
        "touches": _file("touches.csv", sim.touches_csv.encode()),
    }
    body.update(over)
    return body


def test_plate_calibration_is_stored_and_maps(client, sim):
    check = pairs_from_text(sim.check_csv, "check.csv")
    r = client.post("/api/plate/calibrate", json=_body(sim, name="cell 1"))
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["model"] == "homography-radial" and out["plate"]["spec"] == SPEC
    cal = Calibration.from_dict(out["calibration"], "answer")  # the answer is a file that proves itself
    assert cal.plate is not None
    cal_id = out["stored"]["id"]
    pts = check.uv_px[:5].tolist()
    m = client.post(f"/api/calibrations/{cal_id}/image-to-robot", json={"points": pts})
    assert m.status_code == 200, m.text
    got = m.json()
    want = cal.map(np.array(pts))
    assert np.allclose(np.array(got["points"]), want.xyz_mm, atol=1e-9)
    assert np.allclose(got["sigma_mm"], want.sigma_mm, rtol=1e-9)  # the touches' term included
    assert np.abs(want.xyz_mm[:, :2] - check.xyz_mm[:5, :2]).max() < 0.3


@pytest.mark.parametrize(
    "over, field, words",
    [
        ({"plate": "chessboard:9x6"}, "plate", "expected KIND:COLSxROWS:PITCH_MM"),
        ({"plate": "chessboard:8x6:15"}, "images[0]", "saw a chessboard of 9x6 inner corners"),
        ({"model": "nope"}, "model", "unknown model 'nope'"),
    ],
)
def test_refusals_name_the_field(client, sim, over, field, words):
    r = client.post("/api/plate/calibrate", json=_body(sim, **over))
    assert r.status_code == 422
    assert r.json()["field"] == field and words in r.json()["error"]


def test_a_bad_touch_is_named(client, sim):
    rows = sim.touches_csv.splitlines()
    u, v, x, y, z, tid = rows[2].split(",")
    rows[2] = ",".join([u, v, f"{float(x) * 1.0 + 15:.3f}", y, z, tid])  # B touched one square away
    r = client.post("/api/plate/calibrate", json=_body(sim, touches=_file("t.csv", "\n".join(rows).encode())))
    assert r.status_code == 422 and r.json()["field"] == "touches"
    assert "touch B (line 3)" in r.json()["error"]


def test_tcp_line_answers_a_plate_calibration(sim):
    """The TCP line service's answer to ``u,v sigma`` for a plate calibration: its point and its
    sigma_mm with the touches' error, as the library maps it."""
    from eyetohand.calibration import calibrate_plate
    from eyetohand.calibration.touches import touches_from_text
    from eyetohand.positioning import answer

    cal = calibrate_plate(
        [sim.image], SPEC, touches_from_text(sim.touches_csv, "t.csv", ["p.png"]), names=["p.png"]
    )
    u, v = sim.true_uv_px[20]
    got = [float(x) for x in answer(cal, f"{u:.4f},{v:.4f},sigma".encode()).decode().split(",")]
    want = cal.map(np.array([[float(f"{u:.4f}"), float(f"{v:.4f}")]]))
    assert np.allclose(got[:3], want.xyz_mm[0], atol=1e-3) and got[3] == pytest.approx(
        want.sigma_mm[0], rel=1e-3
    )
    assert got[3] > 10 * cal.uncertainty.sigma_mm(cal.model, want.uv_px, want.xyz_mm[:, 2])[0]
