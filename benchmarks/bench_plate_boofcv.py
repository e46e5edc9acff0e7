"""The plate path on real photos: ``python benchmarks/bench_plate_boofcv.py``.

BoofCV's ``sony_chess`` (13 frames of a 5 x 7-square chessboard, 30 mm squares: 4 x 6 inner corners)
and ``sony_circle_regular`` (6 frames of a 10 x 8 dot grid, 25 mm apart), 640 x 480 (tests/data/boofcv).
The plate's own geometry stands in for the robot: each frame is calibrated alone with
``calibrate_plate`` from its 4 corner "touches" read off the plate (robot frame = the plate's, turned
so z points to the camera). The reference: OpenCV's ``calibrateCamera`` on *all* frames of the set
(k1, k2, p1, p2, k3), each frame's pose from it. Per frame: the distance (mm) between our map and
the reference's (every detected point and a grid of pixels inside the plate's hull, on the plate's
plane), our map's training RMS, and our one-image lens (f, k1) beside the reference's. BoofCV's own
intrinsics for sony_chess (intrinsic.yaml): f 701.0 / 698.7 px, k1 -0.2556, k2 0.1000.
"""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from eyetohand.calibration import Touch, calibrate_plate
from eyetohand.vision import PlateSpec, detect_plate

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "boofcv"
FLIP = np.diag([1.0, -1.0, -1.0])  # plate frame (z away from the camera) -> a robot frame, z to the camera


def run(folder: str, spec_text: str) -> None:
    import cv2

    spec = PlateSpec.parse(spec_text)
    frames, dets = [], []
    for f in sorted(glob.glob(str(DATA / folder / "*.jpg"))):
        try:
            dets.append(detect_plate(f, spec))
            frames.append(f)
        except ValueError as exc:
            print(f"  {Path(f).name}: {exc}")
    obj = [spec.points_mm().astype(np.float32)] * len(dets)
    img = [d.uv_px.astype(np.float32) for d in dets]
    size = dets[0].image_size
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None)
    print(
        f"{folder}: {len(dets)} frames; OpenCV calibrateCamera on all: rms {rms:.3f} px, f {K[0, 0]:.1f}/"
        f"{K[1, 1]:.1f} px, c ({K[0, 2]:.1f}, {K[1, 2]:.1f}), k1 {dist[0, 0]:.4f}, k2 {dist[0, 1]:.4f}"
    )
    pts = spec.points_mm()
    diffs = []
    for k, (f, det) in enumerate(zip(frames, dets, strict=True)):
        robot = pts @ FLIP.T
        touches = [
            Touch(tuple(det.uv_px[i]), tuple(robot[i]), 0, lab, j + 2)
            for j, (lab, i) in enumerate(spec.corner_labels().items())
        ]
        cal = calibrate_plate([f], spec, touches, touch_noise_mm=0.01)
        # pixels: the detected points and a grid inside their hull
        lo, hi = det.uv_px.min(axis=0), det.uv_px.max(axis=0)
        gu, gv = np.meshgrid(np.linspace(lo[0], hi[0], 12), np.linspace(lo[1], hi[1], 12))
        grid = np.column_stack([gu.ravel(), gv.ravel()])
        hull = cv2.convexHull(det.uv_px.astype(np.float32))
        inside = np.array([cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in grid])
        uv = np.vstack([det.uv_px, grid[inside]])
        ours = cal.map(uv, allow_outside=True).xyz_mm @ FLIP  # back to plate coordinates (FLIP = FLIP^-1)
        R, _ = cv2.Rodrigues(rvecs[k])
        n = cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
        rays = np.column_stack([n, np.ones(len(n))]) @ R  # plate-frame directions R^T (x, y, 1)
        c = -R.T @ tvecs[k].ravel()
        s = -c[2] / rays[:, 2]
        ref = c + s[:, None] * rays
        d = np.linalg.norm(ours[:, :2] - ref[:, :2], axis=1)
        diffs.append(d)
        lens = next(x for x in cal.notes if x.startswith("camera from the plate"))
        print(
            f"  {Path(f).name}: ours vs OpenCV-all RMS {np.sqrt(np.mean(d**2)):.3f} mm, max {d.max():.3f} mm "
            f"({len(uv)} px); train RMS {cal.train.rms_mm:.3f} mm; {lens.split(': ', 1)[1]}"
        )
    all_d = np.concatenate(diffs)
    print(f"  all frames: RMS {np.sqrt(np.mean(all_d**2)):.3f} mm, max {all_d.max():.3f} mm")


def main() -> int:
    run("sony_chess", "chessboard:4x6:30")
    run("sony_circle_regular", "circles:10x8:25")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
