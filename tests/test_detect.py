"""Target detection: accuracy on exact renders, against OpenCV, on real dot-grid photos, and the
refusals (no target, ambiguous, cut, unreadable files)."""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from eyetohand import InputError, detect_circles, detect_target
from eyetohand.geometry.camera import Camera
from eyetohand.vision import Miss
from eyetohand.vision.detect import annotate, fit_ellipse, load_image
from eyetohand.vision.render import Target, render

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
DOTS = Path(__file__).parent / "data" / "boofcv" / "sony_circle_regular"


def err(d, truth):
    return float(np.hypot(d.u - truth.ellipse_centre_px[0], d.v - truth.ellipse_centre_px[1]))


@pytest.fixture(scope="module")
def small_cam():
    """A 640×512 camera seeing the 5 mm circle about 60 px wide, tilted, with lens distortion."""
    return Camera.looking_down((640, 512), focal_px=3600.0, tilt_deg=10.0, dist=(-0.15, 0.1, 3e-4, -2e-4, 0))


# ---------------------------------------------------------------- accuracy


def test_full_size_renders_beat_simpleblobdetector():
    """2448×2048 renders, blur σ 0.6–1.4 px, noise σ 1–3 grey levels (the benchmark's scenes): every
    target found, no error above 0.06 px, median ≤ 0.7× SimpleBlobDetector's on the same images."""
    from bench_detect import blob_detector, scenes

    sbd = blob_detector()
    ours, theirs = [], []
    for img, truth, _, _ in scenes(4, seed=11):
        d = detect_target(img)
        assert d.ok, d.reason
        ours.append(err(d, truth))
        kp = sbd.detect(img)
        theirs.append(
            min(
                np.hypot(k.pt[0] - truth.ellipse_centre_px[0], k.pt[1] - truth.ellipse_centre_px[1])
                for k in kp
            )
        )
    print(
        f"median error: ours {np.median(ours):.4f} px, SimpleBlobDetector {np.median(theirs):.4f} px; "
        f"max ours {max(ours):.4f} px"
    )
    assert max(ours) < 0.06
    assert np.median(ours) <= 0.7 * np.median(theirs)


@pytest.mark.parametrize("blur, noise, seed", [(0.6, 1, 0), (1.0, 2, 1), (1.4, 3, 2), (1.4, 1, 3)])
def test_accuracy_over_blur_and_noise(small_cam, blur, noise, seed):
    rng = np.random.default_rng(seed)
    for _ in range(3):
        xy = rng.uniform(-5, 5, 2)
        img, tr = render(
            small_cam, (*xy, 0.0), angle_deg=rng.uniform(0, 180), blur_px=blur, noise=noise / 255, rng=rng
        )
        d = detect_target(img)
        assert d.ok and d.polarity == "dark" and err(d, tr) < 0.06, (d.reason, err(d, tr) if d.ok else None)
        assert d.diameter_px == pytest.approx(tr.diameter_px, abs=0.15)
        assert 0.5 < d.score <= 1
        # the intensity model fitted, and its edge spread is the blur with the pixel's own (1/12 px²)
        assert d.method == "intensity"
        assert d.blur_px == pytest.approx(np.hypot(blur, np.sqrt(1 / 12)), rel=0.1)


def test_intensity_fit_beats_the_edge_points_it_starts_from():
    """The intensity-model fit against the edge-point ellipse it is seeded with (``refine="edge"``), on
    the same full-size renders: the fit is the more accurate (median over 4 images); seeded with the
    wrong polarity it refuses (then the edge fit is kept)."""
    from bench_detect import scenes

    from eyetohand.vision.detect import noise_sigma
    from eyetohand.vision.detect.refine import _fit_intensity

    fit_err, edge_err = [], []
    for img, truth, _, _ in scenes(4, seed=5):
        d = detect_target(img)
        e = detect_target(img, refine="edge")
        assert d.ok and d.method == "intensity" and e.ok and e.method == "edge" and e.blur_px is None
        fit_err.append(err(d, truth))
        edge_err.append(err(e, truth))
        grey = img.astype(np.float32)
        assert _fit_intensity(grey, e.ellipse, -1.0, noise_sigma(grey)) is None
        assert _fit_intensity(grey, e.ellipse, 1.0, noise_sigma(grey)) is not None
    print(
        f"median error: intensity fit {np.median(fit_err):.4f} px, edge points {np.median(edge_err):.4f} px"
    )
    assert np.median(fit_err) < np.median(edge_err)
    with pytest.raises(InputError, match="refine"):
        detect_target(img, refine="moments")


