"""The paper's equation (5) — the 11-unknown projection matrix — for pairs at two or more heights.

Maps (u, v) of an object at a known height z to (x, y): with z known, the projection becomes a
plane-to-image homography, solved per point in closed form. On coplanar pairs equation (5) has rank 9
of 11 and no unique solution, so the model refuses them.
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from eyetohand.core import DegenerateError
from eyetohand.geometry import apply_h, hartley, spread_ratio
from eyetohand.models.base import HeightRule, Model, check_enough
from eyetohand.models.homography import null_space_rows

COPLANAR_RATIO = 1e-4


def dlt_projection(
    uv_px: np.ndarray,
    xyz_mm: np.ndarray,
    model_name: str,
    *,
    what: str = "the paper's equation 5",
    z_offset_mm: float = 0.0,
):
    """Normalised DLT: returns (P_n (3×4, P_n[2,3] = 1), T_uv, T_xyz, condition number).

    ``what`` names the model in the coplanar refusal (a caller's own label), ``z_offset_mm`` is added
    back to the z it reports when the caller passes centred points."""
    check_enough(model_name, 7, len(uv_px))
    ratio = spread_ratio(xyz_mm)
    if ratio < COPLANAR_RATIO:
        z = xyz_mm[:, 2] + z_offset_mm
        where = f"all z = {z[0]:.3f} mm" if np.ptp(z) < 1e-6 else "they lie on one plane"
        raise DegenerateError(
            f"model '{model_name}' ({what}) needs pairs at two or more heights; "
            f"these {len(uv_px)} pairs are coplanar ({where}), so its projection matrix is rank-deficient: "
            "use affine, homography or homography-radial"
        )
    T_uv, uv_n = hartley(uv_px)
    T3, X_n = hartley(xyz_mm)
    n = len(uv_n)
    Xh = np.column_stack([X_n, np.ones(n)])
    zeros = np.zeros((n, 4))
    A = np.vstack(
        [
            np.hstack([Xh, zeros, -uv_n[:, :1] * Xh]),
            np.hstack([zeros, Xh, -uv_n[:, 1:2] * Xh]),
        ]
    )
    vt, s = null_space_rows(A)
    if s[-2] < 1e-9 * s[0]:
        raise DegenerateError(f"model '{model_name}': the pairs do not determine a projection")
    P = vt[-1].reshape(3, 4)
    if abs(P[2, 3]) < 1e-12:
        raise DegenerateError(f"model '{model_name}': degenerate projection (P[2,3] = 0)")
    return P / P[2, 3], T_uv, T3, float(s[0] / s[-2])


class DLT3D(Model):
    """Projection matrix P (robot → image) in normalised coordinates, P[2, 3] = 1 (11 unknowns)."""

    name = "dlt3d"
    n_params = 11
    min_pairs = 7
    height_rule = HeightRule.GIVEN
    constant_shapes = MappingProxyType({"T_uv": (3, 3), "T_xyz": (4, 4)})
    summary = "11 unknowns: the paper's equation (5), pairs at 2+ heights, no lens distortion"

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> DLT3D:
        uv = np.asarray(uv_px, float)
        xyz = np.asarray(xyz_mm, float)
        P, T_uv, T3, cond = dlt_projection(uv, xyz, cls.name)
        z = xyz[:, 2]
        diagnostics = {"heights_mm": sorted({round(float(v), 6) for v in z}), "condition_number": cond}
        return cls(P.reshape(-1)[:11], {"T_uv": T_uv.tolist(), "T_xyz": T3.tolist()}, diagnostics)

    def _prepare(self) -> None:
        self._T_uv = np.asarray(self.constants["T_uv"], float)
        self._T3 = np.asarray(self.constants["T_xyz"], float)

    def _P(self, params) -> np.ndarray:
        p = np.asarray(params, float).reshape(-1, 11)
        return np.concatenate([p, np.ones((len(p), 1))], axis=1).reshape(-1, 3, 4)

    def batch_image_to_robot(self, params, uv_px, z_mm):
        P = self._P(params)
        uv_n = apply_h(self._T_uv, uv_px)
        s3, c = self._T3[0, 0], -self._T3[:3, 3] / self._T3[0, 0]
        z_n = s3 * (np.asarray(z_mm, float) - c[2])  # (N,)
        # rows (P1 - u P3) and (P2 - v P3), each (P, N, 4)
        a = P[:, None, 0, :] - uv_n[None, :, 0:1] * P[:, None, 2, :]
        b = P[:, None, 1, :] - uv_n[None, :, 1:2] * P[:, None, 2, :]
        ra = -(a[..., 2] * z_n + a[..., 3])
        rb = -(b[..., 2] * z_n + b[..., 3])
        det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            x_n = (ra * b[..., 1] - a[..., 1] * rb) / det
            y_n = (a[..., 0] * rb - ra * b[..., 0]) / det
        x = x_n / s3 + c[0]
        y = y_n / s3 + c[1]
        z = np.broadcast_to(np.asarray(z_mm, float), x.shape)
        return np.stack([x, y, z], axis=-1)

    @property
    def matrix_robot_to_image(self) -> np.ndarray:
        """3×4 projection matrix mapping (x, y, z, 1) mm to (u, v, 1) px (up to scale)."""
        P = np.linalg.inv(self._T_uv) @ self._P(self.params)[0] @ self._T3
        return P / P[2, 3]

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        h = np.column_stack([xyz, np.ones(len(xyz))]) @ self.matrix_robot_to_image.T
        return h[:, :2] / h[:, 2:3]
