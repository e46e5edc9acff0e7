"""Speed of the one lens (eyetohand.geometry.lens) through the camera: ``python benchmarks/bench_lens.py``.

One point and 500 000 points through ``Camera.image_to_robot`` (undistort, ray, plane) and
``Camera.robot_to_image``, each as a ratio to OpenCV's ``cv2.undistortPoints`` /
``cv2.projectPoints`` on the same points in the same run (OpenCV's undistortion at its default 5
fixed-point steps, which stops short of convergence on a strong lens; ours runs to 1e-14).
"""

from __future__ import annotations

import argparse
import timeit

import cv2
import numpy as np

from eyetohand.geometry.camera import Camera

LENSES = {
    "strong, tangential + k3": (-0.28, 0.12, 1.5e-3, -8e-4, -0.02),
    "radial only": (-0.08, 0.12, 0.0, 0.0, 0.0),
}


def _best_s(fn, number: int) -> float:
    return min(timeit.repeat(fn, number=number, repeat=5)) / number


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=500_000)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    for label, dist in LENSES.items():
        cam = Camera.looking_down((2448, 2048), focal_px=3000.0, height_mm=450.0, tilt_deg=15.0, dist=dist)
        K, d, rvec, t = cam.K, cam.dist, np.array(cam.rvec), cam.t
        for n in (1, args.points):
            uv = rng.uniform([0, 0], [2447, 2047], (n, 2))
            xyz = cam.image_to_robot(uv, 10.0)
            number = 2000 if n == 1 else 1
            ours_i = _best_s(lambda uv=uv, cam=cam: cam.image_to_robot(uv, 10.0), number)
            ocv_i = _best_s(lambda uv=uv, K=K, d=d: cv2.undistortPoints(uv.reshape(-1, 1, 2), K, d), number)
            ours_p = _best_s(lambda xyz=xyz, cam=cam: cam.robot_to_image(xyz), number)
            ocv_p = _best_s(
                lambda xyz=xyz, K=K, d=d, rvec=rvec, t=t: cv2.projectPoints(xyz, rvec, t, K, d), number
            )
            unit, scale = ("us", 1e6) if n == 1 else ("ms", 1e3)
            print(
                f"{label:24s} N={n:<7d} image_to_robot {ours_i * scale:8.2f} {unit} "
                f"({ours_i / ocv_i:5.2f}x undistortPoints)   robot_to_image {ours_p * scale:8.2f} {unit} "
                f"({ours_p / ocv_p:5.2f}x projectPoints)"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
