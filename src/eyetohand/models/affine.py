"""Affine image→robot map (6 unknowns): the family the paper's equation (13) produces on one plane."""

from __future__ import annotations

import numpy as np

from ..normalize import apply_h
from .base import Model
from .planar import frames, planar_setup, to_robot


class Affine(Model):
    """x, y = A · (u, v, 1), solved by least squares in Hartley-normalised coordinates.

    The parameters are the 2×3 matrix in normalised coordinates (well conditioned for the solvers);
    ``matrix_image_to_robot`` gives it in pixels → mm.
    """

    name = "affine"
    n_params = 6
    min_pairs = 4
    summary = "6 unknowns: scale, rotation, shear, offset (camera looking straight down)"

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> Affine:
        uv, xyz, z0, T_uv, T_xy, uv_n, xy_n = planar_setup(cls.name, cls.min_pairs, uv_px, xyz_mm)
        design = np.column_stack([uv_n, np.ones(len(uv_n))])
        sol, *_ = np.linalg.lstsq(design, xy_n, rcond=None)  # (3, 2)
        meta = {
            "T_uv": T_uv.tolist(),
            "T_xy": T_xy.tolist(),
            "plane_z_mm": z0,
            "condition_number": float(np.linalg.cond(design)),
        }
        return cls(sol.T.reshape(-1), meta)

    def __init__(self, params, meta):
        super().__init__(params, meta)
        self._T_uv, self._Tinv_xy = frames(self.meta)

    def batch_image_to_robot(self, params, uv_px, z_mm):
        A = np.asarray(params, float).reshape(-1, 2, 3)
        uv_n = apply_h(self._T_uv, uv_px)
        xy_n = np.einsum("pij,nj->pni", A[:, :, :2], uv_n) + A[:, None, :, 2]
        return to_robot(xy_n, self._Tinv_xy, z_mm)

    @property
    def matrix_image_to_robot(self) -> np.ndarray:
        """3×3 homogeneous matrix mapping (u, v, 1) px to (x, y, 1) mm."""
        A = np.vstack([self.params.reshape(2, 3), [0.0, 0.0, 1.0]])
        return self._Tinv_xy @ A @ self._T_uv

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        return apply_h(np.linalg.inv(self.matrix_image_to_robot), xyz[:, :2])
