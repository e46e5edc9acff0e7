"""Automatic model choice: never much worse than a homography without distortion, and gains what
the distortion model gains with it."""

import numpy as np
from synth import grid_pairs, make_camera, random_pairs

from eyetohand import calibrate


def rms_on(cal, check):
    return cal.check.rms_mm


def test_auto_without_distortion_is_as_good_as_homography():
    for seed in range(3):
        cam = make_camera(tilt_deg=12, seed=seed)
        pairs = grid_pairs(cam, 5, heights=(100.0,), noise_px=0.3, seed=seed + 10)
        check = random_pairs(cam, 60, heights=(100.0,), seed=seed + 20)
        auto = calibrate(pairs, "auto", check=check, loo=False)
        hom = calibrate(pairs, "homography", check=check, loo=False)
        assert auto.check.rms_mm <= 1.10 * hom.check.rms_mm, (seed, auto.model_name)


def test_auto_with_distortion_gains_what_the_distortion_model_gains():
    cam = make_camera(tilt_deg=8, dist=[-0.22, 0.05, 0, 0, 0])
    pairs = grid_pairs(cam, 6, heights=(100.0,), noise_px=0.3, span_mm=160)
    check = random_pairs(cam, 60, heights=(100.0,), span_mm=150)
    auto = calibrate(pairs, "auto", check=check, image_size=cam["size"], loo=False)
    hom = calibrate(pairs, "homography", check=check, loo=False)
    rad = calibrate(pairs, "homography-radial", check=check, image_size=cam["size"], loo=False)
    assert auto.model_name == "homography-radial"
    assert auto.check.rms_mm <= 1.05 * rad.check.rms_mm
    assert auto.check.rms_mm < 0.5 * hom.check.rms_mm


def test_auto_with_few_pairs_never_takes_more_unknowns_than_supported():
    cam = make_camera(tilt_deg=12)
    # 8 pairs = 16 equations: a homography (8 unknowns) can be cross-validated, the distortion
    # model (10) cannot; with 5 pairs only the affine (6) can
    pairs = grid_pairs(cam, 3, heights=(100.0,), noise_px=0.3).subset(range(8))
    cal = calibrate(pairs, "auto", loo=False)
    rows = {r["model"]: r for r in cal.selection["candidates"]}
    assert rows["homography-radial"]["considered"] is False
    assert rows["homography-radial"]["why"] == "needs at least 9 pairs, have 8"
    assert rows["homography"]["considered"] is True
    assert cal.model_name in ("affine", "homography")
    cal5 = calibrate(pairs.subset(range(5)), "auto", loo=False)
    assert cal5.model_name == "affine"
    assert np.isfinite(cal.train.rms_mm)
