"""The circle target's perspective bias corrected (issue 31 part 4): on a rendered, tilted cell the
corrected fit maps the true centres' pixels nearer, on a square-on view it changes nothing; the
ellipse centre agrees with the closed form; the diameter is refused in the same words by the
library, the CLI and HTTP, and a calibration file keeps it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from synth import detect_rendered, limit_view, plane_grid

from eyetohand import Calibration, PointPairs
from eyetohand.calibration import (
    FitRequest,
    calibrate_request,
    corrected_centres_px,
    ellipse_centres_px,
    fit_corrected,
)
from eyetohand.cli import main
from eyetohand.core import InputError
from eyetohand.geometry import Camera
from eyetohand.server.app import create_app
from eyetohand.vision.render import circle_truth

SIZE = (1920, 1200)
DISTANCE_MM = 800.0
DIAMETER_MM = 20.0


def camera(tilt_deg: float) -> Camera:
    """benchmarks/bias.py's cell: f 2400 px, the plane 800 mm along the axis, tilted ``tilt_deg``."""
    return limit_view(tilt_deg, DISTANCE_MM, SIZE)


def detected(cam: Camera, xyz_mm: np.ndarray, rng) -> np.ndarray:
    """The targets rendered at ``xyz_mm`` and found by ``detect_target``."""
    return detect_rendered(cam, xyz_mm, DIAMETER_MM, rng)


@pytest.fixture(scope="module")
def cells():
    """Per tilt (20°, 0°): training pairs of rendered, detected 20 mm targets on a 5×5 grid, exact
    robot positions; check: an 8×8 grid of other plane points and their centres' exact pixels."""
    out = {}
    for tilt in (20.0, 0.0):
        cam = camera(tilt)
        train = plane_grid(cam, 5, 0.1, 0.9)
        check = plane_grid(cam, 8, 0.14, 0.86)
        pairs = PointPairs.from_arrays(detected(cam, train, np.random.default_rng(31)), train)
        out[tilt] = cam, pairs, check, cam.robot_to_image(check)
    return out


def check_rms_mm(cal: Calibration, check: np.ndarray, uv_px: np.ndarray) -> float:
    err = cal.image_to_robot(uv_px, allow_outside=True, part_diameter_mm=0.0)[:, :2] - check[:, :2]
    return float(np.sqrt((err**2).sum(axis=1).mean()))


def fit(pairs: PointPairs, diameter_mm: float | None) -> Calibration:
    request = FitRequest.from_names("homography", image_size=SIZE, loo=False, target_diameter_mm=diameter_mm)
    return calibrate_request(request, pairs)


def test_the_correction_removes_the_bias_on_a_tilted_view(cells):
    _, pairs, check, uv_true = cells[20.0]
    before = check_rms_mm(fit(pairs, None), check, uv_true)
    after = check_rms_mm(fit(pairs, DIAMETER_MM), check, uv_true)
    # r² sin θ / Z = 100 · 0.342 / 800 mm = 43 µm before; what is left is the detector's noise
    assert before > 0.03, before
    assert after < 0.5 * before, (before, after)


def test_the_correction_changes_nothing_square_on(cells):
    _, pairs, check, uv_true = cells[0.0]
    before = check_rms_mm(fit(pairs, None), check, uv_true)
    after = check_rms_mm(fit(pairs, DIAMETER_MM), check, uv_true)
    assert abs(after - before) < 1e-3, (before, after)  # 1 µm


def test_the_ellipse_centre_is_the_closed_forms(cells):
    """Against the renderer's own ellipse (circle_truth) and the conic H⁻ᵀ C H⁻¹ of the plane→image
    homography H = K [r1 r2 t] (Hartley & Zisserman 8.2: a conic maps by the inverse transpose)."""
    cam = cells[20.0][0]
    xyz = plane_grid(cam, 3, 0.1, 0.9)
    got = ellipse_centres_px(cam.robot_to_image, xyz, DIAMETER_MM)
    truth = np.array([circle_truth(cam, X, DIAMETER_MM).ellipse_centre_px for X in xyz])
    H = cam.K @ np.column_stack([cam.R[:, 0], cam.R[:, 1], np.ravel(cam.t)])
    Hi = np.linalg.inv(H)
    r = DIAMETER_MM / 2
    for k, (x, y, _) in enumerate(xyz):
        C = np.array([[1, 0, -x], [0, 1, -y], [-x, -y, x * x + y * y - r * r]])
        E = Hi.T @ C @ Hi
        centre = np.linalg.solve(E[:2, :2], -E[:2, 2])
        assert np.allclose(got[k], centre, atol=1e-6), (got[k], centre)
    assert np.allclose(got, truth, atol=1e-4)
    assert np.abs(got - cam.robot_to_image(xyz)).max() > 0.05  # the bias this test is about


