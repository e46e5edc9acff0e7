"""One pixel and many take different code — plain floats for one (``models.base.one_point``), the compiled
loop or NumPy chunks for many — and must not give different answers (issue 26): for every registered
model, on, near and beyond its horizon and for non-finite pixels, one point gives what the many-point
paths give it, or the same refusal in the same words — by the model, by a Calibration, and through the
real server's HTTP and TCP and the CLI (a point exactly on a homography's horizon, w = 0, used to raise
ZeroDivisionError in the one-point path: an "internal error" exit 1 and a plain-text HTTP 500).

The cameras here are tilted 70° from straight down, so that a homography's horizon (its vanishing line,
f·cot 70° ≈ 950 px from the principal point) crosses the image.
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
from unittest import mock

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import ServeProcess, src_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numerics import EPS, K, rounding_condition
from synth import make_camera, project

from eyetohand.calibration.file import Calibration
from eyetohand.calibration.fit import calibrate
from eyetohand.core.errors import InputError
from eyetohand.core.pairs import PointPairs
from eyetohand.models import MODELS
from eyetohand.models import base as models_base

NON_FINITE = "image points must be finite numbers (px)"
HORIZON_WORDS = "maps to no finite robot point (on or beyond the model's horizon)"
LENS = {"homography-radial", "camera"}  # their many-point lens inverse: equal to rounding, not bit for bit


def steep_pairs(name: str) -> tuple[PointPairs, tuple[int, int]]:
    """5 × 5 grid pairs (at two heights for the models of several heights) where a camera tilted 70°
    looks, 0.2 px noise; a small lens for the models that fit one."""
    dist = [-0.05, 0.01, 0, 0, 0] if name in LENS else None
    cam = make_camera(tilt_deg=70.0, dist=dist, seed=2)
    R, _ = cv2.Rodrigues(cam["rvec"])
    axis, c = R.T @ np.array([0.0, 0.0, 1.0]), cam["centre"]
    g = np.linspace(-60.0, 60.0, 5)
    heights = (100.0, 140.0) if MODELS[name].needs_heights() else (100.0,)
    pts = []
    for z in heights:
        look = c + (z - c[2]) / axis[2] * axis
        pts += [[look[0] + a, look[1] + b, z] for a in g for b in g]
    xyz = np.array(pts)
    uv = project(cam, xyz) + np.random.default_rng(1).normal(scale=0.2, size=(len(xyz), 2))
    return PointPairs.from_arrays(uv, xyz), cam["size"]


class Steep:
    """A model's calibration on :func:`steep_pairs`, the height its points are mapped at, a point well
    inside its region, and pixels on its horizon: the images of plane points 10⁹ mm away in 72
    directions (for the affine models, which have none, far pixels)."""

    def __init__(self, name: str):
        pairs, size = steep_pairs(name)
        self.cal = calibrate(pairs, name, "lm", image_size=size, loo=False)
        self.model = self.cal.model
        self.z = 120.0 if self.model.needs_heights() else None
        z_plane = 100.0 if self.z is None else self.z
        self.inside = pairs.uv_px.mean(axis=0)
        ang = np.linspace(0.0, 2 * np.pi, 72, endpoint=False)
        c = pairs.xyz_mm[:, :2].mean(axis=0)
        far = np.column_stack([c + 1e9 * np.column_stack([np.cos(ang), np.sin(ang)]), np.full(72, z_plane)])
        h = self.model.robot_to_image(far)
        self.horizon = h[np.isfinite(h).all(axis=1)]
        assert len(self.horizon) >= 10

    def z_one(self):
        return self.z

    def z_many(self, n: int):
        return None if self.z is None else np.full(n, self.z)


_STEEP: dict[str, Steep] = {}


def steep(name: str) -> Steep:
    if name not in _STEEP:
        _STEEP[name] = Steep(name)
    return _STEEP[name]


def outcome(fn):
    """What ``fn()`` gives: its array, or the words of its InputError."""
    try:
        return np.asarray(fn(), float)
    except InputError as exc:
        return str(exc)


def one_point_forms(u: float, v: float):
    """The forms the one-point path takes (models.base.one_point): (2,) and (1, 2) arrays, a tuple, a
    nested list."""
    return (np.array([u, v]), np.array([[u, v]]), (u, v), [[u, v]])


def assert_same(one, many, what: str, *, lens: bool, rounding=None) -> None:
    """``one`` and ``many`` the same refusal (words), or the same bits — or for a lens model, where the
    many-point Newton steps of the lens inverse go on until the batch's slowest point converges, the
    same to within K·κ·eps·‖many‖, κ the one-point map's condition number there (``rounding()``)."""
    if isinstance(one, str) or isinstance(many, str):
        assert one == many, what
        return
    assert one.shape == many.shape, what
    if np.array_equal(one.view(np.int64), many.view(np.int64)):
        return
    assert lens, f"{what}: {one} != {many} (bits)"
    np.testing.assert_array_equal(np.isfinite(one), np.isfinite(many), err_msg=what)
    ok = np.isfinite(many)
    kappa = rounding()
    tol = K * kappa * EPS * float(np.linalg.norm(many[ok]))
    assert float(np.linalg.norm(one[ok] - many[ok])) <= tol, (what, one, many, kappa)


