"""The fast paths give what the general ones give: one-point maps vs the batch map, closed-form and
warm-started leave-one-out vs full refits; and start-up stays light (no SciPy, OpenCV, matplotlib or
FastAPI imported by the CLI or the calibration module)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
HEAVY = ("scipy", "cv2", "matplotlib", "fastapi")


@pytest.mark.parametrize("module", ["eyetohand.cli", "eyetohand.calibration.file", "eyetohand"])
def test_import_does_not_pull_heavy_packages(module):
    code = f"import json, sys; import {module}; print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == []


@pytest.mark.parametrize("name", ["affine", "homography", "homography-radial", "paper", "dlt3d", "camera"])
def test_loading_a_calibration_and_mapping_a_point_pulls_no_heavy_package(name, tmp_path):
    """What ``eyetohand apply CAL --uv U V`` does — load a file (which re-proves its statistics, its
    outlier flags included) and map one guarded point with sigma — imports none of SciPy, OpenCV,
    matplotlib, FastAPI (SciPy alone costs ~0.2 s of start-up)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from synth import grid_pairs, make_camera

    from eyetohand.calibration.fit import calibrate

    if name in ("dlt3d", "camera"):
        pairs = grid_pairs(make_camera(dist=[-0.05, 0.01, 0, 0, 0], seed=3), 4, heights=(0.0, 40.0), seed=6)
        z = "20.0"
    else:
        pairs = load_pairs(PAPER)
        z = "None"
    path = tmp_path / "cal.json"
    calibrate(pairs, name, "lm").save(path)
    u, v = pairs.uv_px.mean(axis=0).tolist()
    code = (
        "import json, sys; from eyetohand.calibration.file import Calibration; "
        f"r = Calibration.load({str(path)!r}).map([{u}, {v}], {z}); "
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    )
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == []


def test_chi2_quantile_without_scipy_equals_scipys():
    """The outlier test's χ² quantile, in closed form (no SciPy on a calibration's load), against
    SciPy's ``2 gammainccinv(dof/2, q)``."""
    from scipy.special import gammainccinv

    from eyetohand.solve.evaluate import _chi2_isf

    for dof in range(1, 9):
        for q in (0.999, 0.9, 0.5, 0.1, 1e-2, 1e-4, 1e-4 / 7, 1e-8, 1e-4 / 10**6, 1e-12, 1e-15):
            assert _chi2_isf(q, dof) == pytest.approx(2.0 * gammainccinv(dof / 2.0, q), rel=1e-12, abs=0)


# ---------------------------------------------------------------- one-parameter-set fast paths

import numpy as np  # noqa: E402

from eyetohand.calibration.fit import fit_model  # noqa: E402
from eyetohand.core.errors import InputError  # noqa: E402
from eyetohand.core.pairs import load_pairs  # noqa: E402

PAPER = SRC / "eyetohand" / "data" / "paper" / "calibration_points.csv"