def test_uneven_light_bright_target_and_16_bit(small_cam):
    img, tr = render(small_cam, (2.0, 1.0, 0.0), angle_deg=30, blur_px=1.0, noise=2 / 255, rng=5, bits=16)
    ramp = np.linspace(0.25, 1.0, img.shape[1])[None, :] * np.linspace(1.0, 0.6, img.shape[0])[:, None]
    dim = np.rint(img * ramp).astype(np.uint16)  # light falls from 100 % to 15 % across the image
    d = detect_target(dim)
    assert d.ok and err(d, tr) < 0.06, d.reason
    bright = Target(circle_level=0.9, strip_level=0.15, belt_level=0.5)
    img, tr = render(
        small_cam, (-3.0, 2.0, 0.0), angle_deg=70, target=bright, blur_px=1.2, noise=2 / 255, rng=6
    )
    d = detect_target(img)
    assert d.ok and d.polarity == "bright" and err(d, tr) < 0.06, d.reason
    assert not detect_target(img, polarity="dark").ok


def test_image_formats_give_the_same_centre(small_cam, tmp_path):
    img, tr = render(small_cam, (1.0, 2.0, 0.0), angle_deg=20, blur_px=1.0, noise=1 / 255, rng=7, bits=16)
    img8 = (img >> 8).astype(np.uint8)
    files = {
        "a.png": img,
        "b.png": img8,
        "c.bmp": img8,
        "d.tif": img,
        "e.jpg": img8,
        "f.png": cv2.cvtColor(img8, cv2.COLOR_GRAY2BGR),
    }
    for name, a in files.items():
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if name.endswith(".jpg") else []
        assert cv2.imwrite(str(tmp_path / name), a, params)
        d = detect_target(tmp_path / name)
        assert d.ok, (name, d.reason)
        assert err(d, tr) < (0.1 if name.endswith(".jpg") else 0.06), name
    assert load_image(tmp_path / "a.png")[2] == 65535.0 and load_image(tmp_path / "b.png")[2] == 255.0


# ---------------------------------------------------------------- refusals


def canvas(h=480, w=640, bg=200.0):
    return np.full((h, w), bg, np.float32)


def disc(img, cx, cy, r, level):
    """A disc drawn at 4× and area-averaged down (anti-aliased)."""
    big = np.zeros((img.shape[0] * 4, img.shape[1] * 4), np.uint8)
    centre = (int(round((4 * cx + 1.5) * 16)), int(round((4 * cy + 1.5) * 16)))
    cv2.circle(big, centre, int(round(4 * r * 16)), 255, -1, cv2.LINE_8, 4)
    cov = cv2.resize(big.astype(np.float32) / 255, img.shape[::-1], interpolation=cv2.INTER_AREA)
    return img + (level - img) * cov


def finish(img, seed=0, blur=1.0, noise=2.0):
    img = cv2.GaussianBlur(img, (0, 0), blur) if blur else img
    img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


REFUSALS = {
    "blank": (lambda: finish(canvas(), noise=0, blur=0), "no contrast"),
    "flat with noise": (lambda: finish(canvas()), "no target found"),
    "noise only": (
        lambda: np.random.default_rng(1).integers(0, 256, (480, 640)).astype(np.uint8),
        "no target found",
    ),
    "two equal circles": (
        lambda: finish(disc(disc(canvas(), 200.3, 200.7, 30, 30), 450, 260, 30, 30)),
        "ambiguous: 2",
    ),
    "a square": (lambda: finish(cv2.rectangle(canvas(), (250, 180), (310, 240), 30, -1)), "no target found"),
    "a square at 45°": (
        lambda: finish(
            cv2.fillPoly(canvas(), [np.array([[300, 150], [345, 195], [300, 240], [255, 195]])], 30)
        ),
        "no target found",
    ),
    "a circle cut by the border": (
        lambda: finish(disc(canvas(), 620, 200, 40, 30)),
        "cut by the image border",
    ),
}


