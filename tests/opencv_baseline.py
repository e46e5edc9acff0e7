"""Test oracle — the white-box reference: OpenCV's camera calibration on the same pairs, used to judge
the models (tests/test_multiheight.py, benchmarks/study_sim.py; not part of the package).

``cv2.calibrateCamera`` with the pairs' robot points as one view's object points. They span two or
more heights, so the object is not planar and OpenCV needs a starting camera matrix
(``CALIB_USE_INTRINSIC_GUESS``): the lens's nominal focal length and the image centre, which a user
knows from the data sheets. Distortion: OpenCV's default five terms (k1, k2, p1, p2, k3). A check
pixel is mapped back by ``undistortPoints`` to a ray and intersected with the plane z = h.
"""

from __future__ import annotations

import numpy as np

from eyetohand.core.errors import InputError


class OpenCVCalibration:
    """``cv2.calibrateCamera`` on pairs at several heights; ``image_to_robot(uv, z)`` back-projects."""

    def __init__(self, pairs, image_size, focal_px: float, *, flags: int = 0):
        import cv2

        if len(pairs.z_levels_mm) < 2:
            raise InputError("the OpenCV baseline needs pairs at two or more heights (non-planar)")
        w, h = image_size
        K0 = np.array([[focal_px, 0.0, (w - 1) / 2.0], [0.0, focal_px, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        obj = [pairs.xyz_mm.astype(np.float32)]
        img = [pairs.uv_px.astype(np.float32)]
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            obj, img, (int(w), int(h)), K0, None, flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags
        )
        self.rms_px = float(rms)
        self.K = K
        self.dist = dist.ravel()
        self.R = cv2.Rodrigues(rvecs[0])[0]
        self.t = tvecs[0].ravel()

    def image_to_robot(self, uv_px, z_mm) -> np.ndarray:
        import cv2

        uv = np.asarray(uv_px, float).reshape(-1, 1, 2)
        n = cv2.undistortPoints(
            uv, self.K, self.dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
        )
        ray = np.column_stack([n.reshape(-1, 2), np.ones(len(uv))]) @ self.R
        c = -self.R.T @ self.t
        z = np.broadcast_to(np.asarray(z_mm, float), (len(uv),))
        s = (z - c[2]) / ray[:, 2]
        return c + s[:, None] * ray

    def residuals(self, uv_px, xyz_mm) -> np.ndarray:
        xyz = np.asarray(xyz_mm, float)
        return self.image_to_robot(uv_px, xyz[:, 2]) - xyz