def _compare(model, uv, z):
    """Fast paths (many points, each point alone) against the batch map: equal to 1e-12 mm."""
    batch = model.batch_image_to_robot(model.params[None], uv, z)[0]
    zq = None if model.height_rule.value == "computed" else z
    many = model.image_to_robot(uv, zq)
    np.testing.assert_allclose(many, batch, rtol=0, atol=1e-12)
    for i in range(0, len(uv), max(1, len(uv) // 40)):
        zi = None if zq is None else float(z[i])
        for form in (uv[i], uv[i : i + 1], tuple(uv[i].tolist()), [uv[i].tolist()]):
            np.testing.assert_allclose(model.image_to_robot(form, zi), batch[i : i + 1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["affine", "homography", "homography-radial", "paper"])
def test_planar_fast_paths_equal_the_batch_map(name):
    pairs = load_pairs(PAPER)
    model, _ = fit_model(pairs, name, "lm")
    rng = np.random.default_rng(3)
    n = 20_000  # several chunks
    uv = rng.uniform(pairs.uv_px.min(0) - 200, pairs.uv_px.max(0) + 200, size=(n, 2))
    _compare(model, uv, np.full(n, float(pairs.xyz_mm[0, 2])))
    # no z: the plane's (and the one-point path refuses a non-finite pixel like the general one)
    assert model.image_to_robot(uv[0])[0, 2] == pytest.approx(model.image_to_robot(uv[:2])[0, 2], abs=0)
    with pytest.raises(Exception, match="finite"):
        model.image_to_robot((float("nan"), 1.0))


@pytest.mark.parametrize("name", ["camera", "dlt3d"])
def test_camera_fast_paths_equal_the_batch_map(name):
    sys.path.insert(0, str(Path(__file__).parent))
    from synth import grid_pairs, make_camera

    cam = make_camera(dist=[-0.08, 0.02, 1e-3, -5e-4, 0])
    pairs = grid_pairs(cam, heights=(0.0, 40.0), noise_px=0.05)
    model, _ = fit_model(pairs, name, "lm", image_size=(2448, 2048))
    rng = np.random.default_rng(4)
    n = 20_000
    uv = rng.uniform(pairs.uv_px.min(0) - 200, pairs.uv_px.max(0) + 200, size=(n, 2))
    _compare(model, uv, rng.uniform(-10, 50, n))


@pytest.mark.parametrize("name", ["affine", "homography", "homography-radial"])
def test_closed_form_params_jacobian_matches_differences(name):
    from eyetohand.solve.uncertainty import _steps

    pairs = load_pairs(PAPER)
    model, _ = fit_model(pairs, name, "lm")
    uv = pairs.uv_px[:7] + 3.0
    z = np.full(len(uv), model.plane_z_mm)
    p, h = model.params, _steps(model.params)
    rows = np.vstack([p + np.diag(h), p - np.diag(h)])
    out = model.batch_image_to_robot(rows, uv, z)[..., :2]
    D = len(p)
    numeric = np.moveaxis((out[:D] - out[D:]) / (2 * h)[:, None, None], 0, -1)
    closed = model.params_jacobian(uv, z)
    scale = np.abs(numeric).max()
    np.testing.assert_allclose(closed, numeric, rtol=0, atol=1e-6 * scale)
    one = np.concatenate([model.params_jacobian(uv[i : i + 1], z[i : i + 1]) for i in range(len(uv))])
    np.testing.assert_allclose(one, closed, rtol=1e-12, atol=1e-15 * scale)


@pytest.fixture(params=["compiled", "fallback"])
def rows_path(request, monkeypatch):
    """The lens-free planar maps of many pixels, by the compiled loop (eyetohand.models._rows) or, as where
    it could not be built, by NumPy and OpenCV."""
    from eyetohand.models import base

    if request.param == "fallback":
        monkeypatch.setattr(base, "_ROWS", None)
    else:
        assert base.rows_kernel() is not None
    return request.param


def test_compiled_loop_is_built():
    """The install builds the compiled loop (setup.py; optional only for machines without a C
    compiler): CI's machine has one, so its figures and tests are of the loop users get."""
    from eyetohand.models import _rows
    from eyetohand.models.base import rows_kernel

    assert rows_kernel() is _rows


@pytest.mark.parametrize("name", ["affine", "homography", "paper"])
def test_compiled_loop_equals_the_numpy_chunks_bit_for_bit(name, monkeypatch):
    """The compiled loop does the NumPy chunks' arithmetic in their order (no fused multiply-add):
    the same bits for every point — a horizon point's ±inf or NaN too — whatever the input's
    layout (a strided view, Fortran order, integers) or z (the plane's, one number, one per point)."""
    from eyetohand.models import base

    pairs = load_pairs(PAPER)
    model, _ = fit_model(pairs, name, "lm")
    rng = np.random.default_rng(11)
    n = 3 * base.MAP_CHUNK + 17  # several NumPy chunks
    uv = rng.uniform(pairs.uv_px.min(0) - 900, pairs.uv_px.max(0) + 900, size=(n, 2))
    if name == "homography":  # the horizon w = 0 (and points beside it)
        h = model.matrix_image_to_robot
        uv[:4, 1] = -(h[2, 0] * uv[:4, 0] + h[2, 2]) / h[2, 1]
    z_each = rng.uniform(-50, 150, n)
    inputs = [uv, np.asfortranarray(uv), np.column_stack([uv, uv])[:, ::2], np.rint(uv).astype(np.int64)]
    zs = [None, 42.5, z_each] if name != "paper" else [None]
    fast = [model.image_to_robot(u, z) for u in inputs for z in zs]
    monkeypatch.setattr(base, "_ROWS", None)
    slow = [model.image_to_robot(u, z) for u in inputs for z in zs]
    for a, b in zip(fast, slow, strict=True):
        assert a.shape == (n, 3) and a.flags.c_contiguous
        np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))
    if name == "homography":
        assert not np.isfinite(fast[0][:4, :2]).all() or np.abs(fast[0][:4, :2]).max() > 1e6


def test_compiled_loop_refuses_what_it_cannot_read():
    """The compiled functions check their buffers (type, layout, size) and raise, never read past one."""
    from eyetohand.models import _rows

    uv = np.zeros((5, 2))
    h = np.eye(3).ravel()
    out = np.empty((5, 3))
    assert _rows.planar_rows(uv, h, True, 1.0, out) is True
    with pytest.raises(ValueError, match="out: expected 15 float64 values"):
        _rows.planar_rows(uv, h, True, 1.0, np.empty((4, 3)))
    with pytest.raises(ValueError, match="z: expected 5 float64 values"):
        _rows.planar_rows(uv, h, True, np.zeros(4), out)
    with pytest.raises(ValueError, match="h: expected 9"):
        _rows.planar_rows(uv, h[:6], False, 1.0, out)
    with pytest.raises(ValueError, match="uv: expected float64 values in groups of 2"):
        _rows.planar_rows(np.zeros(3), h, True, 1.0, out)
    with pytest.raises(ValueError, match="uv: expected float64"):
        _rows.planar_rows(uv.astype(np.float32), h, True, 1.0, out)
    with pytest.raises(TypeError, match="uv: expected a C-contiguous float64"):
        _rows.planar_rows(np.asfortranarray(np.zeros((5, 2))), h, True, 1.0, out)
    with pytest.raises(TypeError, match="out: expected a C-contiguous writable"):
        ro = np.empty((5, 3))
        ro.flags.writeable = False
        _rows.affine3_rows(uv, h, 0.0, 0.0, ro)
    uv[2, 1] = np.nan
    assert _rows.affine3_rows(uv, h, 0.0, 0.0, out) is False


@pytest.mark.parametrize("name", ["affine", "homography", "paper"])
def test_many_points_equal_the_numpy_map(name, rows_path):
    """From CV_MIN_POINTS points the affine-family maps go through the compiled loop or, without
    it, OpenCV; either must equal the elementwise NumPy path of smaller batches (and the batch map)
    to 1e-9 mm, the horizon included for a homography."""
    from eyetohand.models.base import CV_CHUNK, CV_MIN_POINTS

    pairs = load_pairs(PAPER)
    model, _ = fit_model(pairs, name, "lm")
    rng = np.random.default_rng(7)
    n = max(CV_MIN_POINTS, 2 * CV_CHUNK) + 123  # several chunks and a short one
    uv = rng.uniform(pairs.uv_px.min(0) - 500, pairs.uv_px.max(0) + 500, size=(n, 2))
    z = np.full(n, float(pairs.xyz_mm[0, 2]))
    if name == "homography":  # points on the horizon w = 0, where OpenCV would write (0, 0)
        h = model.matrix_image_to_robot
        u = uv[:5, 0]
        uv[:5, 1] = -(h[2, 0] * u + h[2, 2]) / h[2, 1]
    zq = None if name == "paper" else z
    fast = model.image_to_robot(uv, zq)
    slow = np.concatenate(
        [
            model.image_to_robot(uv[s : s + 5000], None if zq is None else zq[s : s + 5000])
            for s in range(0, n, 5000)
        ]
    )
    assert fast.shape == (n, 3)
    np.testing.assert_allclose(fast[5:], slow[5:], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.isfinite(fast), np.isfinite(slow))
    if name == "homography":
        big = np.abs(slow[:5, :2]) > 1e6
        assert (~np.isfinite(slow[:5, :2]) | big).all()  # the horizon: not mapped to (0, 0)
        finite = np.isfinite(slow[:5])
        np.testing.assert_allclose(fast[:5][finite], slow[:5][finite], rtol=1e-9)
    else:
        np.testing.assert_allclose(fast[:5], slow[:5], rtol=0, atol=1e-9)
    batch = model.batch_image_to_robot(model.params[None], uv[5:], z[5:])[0]
    np.testing.assert_allclose(fast[5:], batch, rtol=0, atol=1e-9)
    if name != "paper":  # one height for all the points: a number, or None (the plane)
        for zone in (None, float(z[0])):
            np.testing.assert_allclose(model.image_to_robot(uv[5:], zone), batch, rtol=0, atol=1e-9)


# ---------------------------------------------------------------- leave-one-out without refits


def _loo_cases():
    sys.path.insert(0, str(Path(__file__).parent))
    from synth import grid_pairs, make_camera

    paper = load_pairs(PAPER)
    cam = make_camera(dist=[-0.05, 0.01, 0, 0, 0], seed=3)
    cell = grid_pairs(cam, n_side=5, noise_px=0.15, seed=5)  # 25 pairs, one height
    cell3 = grid_pairs(cam, n_side=4, heights=(0.0, 40.0), noise_px=0.15, seed=6)
    return [
        ("paper data", paper, "affine", "linear"),
        ("paper data", paper, "affine", "lm"),
        ("paper data", paper, "homography", "lm"),
        ("simulated cell", cell, "homography", "lm"),
        ("simulated cell", cell, "affine", "lm"),
        ("simulated cell, two heights", cell3, "dlt3d", "lm"),
    ]


@pytest.mark.parametrize("case", range(6))
def test_gauss_newton_leave_one_out_matches_refits(case):
    from eyetohand.calibration.fit import cross_validate, loo_gauss_newton

    what, pairs, name, opt = _loo_cases()[case]
    full, _ = fit_model(pairs, name, opt)
    fast = loo_gauss_newton(full, pairs.uv_px, pairs.xyz_mm)
    assert fast is not None, f"{what}, {name}: the Gauss–Newton leave-one-out fell back"
    refits = cross_validate(pairs, name, opt, refit=True)
    np.testing.assert_allclose(fast, refits, rtol=0, atol=1e-6)
    assert np.abs(fast).max() > 1e-3  # real held-out errors, not zeros
    np.testing.assert_array_equal(cross_validate(pairs, name, opt), fast)


def test_leave_one_out_falls_back_where_the_lens_is_refitted():
    from eyetohand.calibration.fit import _loo_warm
    from eyetohand.models import get_model
    from eyetohand.solve import get_objective, get_solver

    def warm(model: str, optimizer: str, objective: str) -> bool:
        return _loo_warm(get_model(model), get_solver(optimizer), get_objective(objective))

    assert not warm("homography-radial", "lm", "l2")
    assert not warm("homography", "lm", "huber")
    assert not warm("homography", "linear", "l2")
    assert warm("affine", "linear", "l2") and warm("homography", "lm", "l2")


def _radial_cases():
    sys.path.insert(0, str(Path(__file__).parent))
    from synth import grid_pairs, make_camera

    cam = make_camera(tilt_deg=8, dist=[-0.22, 0.05, 0, 0, 0])
    cam3 = make_camera(dist=[-0.05, 0.01, 0, 0, 0], seed=3)
    cam4 = make_camera(tilt_deg=12, dist=[-0.1, 0.02, 0, 0, 0], seed=1)
    return [
        (grid_pairs(cam, 5, heights=(100.0,), noise_px=0.3, span_mm=160), cam["size"]),
        (grid_pairs(cam3, n_side=5, noise_px=0.15, seed=5), cam3["size"]),
        (grid_pairs(cam4, n_side=6, noise_px=0.2, seed=2), cam4["size"]),
    ]


@pytest.mark.parametrize("case", range(3))
def test_warm_started_lens_leave_one_out_matches_refits(case, monkeypatch):
    """homography-radial's held-out fits warm-started from the full lens fit give the refits'
    held-out residuals: within 1e-6 mm of refits converged tightly (measured ≤ 4.1e-7 mm under the
    Haswell, SkylakeX and Sandybridge kernels: two converged fits of the same flat-bottomed valley),
    and within that plus MINPACK's own stopping error of the refits as calibrate does them (at
    LENS_FIT_TOL = 1e-8). That stopping error depends on every step's rounding — 1.3e-6 mm under
    Haswell, 1.9e-6 under SkylakeX, where a fixed 2e-6 held on one kernel only — so it is bounded
    here as the refits' distance from the tightly converged ones."""
    from eyetohand.calibration.fit import cross_validate
    from eyetohand.models import radial

    pairs, size = _radial_cases()[case]
    fast = radial.HomographyRadial.leave_one_out(pairs.uv_px, pairs.xyz_mm, image_size=size)
    model = radial.HomographyRadial.from_pairs(pairs.uv_px, pairs.xyz_mm, image_size=size)
    terms = model.constants["lens_terms"]
    if "centre" in terms:  # each held-out fit chooses its own centre: refits
        assert fast is None
        return
    assert fast is not None, "the warm-started leave-one-out fell back"
    np.testing.assert_array_equal(cross_validate(pairs, "homography-radial", image_size=size), fast)

    def same_terms(uv, xy, centre, f_default, centre_test=True):
        """The refits fit the full fit's lens terms, as the held-out fits do (not their own choice)."""
        p, rms = radial.fit_lens(uv, xy, centre, f_default, k2="k2" in terms)
        return p, np.asarray(centre, float), terms, rms

    monkeypatch.setattr(radial, "choose_lens", same_terms)
    today = cross_validate(pairs, "homography-radial", refit=True, image_size=size)
    monkeypatch.setattr(radial, "LENS_FIT_TOL", 1e-14)
    tight = cross_validate(pairs, "homography-radial", refit=True, image_size=size)
    np.testing.assert_allclose(fast, tight, rtol=0, atol=1e-6)
    # so |fast − today| ≤ 1e-6 + |today − tight| (the triangle inequality), and today's refits stop
    # short of the minimum only by LENS_FIT_TOL's stopping error (1e-8 relative steps, ~1e-6 mm here),
    # not at another minimum (refits that do, where the view does not tell f, differ by up to 0.06 mm)
    assert np.abs(today - tight).max() < 1e-5
    assert np.abs(fast).max() > 1e-3


def _straight_on_cases():
    sys.path.insert(0, str(Path(__file__).parent))
    from synth import grid_pairs, make_camera

    level = make_camera(tilt_deg=0.0, dist=[-0.1, 0.03, 0, 0, 0], seed=1)
    tilted = make_camera(tilt_deg=12.0, seed=0)  # no image size: the points' centre is no principal point
    return [
        ("the paper's pairs", load_pairs(PAPER), 2e-6),
        ("a level camera with a lens", grid_pairs(level, 5, heights=(100.0,), noise_px=0.2, seed=3), 1e-5),
        ("a tilted camera, no lens", grid_pairs(tilted, 5, heights=(100.0,), noise_px=0.3, seed=10), 2e-5),
    ]


@pytest.mark.parametrize("case", range(3))
def test_lens_leave_one_out_holds_f_where_the_view_does_not_tell_it(case, monkeypatch):
    """Where the view does not tell the focal length, the held-out lens fits are the full fit refined
    on each subset with f held (a refit from its own start ends wherever that start puts it along
    the valley of equal (f, k1, k2)). They are SciPy's Levenberg–Marquardt with its own forward
    differences converged tightly, to the case's tolerance (the batched Jacobian only changes
    rounding, which the valley's shallow remainder turns into up to ~5e-6 mm here); every held-out lens
    keeps the full fit's f and moves k1 or the pose; ``cross_validate`` takes them, no refits."""
    from scipy.optimize import least_squares

    from eyetohand.calibration.fit import cross_validate
    from eyetohand.models import radial

    what, pairs, tol_mm = _straight_on_cases()[case]
    uv, xy = pairs.uv_px, pairs.xyz_mm[:, :2]
    centre, f_default, _ = radial._centre(uv, None)
    assert not radial.lens_start(uv, xy, centre, f_default)[1], f"{what}: the view tells f here"
    p_full, _, terms, _ = radial.choose_lens(uv, xy, centre, f_default, centre_test=False)
    free = radial.lens_free("k2" in terms)[1:]
    lenses = []
    held = radial.lens_refit_holding_focal
    monkeypatch.setattr(radial, "lens_refit_holding_focal", lambda *a: lenses.append(held(*a)) or lenses[-1])
    fast = radial.HomographyRadial.leave_one_out(pairs.uv_px, pairs.xyz_mm)
    assert fast is not None and len(lenses) == len(pairs)
    assert all(p[0] == p_full[0] for p in lenses)
    assert all(np.abs(p[1:] - p_full[1:]).max() > 0 for p in lenses)
    np.testing.assert_array_equal(cross_validate(pairs, "homography-radial"), fast)

    def scipy_held_f(p, uv_s, xy_s, c, k2=True):
        def with_q(q):
            out = np.array(p, float)
            out[free] = q
            return out

        sol = least_squares(
            lambda q: (radial.project_plane(with_q(q), xy_s, c) - uv_s).ravel(),
            p[free],
            method="lm",
            x_scale="jac",
            ftol=1e-14,
            xtol=1e-14,
            gtol=1e-14,
        )
        return with_q(sol.x)

    monkeypatch.setattr(radial, "lens_refit_holding_focal", scipy_held_f)
    reference = radial.HomographyRadial.leave_one_out(pairs.uv_px, pairs.xyz_mm)
    np.testing.assert_allclose(fast, reference, rtol=0, atol=tol_mm)
    assert np.abs(fast).max() > 1e-3


@pytest.mark.parametrize("name", ["affine", "homography", "paper"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_many_points_refuse_a_non_finite_pixel_anywhere(name, bad, rows_path):
    """The compiled loop tests every pixel's exponent bits, the OpenCV path each chunk's L1 norm: a
    NaN or ±inf anywhere — the first chunk, a middle one, the short last one — is refused with
    as_uv's words, and nothing is returned; the small-array path refuses it the same."""
    from eyetohand.models.base import CV_CHUNK, CV_MIN_POINTS

    pairs = load_pairs(PAPER)
    model, _ = fit_model(pairs, name, "lm")
    n = max(CV_MIN_POINTS, 2 * CV_CHUNK) + 77
    base = np.random.default_rng(3).uniform(pairs.uv_px.min(0), pairs.uv_px.max(0), size=(n, 2))
    for row, col in ((0, 0), (CV_CHUNK + 5, 1), (n - 1, 0)):
        uv = base.copy()
        uv[row, col] = bad
        with pytest.raises(InputError, match="image points must be finite numbers"):
            model.image_to_robot(uv)
        with pytest.raises(InputError, match="image points must be finite numbers"):
            model.image_to_robot(uv[max(row - 3, 0) : row + 3])


def test_lens_fit_rows_equal_scipys_own_differences_bit_for_bit():
    """The lens fit's forward differences in one batched projection: ``project_plane_rows`` equals
    ``project_plane`` row by row bit for bit, so on a view that tells f the lens fit takes SciPy's
    default Levenberg–Marquardt iterates exactly (same evaluations, same answer)."""
    from scipy.optimize import least_squares

    from eyetohand.models import radial

    sys.path.insert(0, str(Path(__file__).parent))
    from synth import grid_pairs, make_camera

    cam = make_camera(tilt_deg=8, dist=[-0.22, 0.05, 0, 0, 0])
    pairs = grid_pairs(cam, 5, heights=(100.0,), noise_px=0.3, span_mm=160)
    uv, xy = pairs.uv_px, pairs.xyz_mm[:, :2]
    centre, f_default, _ = radial._centre(uv, cam["size"])
    p0, told = radial.lens_start(uv, xy, centre, f_default)
    assert told
    rng = np.random.default_rng(3)
    P = p0 + rng.normal(size=(40, 9)) * np.maximum(np.abs(p0), 1e-3) * 1e-3
    rows = radial.project_plane_rows(P, xy, centre)
    one = np.stack([radial.project_plane(p, xy, centre) for p in P])
    np.testing.assert_array_equal(rows.view(np.int64), one.view(np.int64))
    tol = radial.LENS_FIT_TOL
    scipy_own = least_squares(
        lambda p: (radial.project_plane(p, xy, centre) - uv).ravel(),
        p0,
        method="lm",
        x_scale="jac",
        ftol=tol,
        xtol=tol,
        gtol=tol,
    )
    ours = radial._lens_least_squares(p0, uv, xy, centre, np.arange(9))
    assert ours.nfev == scipy_own.nfev
    np.testing.assert_array_equal(ours.x, scipy_own.x)


@pytest.mark.parametrize("failure", ["raises", "not finite"])
def test_held_focal_lens_fits_that_fail_fall_back_to_refits(failure, monkeypatch):
    """A held-out lens fit SciPy refuses (residuals not finite at its start) or that ends non-finite
    is not used: leave-one-out says None and ``cross_validate`` refits, as it does where the batched
    fits of a view that tells f cannot be trusted."""
    from eyetohand.calibration.fit import cross_validate
    from eyetohand.models import radial

    pairs = load_pairs(PAPER)

    def broken(p_full, uv_s, xy_s, c, k2=True):
        if failure == "raises":
            raise ValueError("Residuals are not finite in the initial point.")
        return np.full_like(p_full, np.nan)

    held = cross_validate(pairs, "homography-radial")
    refits = cross_validate(pairs, "homography-radial", refit=True)
    assert np.abs(held - refits).max() > 1e-2  # the two are told apart here (up to 0.06 mm)
    monkeypatch.setattr(radial, "lens_refit_holding_focal", broken)
    assert radial.HomographyRadial.leave_one_out(pairs.uv_px, pairs.xyz_mm) is None
    # refits: where they stop in the valley is not bit-reproducible run to run (docs/performance.md)
    np.testing.assert_allclose(cross_validate(pairs, "homography-radial"), refits, rtol=0, atol=1e-3)
