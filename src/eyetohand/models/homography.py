"""Planar projective map (8 unknowns): a camera that is tilted relative to the robot's plane."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from eyetohand.core import DegenerateError
from eyetohand.models.planar import PlanarMatrixModel, planar_setup


def dlt_homography(src_n: np.ndarray, dst_n: np.ndarray, model_name: str):
    """Direct linear transform on normalised points: H (3×3, H[2,2] = 1) and the condition number
    (memory and time linear in the number of points: a thin SVD, see ``null_space_rows``)."""
    n = len(src_n)
    x, y = src_n[:, 0], src_n[:, 1]
    X, Y = dst_n[:, 0], dst_n[:, 1]
    zeros, ones = np.zeros(n), np.ones(n)
    rows1 = np.column_stack([x, y, ones, zeros, zeros, zeros, -X * x, -X * y, -X])
    rows2 = np.column_stack([zeros, zeros, zeros, x, y, ones, -Y * x, -Y * y, -Y])
    A = np.vstack([rows1, rows2])
    if not np.isfinite(A).all():  # a caller's undistorted pixel beyond its lens's fold
        raise DegenerateError(f"model '{model_name}': a point is not finite, so no homography can be solved")
    vt, s = null_space_rows(A)
    if s[-2] < 1e-9 * s[0]:
        raise DegenerateError(
            f"model '{model_name}': the pairs do not determine a homography "
            "(at least 4 pairs with no 3 on one line are needed)"
        )
    H = vt[-1].reshape(3, 3)
    if abs(H[2, 2]) < 1e-12:
        raise DegenerateError(f"model '{model_name}': degenerate homography (plane at infinity)")
    return H / H[2, 2], float(s[0] / s[-2])


def null_space_rows(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right singular vectors (rows, last = null vector) and singular values of a tall A, computed
    from the thin SVD (no 2n×2n U: memory linear in the rows)."""
    _, s, vt = np.linalg.svd(A, full_matrices=False)
    return vt, s


class Homography(PlanarMatrixModel):
    """(x, y, 1) ~ H · (u, v, 1), DLT in Hartley-normalised coordinates.

    Parameters: the first 8 elements of H in normalised coordinates (H[2, 2] = 1).
    """

    name = "homography"
    n_params = 8
    nests: ClassVar[tuple[str, ...]] = ("affine",)  # H with its last row (0, 0, 1)
    min_pairs = 5
    summary = "8 unknowns: plane-to-plane perspective (tilted camera), no lens distortion"

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> Homography:
        uv, xyz, plane, T_uv, T_xy, uv_n, xy_n = planar_setup(cls.name, cls.min_pairs, uv_px, xyz_mm)
        H, cond = dlt_homography(uv_n, xy_n, cls.name)
        constants = {"T_uv": T_uv.tolist(), "T_xy": T_xy.tolist(), **plane}
        return cls(H.reshape(-1)[:8], constants, {"condition_number": cond})

    @staticmethod
    def batch_matrices(params) -> np.ndarray:
        p = np.asarray(params, float).reshape(-1, 8)
        return np.concatenate([p, np.ones((len(p), 1))], axis=1).reshape(-1, 3, 3)


def batch_homography(params, pts_n: np.ndarray) -> np.ndarray:
    """Apply (P, 8) homographies (H[2,2] = 1) to (N, 2) or (P, N, 2) points → (P, N, 2)."""
    H = Homography.batch_matrices(params)
    pts = np.broadcast_to(pts_n, (len(H),) + pts_n.shape[-2:])
    num = np.einsum("pij,pnj->pni", H[:, :, :2], pts) + H[:, None, :, 2]
    return num[..., :2] / num[..., 2:3]
