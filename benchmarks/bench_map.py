"""Mapping speed against OpenCV and NumPy, in the same run (ratios, not absolute times).

1. One point through each model's ``image_to_robot`` (µs per call, median of repeats), next to NumPy's
   ``H @ [u, v, 1]`` on a 3×3 matrix (the floor of any Python call) and ``cv2.perspectiveTransform``.
2. 10⁶ points per model vs OpenCV: ``cv2.perspectiveTransform`` for the planar models (affine,
   homography, paper), ``cv2.undistortPoints`` + ``perspectiveTransform`` for homography-radial, and
   ``cv2.undistortPoints`` + the ray/plane intersection in NumPy for camera — each in a child
   process with the BLAS thread count at 1 and at 2 (the map uses no BLAS, so both should agree).
3. One guarded point through ``Calibration.map`` (region check, sigma) on homography.

Simulated cell: a camera 450 mm above the plane, tilted 8°, 2448×2048 px, lens k1 = -0.08 (camera and
homography-radial fitted on its pixels; the planar models on the same pairs). Run time ~30 s:
``python benchmarks/bench_map.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

import cv2
import numpy as np

from eyetohand.calibration.fit import calibrate
from eyetohand.core.pairs import PointPairs
from eyetohand.models import base

BLAS_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _camera():
    w, h = 2448, 2048
    K = np.array([[2600.0, 0, (w - 1) / 2 + 6], [0, 2600.0, (h - 1) / 2 - 4], [0, 0, 1.0]])
    R_down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    R_tilt, _ = cv2.Rodrigues(np.array([0.6, 0.8, 0.0]) * np.deg2rad(8.0))
    R = R_tilt @ R_down
    centre = np.array([20.0, 600.0, 450.0])
    rvec, _ = cv2.Rodrigues(R)
    return K, np.array([-0.08, 0.02, 0.0, 0.0, 0.0]), rvec.ravel(), -R @ centre, R, centre


def _pairs(K, dist, rvec, tvec, heights, n_side=6, seed=1):
    rng = np.random.default_rng(seed)
    g = np.linspace(-60, 60, n_side)
    xx, yy = np.meshgrid(g, g)
    xyz = np.vstack([np.c_[xx.ravel() + 20, yy.ravel() + 600, np.full(xx.size, z)] for z in heights])
    uv, _ = cv2.projectPoints(xyz.reshape(-1, 1, 3), rvec, tvec, K, dist)
    uv = uv.reshape(-1, 2) + rng.normal(scale=0.05, size=(len(xyz), 2))
    return PointPairs.from_arrays(uv, xyz)


def _best_us(fn, number: int, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - t) / number)
    return statistics.median(times) * 1e6


def _ms(fn, repeat: int) -> float:
    fn()  # warm-up, not timed: the first call of a size pays the allocator's page faults
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--big-only", type=int, default=0, help=argparse.SUPPRESS)  # child: BLAS threads
    args = ap.parse_args()
    rep = 3 if args.quick else 7
    K, dist, rvec, tvec, R, centre = _camera()
    plane = _pairs(K, dist, rvec, tvec, (0.0,))
    multi = _pairs(K, dist, rvec, tvec, (0.0, 40.0))
    cals = {
        name: calibrate(plane, name, "lm", loo=False, image_size=(2448, 2048))
        for name in ("affine", "homography", "homography-radial")
    }
    plane_z = plane.xyz_mm[:, 2] + 10.0  # the paper's B needs a plane off z = 0
    cals["paper"] = calibrate(
        PointPairs.from_arrays(plane.uv_px, np.c_[plane.xyz_mm[:, :2], plane_z]), "paper", "lm", loo=False
    )
    cals["camera"] = calibrate(multi, "camera", "lm", loo=False, image_size=(2448, 2048))
    uv1 = plane.uv_px.mean(axis=0)
    H = cals["homography"].model.matrix_image_to_robot

    if args.big_only:
        _big(args, cals, plane, K, H, args.big_only)
        return
    print("1. one point (µs per call, median of repeats)")
    n1 = 2000 if args.quick else 5000
    floor_np = _best_us(lambda: H @ np.array([uv1[0], uv1[1], 1.0]), n1, rep)
    one_cv = uv1.reshape(1, 1, 2)
    floor_cv = _best_us(lambda: cv2.perspectiveTransform(one_cv, H), n1, rep)
    print(f"   NumPy H @ [u, v, 1]: {floor_np:.2f} µs   cv2.perspectiveTransform: {floor_cv:.2f} µs")
    targets = {"affine": 5, "homography": 5, "paper": 5, "homography-radial": 30, "camera": 30}
    for name, cal in cals.items():
        m = cal.model
        z = 20.0 if name == "camera" else None
        t = _best_us(lambda m=m, z=z: m.image_to_robot(uv1, z), n1, rep)
        print(
            f"   {name:18s} {t:7.2f} µs  (goal ≤ {targets[name]} µs; "
            f"{t / floor_np:.1f}× NumPy's matrix product)"
        )

    print(f"2. 10⁶ points (ms, median of {rep}); ratio = eyetohand / OpenCV, goal ≤ 1.5")
    if base.rows_kernel() is None:
        print(
            "   (the compiled loop eyetohand.models._rows was not built: lens-free maps by NumPy and OpenCV)"
        )
    for threads in (1, 2):
        env = {**os.environ, **{v: str(threads) for v in BLAS_VARS}}
        cmd = [sys.executable, __file__, "--big-only", str(threads)] + (["--quick"] if args.quick else [])
        print(
            subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=True).stdout,
            end="",
        )

    print("3. one guarded point, Calibration.map (µs per call)")
    cal = cals["homography"]
    t_plain = _best_us(lambda: cal.model.image_to_robot(uv1), n1, rep)
    t_guard = _best_us(lambda: cal.map(uv1, with_sigma=False), n1 // 2, rep)
    t_sigma = _best_us(lambda: cal.map(uv1), n1 // 2, rep)
    t_rz = _best_us(lambda: cal.map(uv1, angle_deg=30.0, tool_rz_offset_deg=5.0), n1 // 2, rep)
    print(
        f"   model {t_plain:.1f} µs; guarded {t_guard:.1f} µs; "
        f"guarded with sigma {t_sigma:.1f} µs (goal ≤ 60); with sigma, an angle and a tool offset "
        f"{t_rz:.1f} µs"
    )


def _big(args, cals, plane, K, H, threads: int) -> None:
    rep = 3 if args.quick else 7
    n = 10**6
    rng = np.random.default_rng(0)
    lo, hi = plane.uv_px.min(axis=0), plane.uv_px.max(axis=0)
    big = rng.uniform(lo, hi, size=(n, 2))
    big_cv = big.reshape(-1, 1, 2)
    cam = cals["camera"].model.camera
    Kc, dc = np.array(cam["K"]), np.array(cam["dist"])
    Rc, Cc = np.array(cam["R"]), np.array(cam["centre_mm"])
    Hr = cals["homography-radial"].model.matrix_image_to_robot
    rm = cals["homography-radial"].model
    fr, (k1, k2), cr = rm.constants["focal_px"], rm.distortion, np.array(rm.constants["centre_px"])
    Kr = np.array([[fr, 0, cr[0]], [0, fr, cr[1]], [0, 0, 1.0]])

    def cv_camera():
        nrm = cv2.undistortPoints(big_cv, Kc, dc).reshape(-1, 2)
        w = nrm @ Rc.T[:2] + Rc.T[2]  # ray directions in the robot frame
        s = (20.0 - Cc[2]) / w[:, 2]
        return Cc[:2] + s[:, None] * w[:, :2]

    def cv_radial():
        ideal = cv2.undistortPoints(big_cv, Kr, np.array([k1, k2, 0, 0.0]), P=Kr)
        return cv2.perspectiveTransform(ideal, Hr)

    peers = {
        "affine": lambda: cv2.perspectiveTransform(big_cv, cals["affine"].model.matrix_image_to_robot),
        "homography": lambda: cv2.perspectiveTransform(big_cv, H),
        "paper": lambda: cv2.perspectiveTransform(big_cv, H),
        "homography-radial": cv_radial,
        "camera": cv_camera,
    }
    compiled = base.rows_kernel()
    for name, cal in cals.items():
        m = cal.model
        z = 20.0 if name == "camera" else None
        ours = _ms(lambda m=m, z=z: m.image_to_robot(big, z), rep)
        peer = _ms(peers[name], rep)
        line = f"   BLAS {threads}: {name:18s} {ours:7.1f} ms  OpenCV {peer:6.1f} ms  ratio {ours / peer:.2f}"
        if compiled is not None and name in ("affine", "homography", "paper"):
            base._ROWS = None  # what a machine that could not build the compiled loop runs
            try:
                alone = _ms(lambda m=m: m.image_to_robot(big), rep)
            finally:
                base._ROWS = compiled
            line += f"   (without the compiled loop {alone:.1f} ms, ratio {alone / peer:.2f})"
        print(line)


if __name__ == "__main__":
    main()
