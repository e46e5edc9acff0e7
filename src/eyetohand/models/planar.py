"""The planar matrix models: one 3×3 matrix from (normalised) pixels to the robot's plane.

``Homography`` is the general one (8 free elements, H[2, 2] = 1); ``Affine`` is the same map with its
last row fixed at (0, 0, 1) — fewer free coefficients, the same code. Both keep their parameters in
Hartley-normalised coordinates (well conditioned for the solvers) and give the matrix in pixels → mm
as ``matrix_image_to_robot``. Subclasses that correct the pixels first (a lens) override
``_ideal_px`` / ``_distorted_px``.
"""

from __future__ import annotations

from abc import abstractmethod
from types import MappingProxyType
from typing import ClassVar

import numpy as np

from ..normalize import apply_h, hartley
from .base import HeightRule, Model, check_enough, check_not_collinear, check_single_height

PLANAR_CONSTANTS = MappingProxyType({"T_uv": (3, 3), "T_xy": (3, 3), "plane_z_mm": ()})


def planar_setup(name: str, min_pairs: int, uv_px, xyz_mm):
    """Validate planar pairs and return ``(uv, xyz, z0, T_uv, T_xy, uv_n, xy_n)``."""
    uv = np.asarray(uv_px, dtype=float)
    xyz = np.asarray(xyz_mm, dtype=float)
    check_enough(name, min_pairs, len(uv))
    check_not_collinear(name, uv, xyz[:, :2])
    z0 = check_single_height(name, xyz)
    T_uv, uv_n = hartley(uv)
    T_xy, xy_n = hartley(xyz[:, :2])
    return uv, xyz, z0, T_uv, T_xy, uv_n, xy_n


def to_robot(xy_n: np.ndarray, Tinv_xy: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Normalised plane points (P, N, 2) → robot (P, N, 3), z taken from ``z_mm`` (N,)."""
    xy = xy_n * Tinv_xy[0, 0] + Tinv_xy[:2, 2]
    z = np.broadcast_to(z_mm, xy.shape[:2])
    return np.concatenate([xy, z[..., None]], axis=-1)


class PlanarMatrixModel(Model):
    """(x, y, 1) ~ T_xy⁻¹ · M(params) · T_uv · (u', v', 1), with (u', v') = ``_ideal_px(u, v)``."""

    height_rule: ClassVar[HeightRule] = HeightRule.PLANE
    constant_shapes = PLANAR_CONSTANTS

    def _prepare(self) -> None:
        self._T_uv = np.asarray(self.constants["T_uv"], float)
        self._Tinv_xy = np.linalg.inv(np.asarray(self.constants["T_xy"], float))

    @staticmethod
    @abstractmethod
    def batch_matrices(params) -> np.ndarray:
        """(P, 3, 3) normalised matrices from (P, D) parameter rows."""

    def _ideal_px(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels as the matrix sees them (a lens model undistorts here)."""
        return uv_px

    def _distorted_px(self, uv_px: np.ndarray) -> np.ndarray:
        """The inverse of ``_ideal_px``."""
        return uv_px

    def batch_image_to_robot(self, params, uv_px, z_mm):
        M = self.batch_matrices(params)
        pts = apply_h(self._T_uv, self._ideal_px(np.asarray(uv_px, float)))
        num = np.einsum("pij,nj->pni", M[:, :, :2], pts) + M[:, None, :, 2]
        return to_robot(num[..., :2] / num[..., 2:3], self._Tinv_xy, z_mm)

    @property
    def matrix_image_to_robot(self) -> np.ndarray:
        """3×3 matrix mapping (u', v', 1) px to (x, y, 1) mm (up to scale; [2, 2] = 1)."""
        H = self._Tinv_xy @ self.batch_matrices(self.params[None])[0] @ self._T_uv
        return H / H[2, 2]

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        return self._distorted_px(apply_h(np.linalg.inv(self.matrix_image_to_robot), xyz[:, :2]))