def check_point(s: Steep, u: float, v: float) -> None:
    model, z = s.model, s.z
    lens = model.name in LENS
    q = [float(s.inside[0]), float(s.inside[1])]

    def rounding():
        return rounding_condition(lambda uv: {"xyz": model.image_to_robot(uv, z)}, {"uv": np.array([u, v])})[
            "xyz"
        ]

    # the model: one point (each form) against it among others, by the compiled loop and without it
    many_rows = [[u, v], q, [u, v]]
    many = [outcome(lambda: model.image_to_robot(np.array(many_rows), s.z_many(3)))]
    with mock.patch.object(models_base, "_ROWS", None):
        many.append(outcome(lambda: model.image_to_robot(np.array(many_rows), s.z_many(3))))
    for m in many:
        row = m if isinstance(m, str) else m[:1]
        for form in one_point_forms(u, v):
            assert_same(
                outcome(lambda f=form: model.image_to_robot(f, z)),
                row,
                f"{model.name} {form}",
                lens=lens,
                rounding=rounding,
            )
    # a Calibration: the guarded map of the point alone and first of two, allowed outside the region
    zs = None if z is None else [z, z]
    one = outcome(lambda: s.cal.map([[u, v]], z, allow_outside=True).xyz_mm)
    two = outcome(lambda: s.cal.map([[u, v], q], zs, allow_outside=True).xyz_mm[:1])
    assert_same(one, two, f"{model.name} map ({u!r}, {v!r})", lens=lens, rounding=rounding)


def exact_horizon(H: np.ndarray, u: float) -> float | None:
    """A v with w = (H[2,0]·u + H[2,1]·v) + H[2,2] exactly 0 in floating point, near the vanishing line
    at u (None when no float within 200 ulps gives exactly 0)."""
    h6, h7, h8 = (float(h) for h in H[2])
    v0 = -(h6 * u + h8) / h7
    for k in range(200):
        for v in (v0 + k * math.ulp(v0), v0 - k * math.ulp(v0)):
            if (h6 * u + h7 * v) + h8 == 0.0:
                return v
    return None


OFFSETS = st.sampled_from([0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.1, 1.0, 30.0, 1e3, 1e6])


@pytest.mark.parametrize("name", list(MODELS))
@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    i=st.integers(0, 71),
    offset=OFFSETS,
    sign=st.sampled_from([-1.0, 1.0]),
    angle=st.floats(0.0, 2 * np.pi),
    ulps=st.integers(-3, 3),
)
def test_one_point_equals_many_near_and_beyond_the_horizon(name, i, offset, sign, angle, ulps):
    """Pixels on the horizon (the image of far plane points), moved off it by 0 to 10⁶ px in any
    direction and by a few ulps."""
    s = steep(name)
    h = s.horizon[i % len(s.horizon)]
    u = float(h[0] + sign * offset * math.cos(angle))
    v = float(h[1] + sign * offset * math.sin(angle))
    for _ in range(abs(ulps)):
        v = math.nextafter(v, math.copysign(math.inf, ulps))
    check_point(s, u, v)


@pytest.mark.parametrize("name", list(MODELS))
@settings(max_examples=30, deadline=None, derandomize=True)
@given(
    u=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e4, 1e4)),
    v=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1e4, 1e4)),
)
def test_one_point_equals_many_for_any_float(name, u, v):
    """Any pair of floats: NaN and ±inf refused in as_uv's words by both paths, huge ones (whose
    products overflow) given the same ±inf/NaN — refused by a Calibration in the same words."""
    check_point(steep(name), u, v)


@pytest.mark.parametrize("name", list(MODELS))
def test_a_pixel_far_out_is_refused_without_a_runtime_warning(name):
    """A huge pixel (its squared distance to the hull overflows) is refused as outside the region, by
    one point and by many, and the caller sees the refusal only: no numpy RuntimeWarning (CI printed
    "overflow encountered in square" from the region's distance)."""
    import warnings

    s = steep(name)
    q = [float(s.inside[0]), float(s.inside[1])]
    for u, v in ((1e200, 500.0), (500.0, -1e300), (1.7e308, 1.7e308)):
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            for rows in ([[u, v]], [q, [u, v]]):
                with pytest.raises(InputError, match="outside the calibrated region"):
                    s.cal.image_to_robot(np.array(rows), s.z)


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_pixel_is_refused_alike(name, bad):
    s = steep(name)
    for u, v in ((bad, 500.0), (500.0, bad), (bad, bad)):
        check_point(s, u, v)
        assert outcome(lambda u=u, v=v: s.model.image_to_robot((u, v), s.z)) == NON_FINITE