def test_corrected_centres_with_the_calibrations_maps(cells):
    cam, pairs, _, _ = cells[20.0]
    cal = fit(pairs, DIAMETER_MM)
    xyz = plane_grid(cam, 4, 0.2, 0.8)
    ellipse = np.array([circle_truth(cam, X, DIAMETER_MM).ellipse_centre_px for X in xyz])
    moved = corrected_centres_px(cal, ellipse, DIAMETER_MM, 0.0)
    assert np.abs(moved - cam.robot_to_image(xyz)).max() < 0.01  # px; the bias is ≈ 0.12 px
    with pytest.raises(InputError, match="target_diameter_mm must be a finite number of mm above 0"):
        corrected_centres_px(cal, ellipse, 0.0)


BAD = [0, -1.0, float("nan"), float("inf"), True, "20"]


@pytest.mark.parametrize("bad", BAD)
def test_a_bad_diameter_is_refused_in_the_same_words(cells, bad, capsys, tmp_path):
    with pytest.raises(InputError) as made:
        FitRequest(target_diameter_mm=bad)
    words = str(made.value)
    assert words.startswith("target_diameter_mm must be a finite number of mm above 0, got ")
    assert "\n" not in words
    if not isinstance(bad, (bool, str)):  # argparse reads a number; JSON has no nan or inf
        assert main(["calibrate", "nope.csv", f"--target-diameter-mm={bad}"]) == 2
        assert capsys.readouterr().err.strip() == f"error: {words}"
    if not (isinstance(bad, float) and not np.isfinite(bad)):
        with TestClient(create_app(tmp_path / "data")) as client:
            pairs = cells[20.0][1].to_records()
            r = client.post(
                "/api/calibrations", json={"name": "x", "pairs": pairs, "target_diameter_mm": bad}
            )
        assert r.status_code == 422, r.text
        assert r.json()["field"] == "target_diameter_mm"
        if not isinstance(bad, (bool, str)):  # pydantic's own words for a wrong type
            assert r.json()["error"] == f"target_diameter_mm: {words}"


def test_the_file_keeps_the_diameter(cells, tmp_path):
    _, pairs, _, _ = cells[20.0]
    cal = fit(pairs, DIAMETER_MM)
    path = cal.save(tmp_path / "cal.json")
    back = Calibration.load(path)  # proves the stored (corrected) pairs reproduce the statistics
    extra = back.fit.extra
    assert extra["target_diameter_mm"] == DIAMETER_MM and extra["centre_correction_passes"] == 2
    assert extra["detected_sha256"] == pairs.sha256() != back.data_sha256
    assert 0.05 < extra["centre_shift_px_rms"] < 0.3  # the bias here, 0.12 px
    assert np.array_equal(back.model.params, cal.model.params)
    assert "target_diameter_mm" not in fit(pairs, None).fit.to_dict()
    assert any("correct a detection of the same target before mapping" in n for n in back.notes)


def test_the_cli_and_http_fit_with_the_diameter(cells, tmp_path, capsys):
    _, pairs, _, _ = cells[20.0]
    csv = tmp_path / "pairs.csv"
    csv.write_text(pairs.to_csv_text())
    out = tmp_path / "cal.json"
    argv = ["calibrate", str(csv), "--model", "homography", "--image-size", "1920x1200"]
    assert main([*argv, "--target-diameter-mm", "20", "-o", str(out)]) == 0, capsys.readouterr().err
    by_cli = Calibration.load(out)
    want = calibrate_request(
        FitRequest.from_names("homography", image_size=SIZE, target_diameter_mm=20.0), pairs
    )
    assert np.array_equal(by_cli.model.params, want.model.params)
    assert by_cli.fit.extra["target_diameter_mm"] == 20.0
    with TestClient(create_app(tmp_path / "data")) as client:
        body = {"name": "c", "pairs": pairs.to_records(), "model": "homography", "image_size": list(SIZE)}
        r = client.post("/api/calibrations", json={**body, "target_diameter_mm": 20})
        assert r.status_code == 201, r.text
        cal_id = r.json()["id"]
        arrows = r.json()["summary"]["vectors"]["train"]  # of the centres as fitted: no bias left
        assert max(np.hypot(a["du_px"], a["dv_px"]) for a in arrows) < 0.05  # the bias is ≈ 0.12 px
        again = client.get(f"/api/calibrations/{cal_id}").json()["summary"]["vectors"]["train"]
        assert again == arrows
        stored = json.loads(client.get(f"/api/calibrations/{cal_id}/export").text)
    assert stored["fit"]["target_diameter_mm"] == 20.0
    assert np.allclose(stored["model"]["params"], want.model.params, rtol=0, atol=0)