#: the kind each refusal says it is (Detection.miss), for callers that act on it without its words
MISSES = {"two equal circles": Miss.AMBIGUOUS, "a circle cut by the border": Miss.CUT_BY_BORDER}


@pytest.mark.parametrize("case", REFUSALS)
def test_refusals_give_a_reason_and_no_centre(case):
    make, words = REFUSALS[case]
    d = detect_target(make())
    assert not d.ok and d.u is None and d.v is None and d.diameter_px is None
    assert words in d.reason and "\n" not in d.reason
    assert d.miss is MISSES.get(case, Miss.NOT_FOUND)


def test_a_lone_disc_is_found_and_the_hint_or_roi_resolve_two():
    one = finish(disc(canvas(), 300.3, 200.7, 30, 30))
    d = detect_target(one)
    assert d.ok and d.miss is None and np.hypot(d.u - 300.3, d.v - 200.7) < 0.05
    two = finish(disc(disc(canvas(), 200.3, 200.7, 30, 30), 450.2, 260.4, 15, 30))
    assert "ambiguous" in detect_target(two).reason
    d = detect_target(two, diameter_px=60)
    assert d.ok and abs(d.u - 200.3) < 0.1 and abs(d.v - 200.7) < 0.1
    d = detect_target(two, roi=(380, 180, 150, 150))
    assert d.ok and abs(d.u - 450.2) < 0.1 and abs(d.v - 260.4) < 0.1
    assert len(detect_circles(two)) == 2


