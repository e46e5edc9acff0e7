"""Models: known answers against OpenCV, synthetic recovery with known noise, degenerate geometry,
round trips, and the batched forward map the solvers use."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import opencv_single_view_xy
from synth import grid_pairs, make_camera, project, random_pairs

from eyetohand import DegenerateError, InputError, PointPairs, calibrate, get_model
from eyetohand.models import MODELS

CHESS = Path(__file__).parent / "data" / "boofcv" / "sony_chess"


def rms(e):
    return float(np.sqrt(np.mean(np.square(e))))


def errors(model, pairs):
    return np.linalg.norm(model.residuals(pairs.uv_px, pairs.xyz_mm), axis=1)


# ---------------------------------------------------------------- known answers (OpenCV)


def test_affine_matches_opencv_estimate_affine2d():
    # Recipe: cv2.estimateAffine2D with a huge RANSAC threshold keeps every point as an inlier and
    # its LM refinement converges to the least-squares affine map.
    rng = np.random.default_rng(3)
    uv = rng.uniform(0, 2000, (30, 2))
    A = np.array([[0.07, -0.012, 15.0], [0.011, 0.069, 560.0]])
    xy = uv @ A[:, :2].T + A[:, 2] + rng.normal(scale=0.02, size=(30, 2))
    ours = get_model("affine").from_pairs(uv, np.c_[xy, np.zeros(30)])
    ref, inl = cv2.estimateAffine2D(uv, xy, ransacReprojThreshold=1e9, refineIters=100)
    assert inl.all()
    np.testing.assert_allclose(ours.matrix_image_to_robot[:2], ref, rtol=1e-6, atol=1e-8)


def test_homography_matches_opencv_find_homography():
    # Recipe: cv2.findHomography(method=0) = normalised DLT + LM on the destination (robot) error,
    # which is exactly our homography + lm.
    cam = make_camera(tilt_deg=15)
    pairs = random_pairs(cam, 40, noise_px=0.5)
    model, _ = _fit(pairs, "homography", "lm")
    H_cv, _ = cv2.findHomography(pairs.uv_px, pairs.xyz_mm[:, :2], 0)
    test_uv = project(
        cam, np.c_[np.random.default_rng(5).uniform(-50, 50, (20, 2)) + [20, 600], np.zeros(20)]
    )
    ref = cv2.perspectiveTransform(test_uv.reshape(-1, 1, 2), H_cv).reshape(-1, 2)
    np.testing.assert_allclose(model.image_to_robot(test_uv)[:, :2], ref, atol=2e-4)


def _fit(pairs, name, optimizer="lm", **kw):
    from eyetohand.calibration.fit import fit_model

    return fit_model(pairs, name, optimizer, **kw)


def _chess_frames():
    for f in sorted(CHESS.glob("*.jpg")):
        g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        for pat in ((4, 6), (6, 4)):
            ok, c = cv2.findChessboardCorners(g, pat)
            if ok:
                break
        assert ok, f
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
        c = cv2.cornerSubPix(g, c, (5, 5), (-1, -1), crit).reshape(-1, 2).astype(float)
        obj = np.array([[i * 30.0, j * 30.0] for j in range(pat[1]) for i in range(pat[0])])
        yield f.name, c, obj, g.shape[::-1]


def test_radial_matches_opencv_single_view_on_real_photos():
    """Real photos with strong barrel distortion (k1 ≈ -0.26): fit on half the chessboard corners,
    predict the other half. Reference: OpenCV calibrateCamera (one view, principal point fixed at the
    image centre, square pixels, k1 k2 only) + undistortPoints + findHomography."""
    ratios, gains = [], []
    for _name, uv, obj, (w, h) in _chess_frames():
        train = np.arange(len(uv)) % 2 == 0
        pairs = PointPairs.from_arrays(uv[train], obj[train])
        test = PointPairs.from_arrays(uv[~train], obj[~train])
        ours, _ = _fit(pairs, "homography-radial", "lm", image_size=(w, h))
        hom, _ = _fit(pairs, "homography", "lm")
        pred = opencv_single_view_xy(uv[train], obj[train], (w, h), focal_px=500.0)(uv[~train])
        ref = rms(np.linalg.norm(pred - obj[~train], axis=1))
        ratios.append(rms(errors(ours, test)) / ref)
        gains.append(rms(errors(hom, test)) / rms(errors(ours, test)))
    ratios = np.array(ratios)
    assert len(ratios) == 13
    assert ratios.max() < 1.05, ratios  # within 5 % of OpenCV's held-out error on every frame
    assert np.median(gains) > 2.0  # the distortion model more than halves the homography's error


# ---------------------------------------------------------------- synthetic recovery


@pytest.mark.parametrize("name", ["affine", "homography", "homography-radial", "paper"])
def test_noise_free_planar_recovery(name):
    # the camera looks straight down for the affine family to be exact
    tilt = 0.0 if name in ("affine", "paper") else 12.0
    dist = [-0.2, 0.05, 0, 0, 0] if name == "homography-radial" else None
    cam = make_camera(tilt_deg=tilt, dist=dist, pp_offset_px=(0.0, 0.0))  # distortion centre known
    pairs = grid_pairs(cam, 6, heights=(100.0,))
    check = random_pairs(cam, 30, heights=(100.0,), span_mm=110)
    model, _ = _fit(pairs, name, "lm", image_size=cam["size"])
    assert errors(model, check).max() < 1e-3


def test_dlt3d_recovers_distortion_free_camera_at_two_heights():
    cam = make_camera(tilt_deg=10)
    pairs = grid_pairs(cam, 5, heights=(150.0, 200.0))
    check = random_pairs(cam, 40, heights=(175.0, 220.0))
    model, _ = _fit(pairs, "dlt3d", "linear")
    assert errors(model, check).max() < 1e-3


def independent_dlt(uv, xyz):
    """Eq. (5) as printed, without normalisation: a34 = 1, plain least squares."""
    n = len(uv)
    A = np.zeros((2 * n, 11))
    A[0::2, 0:3], A[0::2, 3] = xyz, 1
    A[1::2, 4:7], A[1::2, 7] = xyz, 1
    A[0::2, 8:11] = -uv[:, :1] * xyz
    A[1::2, 8:11] = -uv[:, 1:2] * xyz
    a, *_ = np.linalg.lstsq(A, uv.reshape(-1), rcond=None)
    return np.append(a, 1).reshape(3, 4)


def test_dlt3d_with_noise_matches_independent_dlt():
    cam = make_camera(tilt_deg=10)
    pairs = grid_pairs(cam, 5, heights=(150.0, 200.0), noise_px=0.5, seed=7)
    check = random_pairs(cam, 60, heights=(175.0, 220.0), seed=8)
    model, _ = _fit(pairs, "dlt3d", "linear")
    P = independent_dlt(pairs.uv_px, pairs.xyz_mm)
    # map check points through the independent P: solve the 2x2 system per point
    u, v = check.uv_px.T
    z = check.xyz_mm[:, 2]
    a = P[0] - u[:, None] * P[2]
    b = P[1] - v[:, None] * P[2]
    M = np.stack([np.c_[a[:, 0], a[:, 1]], np.c_[b[:, 0], b[:, 1]]], axis=1)
    rhs = -np.c_[a[:, 2] * z + a[:, 3], b[:, 2] * z + b[:, 3]]
    xy = np.linalg.solve(M, rhs[..., None])[..., 0]
    ref_err = rms(np.linalg.norm(xy - check.xyz_mm[:, :2], axis=1))
    ours = rms(errors(model, check))
    assert ours < 0.3  # mm, sanity: 0.5 px noise at ~0.05 mm/px
    assert abs(ours - ref_err) <= 0.10 * ref_err


def test_radial_recovers_synthetic_distortion():
    cam = make_camera(tilt_deg=5, dist=[-0.25, 0.08, 0, 0, 0])
    pairs = grid_pairs(cam, 7, heights=(0.0,), noise_px=0.2, span_mm=160)
    check = random_pairs(cam, 80, span_mm=150, seed=9)
    radial, _ = _fit(pairs, "homography-radial", "lm", image_size=cam["size"])
    hom, _ = _fit(pairs, "homography", "lm")
    e_r, e_h = rms(errors(radial, check)), rms(errors(hom, check))
    assert e_r < 0.02  # mm: 0.2 px noise is 0.035 mm per point at 0.17 mm/px; the fit averages it
    assert e_h > 5 * e_r


# ---------------------------------------------------------------- degenerate geometry


def test_dlt3d_refuses_coplanar_pairs(paper_pairs):
    with pytest.raises(DegenerateError, match=r"coplanar.*z = 167\.417"):
        _fit(paper_pairs[0], "dlt3d", "linear")


@pytest.mark.parametrize("name", ["affine", "homography", "homography-radial", "paper"])
def test_collinear_pairs_refused(name):
    t = np.linspace(0, 1, 10)
    pairs = PointPairs.from_arrays(np.c_[100 * t, 50 * t + 3], np.c_[t, 2 * t, np.full(10, 5.0)])
    with pytest.raises(DegenerateError, match="collinear"):
        _fit(pairs, name, "linear")


@pytest.mark.parametrize("name", list(MODELS))
def test_too_few_pairs(name):
    cls = get_model(name)
    n = cls.min_pairs - 1
    rng = np.random.default_rng(0)
    pairs = PointPairs.from_arrays(
        rng.uniform(0, 100, (n, 2)), np.c_[rng.uniform(0, 10, (n, 2)), rng.uniform(1, 5, n)]
    )
    with pytest.raises(DegenerateError, match=rf"at least {cls.min_pairs} pairs"):
        _fit(pairs, name, "linear")


def test_single_height_model_refuses_several_heights():
    cam = make_camera()
    pairs = grid_pairs(cam, 4, heights=(150.0, 200.0))
    with pytest.raises(DegenerateError, match="one height"):
        _fit(pairs, "homography", "linear")


def test_unknown_model_lists_choices():
    with pytest.raises(InputError, match=r"unknown model 'foo'; choose one of: auto, affine"):
        get_model("foo")


def test_paper_model_on_coplanar_data_says_how_it_started(paper_pairs):
    cal = calibrate(paper_pairs[0], "paper", "linear", loo=False)
    assert cal.model.equation5_rank == 9
    assert any("rank 9 of 11" in n for n in cal.notes)
    z = cal.image_to_robot(paper_pairs[1].uv_px, allow_outside=True)[:, 2]
    np.testing.assert_allclose(z, 167.4166, atol=1e-9)  # not the degenerate Zc ≈ 0 solution