def test_fit_corrected_needs_a_diameter(cells):
    with pytest.raises(InputError, match="target_diameter_mm"):
        fit_corrected(lambda p, c, last: None, cells[0.0][1], None, None)  # type: ignore[arg-type]


def test_evaluate_and_verify_take_detections_as_the_fit_did(cells):
    """Pairs detected with the same target, checked against a corrected calibration, are corrected
    as its training pairs were: the training pairs score their own statistics, not the bias."""
    from eyetohand.calibration import evaluate_pairs, verify

    _, pairs, _, _ = cells[20.0]
    cal = fit(pairs, DIAMETER_MM)
    assert abs(evaluate_pairs(cal, pairs).stats.rms_mm - cal.train.rms_mm) < 1e-4  # 0.1 µm
    v = verify(cal, pairs, 0.005)  # the bias alone would be ≈ 0.04 mm at every pair
    assert v.passed, v.norm_mm.max()
    plain = fit(pairs, None)
    assert abs(evaluate_pairs(plain, pairs).stats.rms_mm - plain.train.rms_mm) < 1e-12


def test_the_pairs_a_corrected_calibration_was_fitted_on_are_known_again(cells):
    """as_fitted: the detections it was fitted on become its stored pairs bit for bit, its stored
    pairs stay as they are (never corrected twice), so a report on the pairs as detected shows them
    as the training pairs, not as 'given pairs' with a warning."""
    from eyetohand.calibration import as_fitted
    from eyetohand.reports.report import build_report

    _, pairs, _, _ = cells[20.0]
    cal = fit(pairs, DIAMETER_MM)
    assert cal.pairs is not None
    assert as_fitted(cal, pairs) is cal.pairs and as_fitted(cal, cal.pairs) is cal.pairs
    other = pairs.subset(np.arange(20))  # not the fitted set: corrected with the final maps
    moved = as_fitted(cal, other).uv_px - other.uv_px
    assert np.abs(moved - (cal.pairs.uv_px[:20] - pairs.uv_px[:20])).max() < 1e-3  # px
    html, _ = build_report(cal, train_pairs=pairs)
    assert "is not the data this calibration was fitted on" not in html


@pytest.mark.parametrize("model", ["dlt3d", "camera"])
def test_the_correction_at_two_heights(cells, model):
    """The multi-height models: each pair corrected at its own height (the renderer's exact ellipse
    centres + 0.006 px noise, the detector's error; the 20° cell at z = 0 and 100 mm)."""
    cam = cells[20.0][0]
    grid = plane_grid(cam, 5, 0.1, 0.9)
    train = np.vstack([grid, grid + [0, 0, 100.0]])
    check = plane_grid(cam, 8, 0.14, 0.86)
    check = np.vstack([check, check + [0, 0, 50.0]])
    rng = np.random.default_rng(7)
    ellipse = np.array([circle_truth(cam, X, DIAMETER_MM).ellipse_centre_px for X in train])
    pairs = PointPairs.from_arrays(ellipse + rng.normal(0, 0.006, ellipse.shape), train)
    uv_true = cam.robot_to_image(check)
    errors = []
    for diameter in (None, DIAMETER_MM):
        request = FitRequest.from_names(
            model, image_size=SIZE, loo=False, seed=0, target_diameter_mm=diameter
        )
        cal = calibrate_request(request, pairs)
        err = (
            cal.image_to_robot(uv_true, check[:, 2], allow_outside=True, part_diameter_mm=0.0)[:, :2]
            - check[:, :2]
        )
        errors.append(float(np.sqrt((err**2).sum(axis=1).mean())))
    assert errors[0] > 0.03 and errors[1] < 0.5 * errors[0], errors  # r² sin θ / Z ≈ 43 µm at z = 0
