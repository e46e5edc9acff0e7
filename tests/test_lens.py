"""The one lens model (eyetohand.geometry.lens) against OpenCV, and each of its users on its own mapping.

Reference recipe: ``cv2.projectPoints`` of the points (x, y, 1) with zero pose and K = I gives the
distorted normalised points; ``cv2.undistortPoints`` with a tight criterion (200 iterations, eps
1e-16) the ideal ones. OpenCV takes coefficients in the order (k1, k2, p1, p2[, k3]), as lens.py.
"""

import cv2
import numpy as np
import pytest

from eyetohand.core.errors import InputError
from eyetohand.geometry.camera import Camera
from eyetohand.geometry.lens import distort, matrix_to_rodrigues, rodrigues_to_matrix, undistort
from eyetohand.models.pinhole import PinholeCamera
from eyetohand.models.radial import HomographyRadial

TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)
# (k1, k2, p1, p2, k3): mild, strong with tangential and k3, radial only (fast path), tangential only,
# and 4 coefficients (k3 absent)
LENSES = [
    (-0.08, 0.12, 2e-4, -1e-4, 0.0),
    (-0.28, 0.12, 1.5e-3, -8e-4, -0.02),
    (-0.3, 0.4, 0.0, 0.0, 0.05),
    (0.0, 0.0, 2e-3, -1.5e-3, 0.0),
    (0.1, -0.05, 0.0, 0.0, 0.0),
]


def cv_distort(n, k):
    xyz = np.column_stack([n, np.ones(len(n))])
    out, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(k, float))
    return out.reshape(-1, 2)


def cv_undistort(d, k):
    out = cv2.undistortPoints(d.reshape(-1, 1, 2), np.eye(3), np.asarray(k, float), criteria=TIGHT)
    return out.reshape(-1, 2)


@pytest.fixture(scope="module")
def ideal():
    return np.random.default_rng(0).uniform(-0.45, 0.45, (len(LENSES), 400, 2))


def test_distort_matches_project_points_per_row_of_a_swarm(ideal):
    k = np.array(LENSES)
    ours = distort(ideal, k)  # (P, N, 2) points x (P, 5) coefficient rows
    assert ours.shape == ideal.shape
    for i, row in enumerate(LENSES):
        assert np.abs(ours[i] - cv_distort(ideal[i], row)).max() < 1e-13, row
    # one row keeps the points' shape; (N, 2) points against P rows broadcast to (P, N, 2)
    assert np.array_equal(distort(ideal[1], k[1]), ours[1])
    assert distort(ideal[0], k).shape == ideal.shape
    np.testing.assert_array_equal(distort(ideal[0], k[:, :4])[4], distort(ideal[0], k[4, :4]))


def test_undistort_matches_undistort_points_per_row_of_a_swarm(ideal):
    k = np.array(LENSES)
    d = distort(ideal, k)
    n, ok = undistort(d, k)
    assert ok.shape == d.shape[:2] and ok.all()
    for i, row in enumerate(LENSES):
        assert np.abs(n[i] - cv_undistort(d[i], row)).max() < 1e-12, row  # × 5000 px: < 1e-8 px
        assert np.abs(n[i] - ideal[i]).max() < 1e-13
    # 4 coefficients (k3 absent) and the radial-only path give the same as the general one
    n4, _ = undistort(d[4], np.array(LENSES[4][:4]))
    np.testing.assert_allclose(n4, n[4], rtol=0, atol=1e-15)


def test_a_few_points_take_the_plain_float_path_with_the_same_answer(ideal):
    for row in LENSES:
        k = np.array(row)
        d = distort(ideal[0, :40], k)
        many, ok = undistort(d, k)
        few = np.concatenate([undistort(d[i : i + 2], k)[0] for i in range(0, 40, 2)])
        assert ok.all() and np.abs(few - many).max() < 1e-15, row
        np.testing.assert_allclose(
            np.concatenate([distort(d[i : i + 1], k) for i in range(40)]), distort(d, k), rtol=0, atol=1e-16
        )
    one, ok1 = undistort(np.array([0.2, -0.1]), np.array(LENSES[1]))
    assert one.shape == (2,) and ok1.shape == () and bool(ok1)


