"""The renderer: exact anti-aliasing, the truth it records, its knobs, its seeding and its speed."""

import time
from types import SimpleNamespace

import numpy as np
import pytest

from eyetohand.geometry.camera import Camera
from eyetohand.vision.render import Target, circle_truth, exact_conic, render


@pytest.fixture(scope="module")
def small_cam():
    """A 640×512 camera seeing the 5 mm circle about 60 px wide, tilted, with lens distortion."""
    return Camera.looking_down((640, 512), focal_px=3600.0, tilt_deg=10.0, dist=(-0.15, 0.1, 3e-4, -2e-4, 0))


def darkness_centroid(img, tr, level_out, level_in, full=65535.0, margin=3):
    """Centroid and total of (level_out − grey) in a disc window ``margin`` px larger than the circle."""
    f = img.astype(float) / full
    cx, cy = np.round(tr.centroid_px).astype(int)
    r = int(tr.diameter_px / 2) + margin
    yy, xx = np.mgrid[cy - r : cy + r + 1, cx - r : cx + r + 1]
    win = (level_out - f[yy, xx]) * (((xx - cx) ** 2 + (yy - cy) ** 2) <= r * r)
    m = win.sum()
    return np.array([(xx * win).sum(), (yy * win).sum()]) / m, m / (level_out - level_in)


def test_anti_aliasing_is_exact_area_coverage(small_cam):
    """No blur, no noise, 16 bits: the darkness-weighted centroid of the pixels is the area centroid of
    the projected disc, and its total the disc's area — so the anti-aliasing is exact coverage."""
    t = Target()
    for k, (x, y, a) in enumerate([(1.3, -2.1, 10), (-4.2, 3.3, 45), (5.1, 4.4, 80)]):
        img, tr = render(small_cam, (x, y, 0.0), angle_deg=a, blur_px=0, noise=0, vignetting=0, bits=16)
        c, area = darkness_centroid(img, tr, t.strip_level, t.circle_level)
        assert np.hypot(*(c - tr.centroid_px)) < 2e-3, k
        assert area == pytest.approx(np.pi * tr.axes_px[0] * tr.axes_px[1] / 4, rel=2e-4)
        # the imaged ellipse's centre is its area centroid; the image of the circle's centre is elsewhere
        assert np.hypot(*np.subtract(tr.ellipse_centre_px, tr.centroid_px)) < 1e-5
        assert tr.perspective_bias_px > 0.01


def test_blur_keeps_the_centroid(small_cam):
    t = Target()
    img, tr = render(small_cam, (2.2, -1.7, 0.0), angle_deg=33, blur_px=1.4, noise=0, vignetting=0, bits=16)
    c, area = darkness_centroid(img, tr, t.strip_level, t.circle_level, margin=7)
    assert np.hypot(*(c - tr.centroid_px)) < 3e-3
    sharp, _ = render(small_cam, (2.2, -1.7, 0.0), angle_deg=33, blur_px=0, noise=0, vignetting=0, bits=16)
    assert np.abs(img.astype(float) - sharp).max() > 1000  # the blur did something


def test_truth_without_distortion_is_the_exact_conic():
    """Without a lens the image of a circle is an exact conic: the sampled fit's centre equals the
    closed form H⁻ᵀCH⁻¹'s; with distortion the truth moves away from the lens-free conic."""
    straight = Camera.looking_down((2448, 2048), tilt_deg=20.0, dist=(0, 0, 0, 0, 0))
    bent = Camera.looking_down((2448, 2048), tilt_deg=20.0, dist=(-0.2, 0.1, 1e-3, 0, 0))
    for centre in [(0.0, 0.0, 0.0), (40.0, -25.0, 12.0), (-60.0, 30.0, -5.0)]:
        tr = circle_truth(straight, centre, 5.0)
        C, c = exact_conic(straight, centre, 5.0)
        assert np.hypot(*(np.array(tr.ellipse_centre_px) - c)) < 1e-8
        # points of the projected boundary lie on the conic
        th = np.linspace(0, 2 * np.pi, 7)
        ring = np.column_stack(
            [centre[0] + 2.5 * np.cos(th), centre[1] + 2.5 * np.sin(th), np.full(7, centre[2])]
        )
        uv1 = np.column_stack([straight.robot_to_image(ring), np.ones(7)])
        assert np.abs(np.einsum("ni,ij,nj->n", uv1, C / np.abs(C).max(), uv1)).max() < 1e-9
        bent_tr = circle_truth(bent, centre, 5.0)
        _, c_lensless = exact_conic(bent, centre, 5.0)
        if centre != (0.0, 0.0, 0.0):
            assert np.hypot(*(np.array(bent_tr.ellipse_centre_px) - c_lensless)) > 1.0
        assert np.hypot(*(np.array(bent_tr.ellipse_centre_px) - bent_tr.centroid_px)) < 1e-4


