"""Affine image→robot map (6 unknowns): the family the paper's equation (13) produces on one plane."""

from __future__ import annotations

import numpy as np

from eyetohand.models.planar import PlanarMatrixModel, planar_setup


class Affine(PlanarMatrixModel):
    """x, y = A · (u, v, 1): the planar matrix model with its last row fixed at (0, 0, 1), solved by
    least squares in Hartley-normalised coordinates. Parameters: the 2×3 matrix, normalised."""

    name = "affine"
    n_params = 6
    min_pairs = 4
    summary = "6 unknowns: scale, rotation, shear, offset (camera looking straight down)"
    linear_in_params = True  # its linear solve is the least-squares fit: leave-one-out in closed form

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> Affine:
        uv, xyz, plane, T_uv, T_xy, uv_n, xy_n = planar_setup(cls.name, cls.min_pairs, uv_px, xyz_mm)
        design = np.column_stack([uv_n, np.ones(len(uv_n))])
        sol, *_ = np.linalg.lstsq(design, xy_n, rcond=None)  # (3, 2)
        constants = {"T_uv": T_uv.tolist(), "T_xy": T_xy.tolist(), **plane}
        return cls(sol.T.reshape(-1), constants, {"condition_number": float(np.linalg.cond(design))})

    @staticmethod
    def batch_matrices(params) -> np.ndarray:
        A = np.asarray(params, float).reshape(-1, 2, 3)
        last = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (len(A), 1, 3))
        return np.concatenate([A, last], axis=1)