@pytest.mark.parametrize("name", ["homography", "affine"])
def test_exactly_on_the_horizon_w_is_zero(name):
    """A homography's pixels with w = 0 exactly (found ulp by ulp): ±inf (NaN where the numerator is 0
    too) as the compiled loop and NumPy give them, not ZeroDivisionError, and refused by a Calibration
    as the many-point path refuses them; an affine map (w = 1) has no such pixel and maps them."""
    s = steep("homography")
    H = s.model.matrix_image_to_robot
    found = []
    for u in np.linspace(-3000.0, 6000.0, 91):
        v = exact_horizon(H, float(u))
        if v is not None:
            found.append((float(u), v))
    assert len(found) >= 20
    if name == "affine":
        s = steep("affine")
    for u, v in found:
        check_point(s, u, v)
        xyz = s.model.image_to_robot((u, v))
        if name == "homography":
            assert not np.isfinite(xyz[0, :2]).any()
            with pytest.raises(InputError, match=r"maps to no finite robot point \(on or beyond"):
                s.cal.map([[u, v]], allow_outside=True)
        else:
            assert np.isfinite(xyz).all()


def test_ieee_over_zero_is_numpys_division_bit_for_bit():
    from eyetohand.models.planar import ieee_over_zero

    tiny = 5e-324
    for a in (1.0, -1.0, 0.0, -0.0, tiny, -tiny, 1e308, math.inf, -math.inf, math.nan):
        for zero in (0.0, -0.0):
            with np.errstate(all="ignore"):
                want = np.float64(a) / np.float64(zero)
            got = np.float64(ieee_over_zero(a, zero))
            assert got.view(np.int64) == want.view(np.int64), (a, zero, got, want)


# ---------------------------------------------------------------- every interface, through the real server


def test_a_pixel_on_the_horizon_is_refused_alike_by_the_cli_http_and_tcp(tmp_path):
    """`eyetohand apply --uv` (exit 2, one line), the HTTP API (422, JSON naming the point) and the TCP
    line service (ERR) of `eyetohand serve` refuse a pixel exactly on a homography's horizon (w = 0)
    with the words of the many-point path — one point alone and first of two."""
    from eyetohand.server.app import create_app

    pairs, size = steep_pairs("homography")
    records = [
        {"id": f"p{k}", "u": float(a), "v": float(b), "x": float(x), "y": float(y), "z": float(zz)}
        for k, ((a, b), (x, y, zz)) in enumerate(zip(pairs.uv_px, pairs.xyz_mm, strict=True))
    ]
    data = tmp_path / "data"
    app = create_app(data)
    with TestClient(app) as c:
        r = c.post("/api/calibrations", json={"name": "steep", "pairs": records, "model": "homography"})
        assert r.status_code == 201, r.text
        cal = Calibration.from_dict(c.get("/api/calibrations/1").json()["calibration"])
    app.state.store.close()
    H = cal.model.matrix_image_to_robot
    u = 600.0
    v = exact_horizon(H, u)
    assert v is not None
    q = [float(x) for x in cal.pairs.uv_px.mean(axis=0)]
    with pytest.raises(InputError) as many:
        cal.map([[u, v], q], allow_outside=True)
    reason = many.value.reason
    assert HORIZON_WORDS in reason and many.value.field_path == "points[0]"
    path = cal.save(tmp_path / "steep.json")
    cli = subprocess.run(
        [
            sys.executable,
            "-m",
            "eyetohand.cli",
            "apply",
            str(path),
            "--uv",
            repr(u),
            repr(v),
            "--allow-outside",
        ],
        capture_output=True,
        text=True,
        env=src_env(),
        timeout=120,
    )
    assert cli.returncode == 2 and cli.stdout == "", cli.stderr
    assert cli.stderr.count("\n") == 1 and reason in cli.stderr
    srv = ServeProcess(data, "--calibration", "steep", log_level="error")
    try:
        with (
            httpx.Client(base_url=srv.url, timeout=30) as c,
            socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=30) as sock,
        ):
            for points in ([[u, v]], [[u, v], q]):
                r = c.post(
                    "/api/calibrations/1/image-to-robot", json={"points": points, "allow_outside": True}
                )
                assert r.status_code == 422, r.text
                assert r.headers["content-type"].startswith("application/json")
                assert r.json()["field"] == "points[0]" and reason in r.json()["error"]
            f = sock.makefile("rb")
            sock.sendall(f"{u!r},{v!r},allow\n".encode())
            assert f.readline() == f"ERR {reason}\n".encode()
            sock.sendall(f"{q[0]!r},{q[1]!r}\n".encode())  # and the service goes on answering
            assert f.readline().count(b",") == 2
    finally:
        srv.stop()