def test_perspective_bias_grows_with_tilt():
    """Seen straight down on the optical axis the circle's centre projects to the ellipse's centre;
    tilted, the two separate (the bias the detector does not correct)."""
    biases = []
    for tilt in (0.0, 10.0, 30.0):
        cam = Camera.looking_down((2448, 2048), tilt_deg=tilt, dist=(0, 0, 0, 0, 0))
        biases.append(circle_truth(cam, (0.0, 0.0, 0.0), 5.0).perspective_bias_px)
    assert biases[0] < 1e-9 and 0.01 < biases[1] < biases[2]


def test_levels_vignetting_noise_and_bits(small_cam):
    t = Target(belt_grain=0.0)
    clean, tr = render(small_cam, (0, 0, 0), target=t, blur_px=0, noise=0, vignetting=0, bits=16)
    u, v = np.round(tr.ellipse_centre_px).astype(int)
    assert clean[v, u] / 65535 == pytest.approx(t.circle_level, abs=1e-4)
    # a point of the strip 3 mm along its axis from the circle's centre
    su, sv = np.round(small_cam.robot_to_image([3.5, 0.0, 0.0])).astype(int)
    assert clean[sv, su] / 65535 == pytest.approx(t.strip_level, abs=1e-4)
    # vignetting: × (1 − v) at the corners, × 1 at the centre
    vig, _ = render(small_cam, (0, 0, 0), target=t, blur_px=0, noise=0, vignetting=0.3, bits=16)
    assert vig[0, 0] / clean[0, 0] == pytest.approx(0.7, abs=2e-3)
    assert vig[255, 319] / clean[255, 319] == pytest.approx(1.0, abs=2e-3)
    # noise: σ as a fraction of full scale
    noisy, _ = render(small_cam, (0, 0, 0), target=t, blur_px=0, noise=3 / 255, vignetting=0, bits=16, rng=1)
    assert np.std(noisy.astype(float) - clean) / 65535 * 255 == pytest.approx(3.0, rel=0.02)
    eight, _ = render(small_cam, (0, 0, 0), target=t, blur_px=0, noise=0, vignetting=0, bits=8)
    assert eight.dtype == np.uint8 and np.abs(eight.astype(float) - clean / 257).max() <= 0.51
    with pytest.raises(ValueError, match="bits"):
        render(small_cam, (0, 0, 0), bits=12)


def test_render_is_seeded_and_has_the_requested_depth(small_cam):
    a, _ = render(small_cam, (0, 0, 0), rng=3)
    b, _ = render(small_cam, (0, 0, 0), rng=np.random.default_rng(3))
    c, _ = render(small_cam, (0, 0, 0), rng=4)
    assert a.dtype == np.uint8 and (a == b).all() and (a != c).any()
    d, _ = render(small_cam, (0, 0, 0), rng=3, bits=16)
    assert d.dtype == np.uint16 and d.max() > 255


def test_belt_is_textured_and_fixed_in_the_robot_frame(small_cam):
    """Away from the strip two images with the target elsewhere show the same belt, and it has texture
    at several scales (sinusoids and grain)."""
    a, _ = render(small_cam, (-8.0, 0.0, 0.0), angle_deg=90, noise=0, blur_px=0, vignetting=0, bits=16)
    b, _ = render(small_cam, (8.0, 0.0, 0.0), angle_deg=90, noise=0, blur_px=0, vignetting=0, bits=16)
    same = a == b
    assert same.mean() > 0.6
    smooth, _ = render(
        small_cam,
        (-8.0, 0.0, 0.0),
        angle_deg=90,
        target=Target(belt_grain=0),
        noise=0,
        blur_px=0,
        vignetting=0,
        bits=16,
    )
    waves = smooth[same].astype(float) / 65535
    grain = a[same].astype(float) / 65535 - waves
    assert 0.02 < waves.std() < 0.1  # the sinusoids
    assert 0.01 < grain.std() < 0.03  # the grain, σ 0.02 of full scale
    # the grain is fine: neighbouring pixels differ, but less than independent noise would
    g = np.where(same, a.astype(float) / 65535 - smooth.astype(float) / 65535, np.nan)
    step = np.nanstd(np.diff(g, axis=1))
    assert 0.1 * grain.std() < step < 1.0 * grain.std()


def test_any_opencv_style_camera_renders_the_same(small_cam):
    duck = SimpleNamespace(
        K=small_cam.K, dist=small_cam.dist, R=small_cam.R, t=small_cam.t, image_size=small_cam.image_size
    )
    a, ta = render(small_cam, (1.0, 1.0, 0.0), rng=2)
    b, tb = render(duck, (1.0, 1.0, 0.0), rng=2)
    assert np.abs(a.astype(int) - b).max() <= 1
    assert ta.ellipse_centre_px == pytest.approx(tb.ellipse_centre_px)


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_full_size_render_time():
    """2448×2048 with a 60 mm strip across the view: well under two seconds (measured ~0.4 s)."""
    cam = Camera.looking_down((2448, 2048), tilt_deg=8.0)
    times = []
    for k in range(2):
        t0 = time.perf_counter()
        img, _ = render(cam, (3.0, -2.0, 0.0), angle_deg=45 + 10 * k, rng=k)
        times.append(time.perf_counter() - t0)
    print(f"render 2448x2048: {min(times):.3f} s")
    assert img.shape == (2048, 2448) and min(times) < 1.5
