"""The pinhole camera: agreement with OpenCV, round trips, constructors, serialisation, refusals."""

import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from eyetohand.core.errors import InputError
from eyetohand.geometry.camera import Camera, as_camera

STRONG = (-0.28, 0.12, 1.5e-3, -8e-4, -0.02)  # k1 k2 p1 p2 k3: a strongly distorting lens


@pytest.fixture(scope="module")
def cam():
    return Camera.looking_down(
        (2448, 2048),
        focal_px=3000.0,
        height_mm=450.0,
        tilt_deg=15.0,
        tilt_direction_deg=-40.0,
        yaw_deg=70.0,
        dist=STRONG,
        pp_offset_px=(20, -15),
    )


def random_pixels(cam, n, seed=0):
    w, h = cam.image_size
    return np.random.default_rng(seed).uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (n, 2))


def test_projection_matches_opencv_project_points(cam):
    rng = np.random.default_rng(1)
    xyz = np.column_stack([rng.uniform(-150, 150, (2000, 2)), rng.uniform(-20, 60, 2000)])
    ref, _ = cv2.projectPoints(xyz, np.array(cam.rvec), cam.t, cam.K, cam.dist)
    ours = cam.robot_to_image(xyz)
    assert ours.shape == (2000, 2)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-8
    # a tangential-only and a k3-only lens too (each term wired to the right coefficient)
    for d in [(0, 0, 2e-3, 0, 0), (0, 0, 0, -2e-3, 0), (0, 0, 0, 0, 0.05), (0.1, -0.05, 0, 0, 0)]:
        c = Camera.from_opencv(cam.K, d, cam.R, cam.t, cam.image_size)
        ref, _ = cv2.projectPoints(xyz, np.array(c.rvec), c.t, c.K, c.dist)
        assert np.abs(c.robot_to_image(xyz) - ref.reshape(-1, 2)).max() < 1e-8, d


def test_undistortion_matches_opencv_undistort_points(cam):
    uv = random_pixels(cam, 20000)
    ours = cam.image_to_normalized(uv)
    tight = cv2.undistortPoints(
        uv.reshape(-1, 1, 2),
        cam.K,
        cam.dist,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16),
    )
    assert np.isfinite(ours).all()
    assert np.abs(ours - tight.reshape(-1, 2)).max() * cam.fx_px < 1e-8  # px
    # OpenCV's default (5 fixed-point steps) stops short on this lens; ours is converged
    loose = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
    back_loose = cam.normalized_to_image(loose)
    back_ours = cam.normalized_to_image(ours)
    assert np.abs(back_ours - uv).max() < 1e-9
    assert np.abs(back_loose - uv).max() > 1e-4


@pytest.mark.parametrize("z_mm", [0.0, 37.5, -12.0])
def test_image_to_robot_round_trip_on_a_plane(cam, z_mm):
    uv = random_pixels(cam, 5000, seed=int(abs(z_mm)))
    xyz = cam.image_to_robot(uv, z_mm)
    assert xyz.shape == (5000, 3) and np.allclose(xyz[:, 2], z_mm, atol=1e-9)
    assert np.abs(cam.robot_to_image(xyz) - uv).max() < 1e-8
    # per-point heights, and a single point keeps its shape
    z = np.linspace(-10, 40, 5000)
    assert np.allclose(cam.image_to_robot(uv, z)[:, 2], z, atol=1e-9)
    one = cam.image_to_robot(uv[0], z_mm)
    assert one.shape == (3,) and np.allclose(one, xyz[0])
    assert cam.robot_to_image(xyz[0]).shape == (2,)


def test_image_to_ray_passes_through_the_point(cam):
    xyz = np.array([[10.0, -20.0, 5.0], [-80.0, 60.0, 30.0]])
    origin, d = cam.image_to_ray(cam.robot_to_image(xyz))
    assert np.allclose(np.linalg.norm(d, axis=1), 1)
    v = xyz - origin
    assert np.allclose(np.cross(v, d), 0, atol=1e-7)  # the point lies on its pixel's ray
    assert (np.einsum("ij,ij->i", v, d) > 0).all()  # in front