@pytest.mark.parametrize("n_points", [1, 50])  # the plain-float and the vectorised path
def test_beyond_the_fold_is_nan_and_flagged(n_points):
    # k1 = -0.5: r (1 - 0.5 r²) peaks at 0.544 (r = 0.816); a distorted radius 0.7 has no ideal point,
    # and a tangential lens of the same kind folds too
    for k in (np.array([-0.5, 0.0, 0.0, 0.0]), np.array([-0.5, 0.0, 1e-3, 1e-3, 0.0])):
        far = np.tile([0.7 / np.sqrt(2), 0.7 / np.sqrt(2)], (n_points, 1))
        n, ok = undistort(far, k)
        assert not ok.any() and np.isnan(n).all()
        near = np.tile([0.2, 0.1], (n_points, 1))
        n, ok = undistort(np.vstack([near, far]), k)
        assert ok[:n_points].all() and not ok[n_points:].any()
        np.testing.assert_allclose(distort(n[:n_points], k), near, atol=1e-14)
    # a swarm: the row that folds is NaN, the other not
    d = np.full((2, 3, 2), 0.5)
    n, ok = undistort(d, np.array([[-0.5, 0, 0, 0], [-0.05, 0, 0, 0]]))
    assert ok.tolist() == [[False] * 3, [True] * 3]


def test_undistort_refuses_bad_shapes():
    with pytest.raises(InputError, match="k1, k2, p1, p2"):
        undistort(np.zeros((3, 2)), np.zeros(3))
    with pytest.raises(InputError, match="shape"):
        distort(np.zeros((3, 3)), np.zeros(5))


def test_rodrigues_both_ways_match_opencv_batched():
    rng = np.random.default_rng(2)
    r = rng.normal(size=(500, 3))
    r *= rng.uniform(0, np.pi, 500)[:, None] / np.linalg.norm(r, axis=1, keepdims=True)
    r[:3] = [[1e-9, -2e-9, 3e-10], [0, 0, 0], [1e-5, 0, 2e-5]]  # near zero: the series
    r[3:6] = [[np.pi - 1e-7, 0, 0], [0, -(np.pi - 1e-3), 0], [2.0, -1.0, 2.0]]  # near π
    R = rodrigues_to_matrix(r)
    ref = np.array([cv2.Rodrigues(v)[0] for v in r])
    assert R.shape == (500, 3, 3) and np.abs(R - ref).max() < 1e-14
    np.testing.assert_allclose(rodrigues_to_matrix(r[7]), R[7], rtol=0, atol=1e-15)  # the float path
    back = matrix_to_rodrigues(R)
    assert back.shape == (500, 3)
    ref_back = np.array([cv2.Rodrigues(m)[0].ravel() for m in R])
    th = np.linalg.norm(r, axis=1)
    mid = (th > 1e-3) & (th < np.pi - 1e-3)  # OpenCV itself loses digits near 0 and near π
    assert np.abs(back[mid] - ref_back[mid]).max() < 1e-12
    assert np.abs(back - r).max() < 1e-9  # the angles are in [0, π): the vectors themselves
    np.testing.assert_allclose(rodrigues_to_matrix(back), R, rtol=0, atol=1e-15)
    with pytest.raises(InputError, match="rotation 1: expected a 3x3 rotation"):
        matrix_to_rodrigues(np.stack([np.eye(3), np.diag([1.0, 1.0, -1.0])]))


# ---------------------------------------------------------------- the users of the lens, on their own maps


def test_camera_with_non_square_pixels_matches_opencv():
    cam = Camera.look_at(
        (40.0, -30.0, 480.0),
        (0.0, 0.0, 0.0),
        focal_px=3000.0,
        aspect=1.002,
        dist=LENSES[1],
        principal_point_px=(1230.0, 1015.0),
    )
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(-120, 120, (3000, 2)), rng.uniform(-20, 60, 3000)])
    ref, _ = cv2.projectPoints(xyz, np.array(cam.rvec), cam.t, cam.K, cam.dist)
    assert np.abs(cam.robot_to_image(xyz) - ref.reshape(-1, 2)).max() < 1e-8
    uv = rng.uniform([0, 0], [2447, 2047], (3000, 2))
    ref_n = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, criteria=TIGHT).reshape(-1, 2)
    assert np.abs(cam.image_to_normalized(uv) - ref_n).max() * cam.fx_px < 1e-8