def test_unreadable_files_raise_one_line_naming_the_file(tmp_path):
    ok, png = cv2.imencode(".png", finish(disc(canvas(), 300, 200, 30, 30)))
    (tmp_path / "trunc.png").write_bytes(png.tobytes()[: len(png) // 2])
    (tmp_path / "text.png").write_text("not an image\n")
    (tmp_path / "empty.png").write_bytes(b"")
    cv2.imwrite(str(tmp_path / "one.png"), np.zeros((1, 1), np.uint8))
    (tmp_path / "dir.png").mkdir()
    for name, words in [
        ("missing.png", "no such file"),
        ("trunc.png", "truncated PNG"),
        ("text.png", "not an image"),
        ("empty.png", "empty file"),
        ("one.png", "1x1 px"),
        ("dir.png", "folder"),
    ]:
        with pytest.raises(InputError, match=words) as info:
            detect_target(tmp_path / name)
        assert str(tmp_path / name) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(InputError, match="polarity"):
        detect_target(np.zeros((20, 20)), polarity="grey")
    with pytest.raises(InputError, match="roi"):
        detect_target(np.zeros((20, 20)), roi=(10, 10, 50, 50))


def test_annotate_draws_the_ellipse_and_the_centre():
    img = finish(disc(canvas(), 300.3, 200.7, 30, 30))
    d = detect_target(img)
    out = annotate(img, d)
    assert out.shape == (480, 640, 3) and out.dtype == np.uint8
    green = (out[:, :, 1] > 200) & (out[:, :, 2] < 100)
    ys, xs = np.nonzero(green)
    r = np.hypot(xs - 300.3, ys - 200.7)
    assert len(r) > 100 and np.all(np.abs(r - 30) < 2)
    assert out[201, 300, 2] > 200 and out[201, 300, 1] < 100  # the red cross at the centre


def test_fit_ellipse_recovers_a_known_ellipse():
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    a, b, ang = 40.0, 25.0, np.radians(30)
    x, y = a * np.cos(t), b * np.sin(t)
    pts = np.column_stack(
        [x * np.cos(ang) - y * np.sin(ang) + 100.25, x * np.sin(ang) + y * np.cos(ang) + 50.5]
    )
    c, axes, angle, *_ = fit_ellipse(pts)
    assert np.allclose(c, [100.25, 50.5], atol=1e-9) and np.allclose(axes, [80, 50], atol=1e-8)
    assert angle == pytest.approx(30.0, abs=1e-6)


# ---------------------------------------------------------------- real photos: BoofCV dot grids


def _blob():
    """SimpleBlobDetector tuned for these frames: the dots are 20–40 px across (area 300–1300 px²).
    With the default-like area range 10–10⁵ px² the clip's small features join the grid search and
    findCirclesGrid fails on image00000; from a minimum area of 20 px² up it succeeds on all six
    (with CALIB_CB_CLUSTERING for the two steepest views)."""
    p = cv2.SimpleBlobDetector_Params()
    p.minArea, p.maxArea = 50, 3000
    return cv2.SimpleBlobDetector_create(p)


def _opencv_grid(grey):
    """findCirclesGrid's ordered centres (10 columns × 8 rows, symmetric, per calibration_target.yaml),
    or None when it fails."""
    for flags in (cv2.CALIB_CB_SYMMETRIC_GRID, cv2.CALIB_CB_SYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING):
        ok, c = cv2.findCirclesGrid(grey, (10, 8), flags=flags, blobDetector=_blob())
        if ok:
            return c.reshape(-1, 2).astype(float)
    return None


def test_detect_circles_on_real_dot_grid_photos():
    """BoofCV's sony_circle_regular (640×480 JPEG, 10 × 8 dots of 15 mm, 25 mm apart): every dot
    found (and nothing else), each within 0.5 px of findCirclesGrid's centre, and a homography
    (board mm ← px, findHomography method 0) fitted on half the dots predicts the other half at least
    as well from our centres as from OpenCV's."""
    board = np.array([[25.0 * (k % 10), 25.0 * (k // 10)] for k in range(80)])
    train = np.arange(80) % 2 == 0

    def held_out(uv):
        H, _ = cv2.findHomography(uv[train], board[train], 0)
        pred = cv2.perspectiveTransform(uv[~train].reshape(-1, 1, 2), H).reshape(-1, 2)
        return np.sqrt(np.mean(np.sum((pred - board[~train]) ** 2, axis=1)))

    frames = sorted(DOTS.glob("*.jpg"))
    assert len(frames) == 6
    ours_rms, ref_rms, worst = [], [], []
    for f in frames:
        grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ref = _opencv_grid(grey)
        assert ref is not None, f.name
        ours = np.array([[d.u, d.v] for d in detect_circles(f)])
        assert len(ours) == 80, f.name  # the dots, nothing else (no duplicates, no clip features)
        dist = np.linalg.norm(ref[:, None] - ours[None], axis=2)
        match = dist.argmin(axis=1)
        assert len(np.unique(match)) == 80, f.name  # one of ours for each of OpenCV's
        worst.append(dist.min(axis=1).max())
        assert worst[-1] < 0.5, f.name
        ours = ours[match]  # in OpenCV's grid order
        ours_rms.append(held_out(ours))
        ref_rms.append(held_out(ref))
    pairs = zip(ours_rms, ref_rms, strict=True)
    print("\nmax distance to findCirclesGrid px:", [f"{w:.3f}" for w in worst])
    print("held-out rms mm, ours/OpenCV:", [f"{a:.4f}/{b:.4f}" for a, b in pairs])
    assert np.sqrt(np.mean(np.square(ours_rms))) <= np.sqrt(np.mean(np.square(ref_rms)))
    assert max(a / b for a, b in zip(ours_rms, ref_rms, strict=True)) < 1.02


def test_a_small_circle_in_a_large_image_is_found():
    """A 24 px circle in a 2000×1600 image is below the downscaled search's size: the full-scale search
    finds it."""
    img = finish(disc(canvas(1600, 2000), 1200.4, 700.6, 12, 30))
    d = detect_target(img)
    assert d.ok and np.hypot(d.u - 1200.4, d.v - 700.6) < 0.06, d.reason


def test_the_windowed_candidate_search_finds_what_the_whole_image_search_finds():
    """The search labels only windows around what a looser search at half the scale finds: on the
    benchmark's full-size renders and on two circles of a large image (the ambiguous case) it gives the
    same candidates as labelling the whole image at every level, without covering the whole image."""
    from bench_detect import scenes

    from eyetohand.vision.detect import noise_sigma
    from eyetohand.vision.detect.search import _candidates, _search_scale

    two = finish(disc(disc(canvas(1600, 2000), 500.3, 600.7, 40, 30), 1450.2, 960.4, 40, 30))
    images = [img for img, _, _, _ in scenes(3, seed=21)] + [two]
    for img in images:
        grey = load_image(img)[0]
        sigma, f = noise_sigma(grey), _search_scale(grey.shape, None)
        fast, fast_rej, everywhere = _candidates(grey, sigma, "auto", None, f)
        full, full_rej, _ = _candidates(grey, sigma, "auto", None, f, everywhere=True)
        assert not everywhere and len(fast) >= 1
        assert [(c.x, c.y, c.diameter, c.polarity, c.levels) for c in fast] == [
            (c.x, c.y, c.diameter, c.polarity, c.levels) for c in full
        ]
    assert len(fast) == 2 and "ambiguous" in detect_target(two).reason


def test_two_targets_of_one_size_get_a_hint_that_can_help(tmp_path, capsys):
    """Two equal circles: the expected diameter cannot choose, so the refusal says what can (a crop,
    a mask or a region), and `detect --roi` then finds the one asked for."""
    from eyetohand.cli import main as cli_main

    two = finish(disc(disc(canvas(), 200.3, 200.7, 30, 30), 450.2, 260.4, 30, 30))
    for d in (detect_target(two), detect_target(two, diameter_px=60)):
        assert d.reason.startswith("ambiguous: 2") and "diameter" not in d.reason.split("px;")[-1]
        assert "--roi X Y W H" in d.reason and "crop or mask" in d.reason
    sizes = finish(disc(disc(canvas(), 200.3, 200.7, 30, 30), 450.2, 260.4, 12, 30))
    assert detect_target(sizes).reason.endswith("give the expected diameter to choose")
    d = detect_target(two, diameter_px=60, roi=(350, 150, 200, 220))
    assert d.ok and abs(d.u - 450.2) < 0.1 and abs(d.v - 260.4) < 0.1
    path = tmp_path / "two.png"
    cv2.imwrite(str(path), np.clip(two, 0, 255).astype(np.uint8))
    assert cli_main(["detect", str(path), "--diameter", "60"]) == 2
    assert "--roi X Y W H" in capsys.readouterr().err
    assert (
        cli_main(["detect", str(path), "--diameter", "60", "--roi", "350", "150", "200", "220", "--json"])
        == 0
    )
    import json

    rec = json.loads(capsys.readouterr().out)["results"][0]
    assert abs(rec["u"] - 450.2) < 0.1 and abs(rec["v"] - 260.4) < 0.1
    assert cli_main(["detect", str(path), "--roi", "-1", "0", "10", "10"]) == 2
    assert "--roi: expected" in capsys.readouterr().err


def test_noise_sigma_by_counting_equals_the_median_definition():
    """The noise σ of integer images is computed from a histogram of the neighbour differences: it
    must equal 1.4826 · median(|d − median(d)|) / √2 computed with np.median (odd and even counts,
    half-integer medians, 8- and 16-bit ranges), and a non-integer image takes np.median itself."""
    import math

    from eyetohand.vision.detect import noise_sigma

    rng = np.random.default_rng(3)
    for i in range(40):
        h, w = rng.integers(64, 300, 2)
        spread = rng.uniform(0.5, 6) * (300 if i % 4 == 3 else 1)
        a = np.rint(rng.normal(30000 if i % 4 == 3 else 120, spread, (h, w))).astype(np.float32)
        if i % 4 == 2:
            a += rng.uniform(0, 0.5, a.shape).astype(np.float32)  # not integer grey levels
        d = np.diff(a[:: max(1, min(16, h // 64))], axis=1).ravel()
        ref = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2)
        assert noise_sigma(a) == pytest.approx(ref, rel=1e-6)


@pytest.mark.parametrize("diameter", [700.0, 1e300])
def test_a_diameter_larger_than_the_image_is_refused(diameter):
    """No target is larger than its image; 1e300 was an OverflowError (an internal error)."""
    img = np.full((480, 640), 200, np.uint8)
    with pytest.raises(InputError, match=r"diameter_px .* px is larger than the 640x480 image"):
        detect_target(img, diameter_px=diameter)
    with pytest.raises(InputError, match="larger than the 640x480 image"):
        detect_circles(img, diameter_px=diameter)