def test_looking_down_geometry(cam):
    assert cam.position_mm[2] == pytest.approx(450.0)
    assert cam.tilt_deg == pytest.approx(15.0)
    # the optical axis meets the belt at the target point (0, 0, 0)
    c, a = cam.position_mm, cam.optical_axis
    hit = c + (-c[2] / a[2]) * a
    assert np.allclose(hit, 0, atol=1e-9)
    # the image of that point is the principal point, up to distortion (none on the axis)
    assert np.allclose(cam.robot_to_image([0.0, 0.0, 0.0]), [cam.cx_px, cam.cy_px], atol=1e-9)
    moved = Camera.looking_down(tilt_deg=0.0, height_mm=800, target_mm=(100, 50, 20))
    assert np.allclose(moved.position_mm, [100, 50, 820]) and moved.tilt_deg == pytest.approx(0.0, abs=1e-6)


def test_look_at_puts_the_target_at_the_centre_and_up_upwards():
    cam = Camera.look_at((100.0, -300.0, 800.0), (50.0, 20.0, 0.0), image_size=(1000, 800), focal_px=2000)
    assert np.allclose(cam.position_mm, [100, -300, 800])
    assert np.allclose(cam.robot_to_image([50.0, 20.0, 0.0]), [499.5, 399.5], atol=1e-9)
    a = cam.robot_to_image([50.0, 20.0, 0.0])
    b = cam.robot_to_image([50.0, 30.0, 0.0])  # +y robot ("up") appears higher in the image
    assert b[1] < a[1] - 1
    R = cam.R
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    with pytest.raises(InputError, match="parallel"):
        Camera.look_at((0, 0, 500), (0, 0, 0), up=(0, 0, 1))
    with pytest.raises(InputError, match="same point"):
        Camera.look_at((0, 0, 0), (0, 0, 0))


def test_dict_round_trip_and_opencv_views(cam):
    d = cam.to_dict()
    again = Camera.from_dict(json.loads(json.dumps(d)))
    assert again.to_dict() == d
    assert np.array_equal(again.K, cam.K) and np.array_equal(again.dist, cam.dist)
    assert np.allclose(again.R, cam.R) and np.allclose(again.t, cam.t)
    assert cam.dist.tolist() == [STRONG[0], STRONG[1], STRONG[2], STRONG[3], STRONG[4]]
    by_matrix = Camera.from_opencv(cam.K, cam.dist, cam.R, cam.t, cam.image_size)
    assert np.allclose(by_matrix.rvec, cam.rvec) and by_matrix.image_size == (2448, 2048)
    with pytest.raises(InputError, match="unknown key 'focal'"):
        Camera.from_dict({**d, "focal": 3})
    with pytest.raises(InputError, match="missing key 'fx_px'"):
        Camera.from_dict({k: v for k, v in d.items() if k != "fx_px"})


def test_refusals_and_nan_outside_the_model():
    with pytest.raises(InputError, match="focal"):
        Camera(0.0, 100.0, 50, 50, 100, 100)
    with pytest.raises(InputError, match="width_px"):
        Camera(100.0, 100.0, 50, 50, 0, 100)
    with pytest.raises(InputError, match="rotation"):
        Camera.from_opencv(np.eye(3), None, np.ones((3, 3)), (0, 0, 0), (10, 10))
    cam = Camera.look_at((0, 0, 500), (0, 0, 0), up=(0, 1, 0), image_size=(640, 480), focal_px=500)
    # a point behind the camera has no image; a ray parallel to / away from the plane no point
    assert np.isnan(cam.robot_to_image([0.0, 0.0, 600.0])).all()
    assert np.isnan(cam.image_to_robot([320.0, 240.0], 700.0)).all()
    # beyond the fold of a strong barrel lens there is no undistorted point: NaN, not a wrong one
    barrel = Camera(500.0, 500.0, 320.0, 240.0, 640, 480, k1=-0.6)
    n = barrel.undistort(np.array([[0.1, 0.0], [0.5, 0.0]]))
    assert np.isfinite(n[0]).all() and np.isnan(n[1]).all()
    with pytest.raises(InputError, match="shape"):
        cam.robot_to_image(np.zeros((4, 2)))


def test_opencv_style_objects_are_accepted(cam):
    duck = SimpleNamespace(K=cam.K, dist=cam.dist, R=cam.R, t=cam.t, image_size=cam.image_size)
    c = as_camera(duck)
    xyz = np.array([[5.0, 6.0, 7.0]])
    assert np.abs(c.robot_to_image(xyz) - cam.robot_to_image(xyz)).max() < 1e-9
    assert as_camera(cam) is cam
    with pytest.raises(InputError, match="expected a camera"):
        as_camera(object())
