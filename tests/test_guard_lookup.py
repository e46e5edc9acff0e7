"""The guarded many-point path's lookups (issue 29): ``CalibratedRegion.unproven`` (one trapezoid
lookup proves most pixels within the margin), the models' Jacobian bounds and ``horizon_clear`` —
each against the exact rule it stands for: ``outside_px`` and ``check`` for the region,
``Calibration.map`` (the one path that names refusals) for ``image_to_robot``, central differences
for the Jacobian."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from synth import grid_pairs, make_camera

import eyetohand.geometry.region as region_mod
from eyetohand import calibrate
from eyetohand.calibration.horizon import beyond_horizon, horizon_clear
from eyetohand.core import InputError
from eyetohand.core.pairs import PointPairs
from eyetohand.geometry import CalibratedRegion, grown_polygon, local_jacobian


def _region(rng: np.random.Generator, n: int) -> CalibratedRegion:
    pts = rng.uniform(0, 1000, (n, 2)) * rng.uniform(0.05, 2.0, 2)  # long and thin ones too
    return CalibratedRegion.from_pairs(pts, np.c_[pts, np.zeros(n)], plane_z_mm=0.0)


def _probe(reg: CalibratedRegion, rng: np.random.Generator, n: int) -> np.ndarray:
    """Pixels over the hull's box grown by twice the margin, plus pixels just inside and just outside
    the margin along the grown polygon's vertices, the hull's vertices, NaN and infinities."""
    lo = reg.hull_px.min(axis=0) - 2 * reg.margin_px
    hi = reg.hull_px.max(axis=0) + 2 * reg.margin_px
    uv = rng.uniform(lo, hi, (n, 2))
    edge = grown_polygon(reg.hull_px, reg.margin_px)
    c = reg.hull_px.mean(axis=0)
    near = np.vstack([c + (edge - c) * (1 + s) for s in (-1e-9, -1e-12, 0.0, 1e-12, 1e-9)])
    special = np.array([[np.nan, 1.0], [1.0, np.nan], [np.inf, 1.0], [1.0, -np.inf]])
    return np.vstack([uv, near, reg.hull_px, special])


def _exact_status(reg: CalibratedRegion, uv: np.ndarray) -> np.ndarray:
    d = reg.outside_px(uv)
    return np.where(d <= reg.margin_px, np.where(d > 0, 1, 0), 2)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 60))
def test_unproven_leaves_out_only_pixels_the_exact_rule_might_refuse(seed, n):
    rng = np.random.default_rng(seed)
    reg = _region(rng, n)
    uv = _probe(reg, rng, 4000)
    few = reg.unproven(uv)
    proven = np.ones(len(uv), bool)
    proven[few] = False
    exact = _exact_status(reg, uv)
    assert (exact[proven] < 2).all()  # sound: every proven pixel is within the margin (and finite)
    assert np.isfinite(uv[proven]).all()
    assert (np.diff(few) > 0).all()  # indices, in order


def test_unproven_leaves_few_within_the_margin():
    rng = np.random.default_rng(7)
    reg = _region(rng, 30)
    uv = _probe(reg, rng, 200_000)[:200_000]
    inside = _exact_status(reg, uv) < 2
    few = reg.unproven(uv[inside])
    assert len(few) < 0.002 * inside.sum()  # the trapezoids miss only thin slivers at vertices


@pytest.mark.parametrize("seed", range(6))
def test_compiled_and_numpy_lookups_agree(seed, monkeypatch):
    rng = np.random.default_rng(seed)
    reg = _region(rng, int(rng.integers(3, 40)))
    uv = _probe(reg, rng, 5000)
    if region_mod.hull_kernel() is None:
        pytest.fail("the compiled _hull part is not built (setup.py): this test compares it with NumPy")
    few_c = reg.unproven(uv)
    monkeypatch.setattr(region_mod, "_HULL", None)
    assert np.array_equal(few_c, reg.unproven(uv))


# ---------------------------------------------------------------- whole calibrations
def _cells():
    cam = make_camera(tilt_deg=10.0)
    flat = grid_pairs(cam, n_side=6, heights=(40.0,), noise_px=0.05, seed=3)
    lens = make_camera(tilt_deg=10.0, dist=[-0.12, 0.05, 0, 0, 0])
    two = grid_pairs(cam, n_side=5, heights=(0.0, 60.0), noise_px=0.05, seed=4)
    steep = make_camera(tilt_deg=45.0, height_mm=250.0, f_px=900.0)  # the horizon near the view
    tilted = flat.xyz_mm.copy()
    tilted[:, 2] = 0.02 * (tilted[:, 0] - tilted[:, 0].mean()) + 3.0
    return {
        "homography": (flat, "homography", None),
        "affine": (flat, "affine", None),
        "paper": (flat, "paper", None),
        "radial": (grid_pairs(lens, n_side=6, noise_px=0.05, seed=5), "homography-radial", None),
        "dlt3d": (two, "dlt3d", 30.0),
        "steep": (grid_pairs(steep, n_side=6, span_mm=300.0, seed=6), "homography", None),
        "tilted plane": (PointPairs.from_arrays(flat.uv_px, tilted), "homography", None),
    }


CELLS = _cells()


@pytest.fixture(scope="module", params=sorted(CELLS))
def cell(request):
    pairs, model, z = CELLS[request.param]
    return calibrate(pairs, model, loo=False), z


def _around(cal, rng: np.random.Generator, n: int) -> np.ndarray:
    reg = cal.region
    lo = reg.hull_px.min(axis=0) - 1.5 * reg.margin_px
    hi = reg.hull_px.max(axis=0) + 1.5 * reg.margin_px
    return rng.uniform(lo, hi, (n, 2))


def _refusal(f):
    try:
        f()
    except InputError as exc:
        return str(exc)
    return None


def test_many_points_equal_map_bit_for_bit(cell):
    cal, z = cell
    rng = np.random.default_rng(11)
    uv = _around(cal, rng, 40_000)
    ok, d = cal.region.check(uv, allow_outside=True)
    ring = ok & (d > 0)
    ok[ring] = ~beyond_horizon(cal.xy_map(z), cal.centre_jacobian, uv[ring])
    inside = np.ascontiguousarray(uv[ok])
    got = cal.image_to_robot(inside, z)
    want = cal.map(inside, z, with_sigma=False).xyz_mm
    assert got.tobytes() == want.tobytes()


def test_many_points_refused_in_the_words_of_map(cell):
    cal, z = cell
    rng = np.random.default_rng(12)
    uv = _around(cal, rng, 3000)
    for bad in (uv, np.vstack([uv[:5], [[np.nan, 3.0]], uv[5:9]])):
        want = _refusal(lambda b=bad: cal.map(b, z, with_sigma=False))
        assert want is not None
        assert _refusal(lambda b=bad: cal.image_to_robot(b, z)) == want


def test_a_height_to_refuse_is_refused_in_the_words_of_map(cell):
    cal, z = cell
    uv = np.ascontiguousarray(cal.region.hull_px[:3] * 0.5 + cal.region.hull_px.mean(axis=0) * 0.5)
    far = 1e4 if z is None else z + 1e4
    want = _refusal(lambda: cal.map(uv, far, with_sigma=False))
    assert want is not None and "z" in want
    assert _refusal(lambda: cal.image_to_robot(uv, far)) == want


# ---------------------------------------------------------------- the Jacobian's bound and the horizon
def test_planar_jacobian_bound_holds_the_differences():
    rng = np.random.default_rng(3)
    for name in ("homography", "affine", "paper"):
        pairs, model, _ = CELLS["steep" if name == "homography" else name]
        cal = calibrate(pairs, model, loo=False)
        poly = grown_polygon(cal.region.hull_px, cal.region.margin_px, circumscribed=True)
        lo, hi = cal.model.jacobian_det_range(poly)
        t = rng.dirichlet(np.ones(len(poly)), 2000)  # points of the polygon
        det = np.linalg.det(local_jacobian(cal.xy_map(), t @ poly))
        scale = max(abs(lo), abs(hi))
        assert (det >= lo - 1e-6 * scale).all() and (det <= hi + 1e-6 * scale).all()


def test_lens_and_three_dimensional_models_give_no_bound():
    for name in ("radial", "dlt3d"):
        pairs, model, _ = CELLS[name]
        cal = calibrate(pairs, model, loo=False)
        assert cal.model.jacobian_det_range(cal.region.hull_px) is None
        assert not cal.horizon_proven_clear


def test_no_bound_across_the_horizon_and_no_proof_near_it():
    pairs, model, _ = CELLS["steep"]
    cal = calibrate(pairs, model, loo=False)
    H = cal.model.matrix_image_to_robot
    # a polygon the horizon w = 0 crosses: no bound
    hull = cal.region.hull_px
    c = hull.mean(axis=0)
    g = H[2, :2]
    w_c = float(H[2] @ [c[0], c[1], 1.0])
    far = c - g / (g @ g) * w_c * 2.0  # beyond w = 0 along the gradient of w
    assert cal.model.jacobian_det_range(np.vstack([hull, far])) is None
    # a region grown until the horizon is near: the proof is refused, and a pixel past it is beyond
    grown = CalibratedRegion(hull, float(np.linalg.norm(far - c)))
    assert not horizon_clear(cal.model, grown, cal.centre_jacobian)
    assert beyond_horizon(cal.xy_map(), cal.centre_jacobian, far[None])[0]
    assert cal.horizon_proven_clear  # the cell's own margin is well clear of it
