"""A ChArUco board seen in part on the two other ways in (issue 37): the workbench's detect and snap
endpoints (unseen corners are null, the A–D labels are the extreme corners seen, as ``--annotate``
labels them) and the robot's ``CAL PLATE`` / ``CAL TOUCH`` / ``CAL END`` (the labels it answers are
the corners seen; a corner not seen is refused by name; the stored calibration maps within its sigma)."""

from __future__ import annotations

import base64
import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from eyetohand.calibration import Calibration
from eyetohand.cell.collect import Collector
from eyetohand.server.app import create_app
from eyetohand.sim import simulate_plate
from eyetohand.vision import PlateSpec, detect_plate

SPEC = "charuco:9x6:15"


@pytest.fixture(scope="module")
def sim():
    """The board's right part beyond the image's edge (as tests/test_plate_partial.py's "out of view")."""
    s = simulate_plate(spec=SPEC, seed=3, touch_noise_mm=0.05, shift_mm=(100.0, 0.0), n_check=40)
    assert (s.true_uv_px[:, 0] > s.camera.image_size[0]).sum() >= 12
    return s


def _seen_labels(sim) -> dict[str, int]:
    """The labels ``calibrate-plate --annotate`` gives: the extreme corners the library detects."""
    seen = detect_plate(sim.image, SPEC, "plate.png").seen
    assert 12 <= seen.sum() < 54
    return PlateSpec.parse(SPEC).corner_labels(seen)


def test_detect_and_snap_answer_a_partial_board(sim, tmp_path):
    png = cv2.imencode(".png", sim.image)[1].tobytes()
    img = {"name": "plate.png", "data_base64": base64.b64encode(png).decode()}
    with TestClient(create_app(tmp_path / "data")) as c:
        r = c.post("/api/plate/detect", json={"plate": SPEC, "image": img})
        assert r.status_code == 200, r.text
        d = r.json()
        unseen = [i for i, p in enumerate(d["uv_px"]) if p is None]
        assert len(d["uv_px"]) == 54 and 12 <= len(unseen) < 54 - 12 and d["seen"] == 54 - len(unseen)
        labels = {x["label"]: x["index"] for x in d["labels"]}
        assert labels == _seen_labels(sim) and not set(labels.values()) & set(unseen)
        assert all(p is not None for p in d["outline_px"])
        # a click near a seen corner snaps to it; the detected points go back with their nulls
        i = labels["B"]
        u, v = d["uv_px"][i]
        body = {
            "plate": SPEC,
            "uv_px": d["uv_px"],
            "image_size": d["image_size"],
            "touches": [{"u": u + 1.5, "v": v - 1.0, "id": "B"}],
        }
        r = c.post("/api/plate/snap", json=body)
        assert r.status_code == 200, r.text
        assert r.json()["corners"][0]["index"] == i
        # a click where the board is out of view: no corner seen there, refused in the fit's words
        j = unseen[0]
        body["touches"] = [{"u": float(sim.true_uv_px[j, 0]), "v": float(sim.true_uv_px[j, 1]), "id": "E"}]
        r = c.post("/api/plate/snap", json=body)
        assert r.status_code == 422 and r.json()["field"] == "touches", r.text


class _Still:
    """A camera that shows one image (the source protocol's ``grab``)."""

    def __init__(self, image: np.ndarray):
        self.image = image

    def grab(self):
        return self.image.copy(), time.time()

    def close(self) -> None:
        pass


def test_cal_plate_on_a_partial_board_labels_the_corners_seen(sim, tmp_path):
    labels = _seen_labels(sim)
    ids = PlateSpec.parse(SPEC).ids()
    world = sim.placement.to_robot(sim.spec.points_mm())
    rng = np.random.default_rng(7)
    col = Collector(tmp_path / "store", _Still(sim.image), calibration="cell1")
    try:
        assert col.handle(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
        hidden = int(np.argmax(sim.true_uv_px[:, 0]))  # the corner farthest out of view
        reply = col.handle(f"CAL TOUCH {ids[hidden]},0,0,0")
        assert reply.startswith("ERR") and f"corner {ids[hidden]} of {SPEC}:11.25 is not seen" in reply, reply
        for label, i in labels.items():
            xyz = world[i] + rng.normal(0, 0.05, 3)
            reply = col.handle(f"CAL TOUCH {label}," + ",".join(f"{x:.4f}" for x in xyz))
            assert reply.startswith("OK"), reply
        end = col.handle("CAL END")
        assert end.startswith("OK"), end
    finally:
        col.close()
    cal = Calibration.load(tmp_path / "store" / "cell1.json")
    check = np.loadtxt(sim.check_csv.splitlines()[1:], delimiter=",", usecols=range(5))
    m = cal.map(check[:, :2], allow_outside=True)
    ok = np.isfinite(m.xyz_mm[:, 0]) & m.inside
    err = np.linalg.norm(m.xyz_mm[ok, :2] - check[ok, 2:4], axis=1)
    assert ok.sum() >= 10 and np.sqrt(np.mean(err**2)) < 3 * np.sqrt(np.mean(m.sigma_mm[ok] ** 2))