def _plane_point(K, dist, rvec, t, uv, z):
    """OpenCV's answer: undistortPoints → ray → plane z (robot frame)."""
    n = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, criteria=TIGHT).reshape(-1, 2)
    R = cv2.Rodrigues(rvec)[0]
    ray = np.column_stack([n, np.ones(len(n))]) @ R
    c = -R.T @ t
    return c + ((z - c[2]) / ray[:, 2])[:, None] * ray


@pytest.mark.parametrize("aspect", ["free", "square"])
def test_camera_model_matches_opencv_for_every_particle(aspect):
    rng = np.random.default_rng(4)
    origin = np.array([20.0, 600.0, 170.0])
    base = np.array(
        [3000.0, 3004.0, 1230.0, 1015.0, -0.2, 0.1, 8e-4, -5e-4, 3.1, 0.05, -0.4, 5.0, -3.0, 300.0]
    )
    meta = {
        "origin_mm": origin.tolist(),
        "heights_mm": [150.0, 200.0],
        "image_size": [2448, 2048],
        "aspect": aspect,
    }
    if aspect == "square":
        base = np.delete(base, 1)
    model = PinholeCamera(base, meta)
    swarm = base + 1e-3 * np.abs(base) * rng.normal(size=(6, base.size))
    uv = rng.uniform([100, 100], [2300, 1900], (200, 2))
    z = rng.uniform(140, 210, 200)
    ours = model.batch_image_to_robot(swarm, uv, z)
    assert ours.shape == (6, 200, 3)
    for p, row in zip(ours, swarm, strict=True):
        cam = model.with_params(row).camera
        K, dist = np.array(cam["K"]), np.array(cam["dist"])
        rvec = cv2.Rodrigues(np.array(cam["R"]))[0]
        ref = _plane_point(K, dist, rvec, np.array(cam["t_mm"]), uv, z)
        assert np.abs(p - ref).max() < 1e-8
        xyz = ref
        proj, _ = cv2.projectPoints(xyz, rvec, np.array(cam["t_mm"]), K, dist)
        assert np.abs(model.with_params(row).robot_to_image(xyz) - proj.reshape(-1, 2)).max() < 1e-7


def test_camera_model_maps_beyond_the_fold_to_nan():
    model = PinholeCamera(
        np.array([3000.0, 1224.0, 1024.0, -0.6, 0.0, 0.0, 0.0, np.pi, 0, 0, 0, 0, 300.0]),
        {"origin_mm": [0.0, 0.0, 0.0], "heights_mm": [0.0, 50.0], "image_size": None},
    )
    out = model.batch_image_to_robot(
        model.params[None], np.array([[1224.0, 1024.0], [3500.0, 3000.0]]), np.zeros(2)
    )
    assert np.isfinite(out[0, 0]).all() and np.isnan(out[0, 1]).all()


def test_homography_radial_matches_opencv_on_its_own_lens():
    f, c, k1, k2 = 2800.0, np.array([1223.5, 1023.5]), -0.12, 0.09
    rng = np.random.default_rng(5)
    H = np.array([[0.07, 0.01, -80.0], [-0.008, 0.069, 540.0], [1e-7, -2e-7, 1.0]])  # ideal px → mm
    meta = {
        "T_uv": np.eye(3).tolist(),
        "T_xy": np.eye(3).tolist(),
        "plane_z_mm": 150.0,
        "centre_px": c.tolist(),
        "centre_source": "image-size",
        "focal_px": f,
        "k1": k1,
        "k2": k2,
        "lens_fit_rms_px": 0.0,
        "condition_number": 1.0,
    }
    model = HomographyRadial(H.reshape(-1)[:8], meta)
    K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])
    dist = np.array([k1, k2, 0.0, 0.0])
    uv = rng.uniform([0, 0], [2447, 2047], (500, 2))
    ideal = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, P=K, criteria=TIGHT).reshape(-1, 2)
    ref = np.column_stack([ideal, np.ones(len(ideal))]) @ H.T
    ref = ref[:, :2] / ref[:, 2:]
    got = model.image_to_robot(uv)
    assert np.abs(got[:, :2] - ref).max() < 1e-8 and np.all(got[:, 2] == 150.0)
    # and back: robot → ideal pixel → OpenCV's distortion
    n = (ideal - c) / f
    proj, _ = cv2.projectPoints(np.column_stack([n, np.ones(len(n))]), np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(model.robot_to_image(got) - proj.reshape(-1, 2)).max() < 1e-7
