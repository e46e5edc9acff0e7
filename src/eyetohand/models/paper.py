"""The paper's own model: the 12-element matrix B of equations (7)–(13), mapped exactly as written.

Equation (8): (u, v, 1) = B · (x, y, z, 1), with B = A / Zc. Equation (13): R = M⁻¹ P with
M = B[:, :3] and P = (u − b14, v − b24, 1 − b34). The parameter vector is the paper's encoding
[b11 b12 b13 b14 b21 b22 b23 b24 b31 b32 b33 b34], so a solver optimises the same 12 numbers as the
paper's hybrid PSO.

Estimation:
- pairs at two or more heights: equation (5) by normalised DLT, then B = A / mean(Zc);
- pairs at one height (the paper's own data; :func:`eyetohand.geometry.fit_height_plane`, a robot's
  z noise and a tilted table included): equation (5) has rank 9 of 11 and its minimum-norm solution
  is the degenerate Zc ≈ 0, so B is initialised from the planar solution instead — the least-squares
  affine robot→image map (u, v) = A₂ₓ₃ (x, y, 1) on the pairs' plane z = a·x + b·y + z0, placed in B
  as [[a11 a12 0 a13], [a21 a22 0 a23], [−a/z0 −b/z0 1/z0 0]], which makes equation (13) reproduce
  that affine map and return z on that plane (z = z0 on a level one). ``init_note`` records which
  path was taken, ``equation5_rank`` the rank found.
"""

from __future__ import annotations

import numpy as np

from eyetohand.core import DegenerateError
from eyetohand.geometry import fit_height_plane, hartley, spread_ratio
from eyetohand.models.base import (
    CV_MIN_POINTS,
    MAP_CHUNK,
    HeightRule,
    Model,
    as_uv,
    batch_inverse3,
    check_enough,
    check_not_collinear,
    one_point,
    opencv,
    opencv_affine_rows_into,
    refuse_non_finite,
    rows_kernel,
)
from eyetohand.models.dlt3d import COPLANAR_RATIO, dlt_projection


def equation5_rank(uv_px: np.ndarray, xyz_mm: np.ndarray) -> tuple[int, float]:
    """Numerical rank of the paper's 2n×11 matrix of equation (5) as printed (a34 = 1), and its
    condition number. Columns are scaled to unit norm first (which leaves the rank unchanged);
    centring the points, as Hartley normalisation does, would change the equation's rank on
    coplanar data, so it is not used here."""
    uv = np.asarray(uv_px, float)
    X = np.asarray(xyz_mm, float)
    n = len(uv)
    B = np.zeros((2 * n, 11))
    B[0::2, 0:3], B[0::2, 3] = X, 1.0
    B[1::2, 4:7], B[1::2, 7] = X, 1.0
    B[0::2, 8:11] = -uv[:, :1] * X
    B[1::2, 8:11] = -uv[:, 1:2] * X
    norms = np.linalg.norm(B, axis=0)
    B = B / np.where(norms > 0, norms, 1.0)
    s = np.linalg.svd(B, compute_uv=False)
    rank = int((s > 1e-10 * s[0]).sum())
    return rank, float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


class PaperB(Model):
    name = "paper"
    n_params = 12
    min_pairs = 4
    summary = "12 unknowns: the paper's matrix B, equation (13) (affine on one plane)"
    height_rule = HeightRule.COMPUTED  # equation (13) gives z itself
    auto_candidate = False  # the paper's reference model, compared but never chosen by `auto`
    # R = M⁻¹ (u − b14, v − b24, 1 − b34) is affine in (u, v): 9 coefficients from 12 numbers. With
    # (b14, b24, b34) held (b34 ≠ 1), M⁻¹ and the affine map determine each other one to one, so
    # least squares refines the nine elements of M and keeps the start's last column: a problem of
    # full rank (refining all twelve, MINPACK's answer was not reproducible from run to run)
    gauge_params = (3, 7, 11)

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> PaperB:
        uv = np.asarray(uv_px, float)
        xyz = np.asarray(xyz_mm, float)
        check_enough(cls.name, cls.min_pairs, len(uv))
        rank, cond = equation5_rank(uv, xyz)
        plane = fit_height_plane(xyz)
        if not plane.one_height and spread_ratio(xyz) >= COPLANAR_RATIO and len(uv) >= 7:
            P, T_uv, T3, cond = dlt_projection(uv, xyz, cls.name)
            A = np.linalg.inv(T_uv) @ P @ T3
            zc = np.column_stack([xyz, np.ones(len(xyz))]) @ A[2]
            B = A / zc.mean()
            init = f"equation (5), rank {rank} of 11; B = A / mean(Zc)"
        else:
            check_not_collinear(cls.name, uv, xyz[:, :2])
            if not plane.one_height:
                raise DegenerateError(
                    f"model '{cls.name}': the pairs are not one height ({plane.why_not_one()}) and too "
                    "few (7 or more) for equation (5) at several heights"
                )
            z0 = plane.z0_mm
            if abs(z0) < 1e-9:
                raise DegenerateError(
                    f"model '{cls.name}': the plane passes through z = 0 at x = y = 0, where the paper's B "
                    "(third row 1/z0) is undefined; use affine or homography"
                )
            a, b = plane.slope
            T_xy, xy_n = hartley(xyz[:, :2])
            T_uv, uv_n = hartley(uv)
            design = np.column_stack([xy_n, np.ones(len(xy_n))])
            sol, *_ = np.linalg.lstsq(design, uv_n, rcond=None)  # robot -> image, normalised
            A = np.linalg.inv(T_uv) @ np.vstack([sol.T, [0, 0, 1]]) @ T_xy  # px from mm
            B = np.array(
                [
                    [A[0, 0], A[0, 1], 0.0, A[0, 2]],
                    [A[1, 0], A[1, 1], 0.0, A[1, 2]],
                    # the plane z = a·x + b·y + z0 as B's third row: (−a, −b, 1, 0) / z0 · (x, y, z, 1) = 1
                    [-a / z0 if a else 0.0, -b / z0 if b else 0.0, 1.0 / z0, 0.0],
                ]
            )
            cond = float(np.linalg.cond(design))
            where = f"z = {z0:g} mm" if plane.rms_mm == 0.0 and not plane.tilted else plane.describe()
            init = (
                f"coplanar pairs ({where}): equation (5) has rank {rank} of 11, so B was "
                "initialised from the planar least-squares solution, not the degenerate Zc ≈ 0"
            )
        return cls(B.reshape(-1), {}, {"init": init, "equation5_rank": rank, "condition_number": cond})

    def batch_image_to_robot(self, params, uv_px, z_mm):
        B = np.asarray(params, float).reshape(-1, 3, 4)
        Minv, _ = batch_inverse3(B[:, :, :3])
        uv = np.asarray(uv_px, float)
        # R = M⁻¹ P, P = (u − b14, v − b24, 1 − b34), elementwise on (3, points, parameter sets)
        # with the longer axis innermost: no BLAS, no einsum, four passes for all three
        # coordinates. The result is a (P, N, 3) view of those planes.
        G = Minv.transpose(2, 1, 0)  # G[j]: (3, P), row i contiguous, = M⁻¹[:, i, j]
        t = np.ascontiguousarray(B[:, :, 3].T)  # (3, P): b14, b24, b34
        wide = len(B) >= len(uv)
        if wide:  # (3, N, P)
            G, t, u, v = G[:, :, None, :], t[:, None, :], uv[:, 0, None], uv[:, 1, None]
        else:  # (3, P, N)
            G, t, u, v = G[..., None], t[..., None], uv[:, 0], uv[:, 1]
        du, dv, dw = u - t[0], v - t[1], 1.0 - t[2]
        out = np.multiply(G[0], du)
        out += np.multiply(G[1], dv)
        out += G[2] * dw
        return out.transpose(2, 1, 0) if wide else out.transpose(1, 2, 0)

    def _prepare(self) -> None:
        # what the parameters fix: M⁻¹ (same cofactors as the batch map) and (b14, b24, b34)
        B = self.params.reshape(1, 3, 4)
        Minv, _ = batch_inverse3(B[:, :, :3])
        self._Minv = tuple(tuple(row) for row in Minv[0].tolist())
        self._t = tuple(B[0, :, 3].tolist())
        # the same map as a 3×3 affine matrix on (u, v, 1): M⁻¹ (u − b14, v − b24, 1 − b34)
        G = Minv[0]
        # the chunks' arithmetic as rows of (g0, g1, g2 (1 − b34)) for the compiled loop
        dw = 1.0 - self._t[2]
        self._rows_m = np.array([[g0, g1, g2 * dw] for g0, g1, g2 in self._Minv])
        self._affine3 = np.column_stack([G[:, :2], G @ (np.array([0.0, 0.0, 1.0]) - B[0, :, 3])])

    def jacobian_det_range(self, polygon_px: np.ndarray) -> tuple[float, float] | None:
        """Equation (13) is affine in (u, v): det d(x, y)/d(u, v) is one number everywhere."""
        (a0, a1, _), (b0, b1, _), _ = self._Minv
        det = a0 * b1 - a1 * b0
        return det, det

    def image_to_robot(self, uv_px, z_mm=None) -> np.ndarray:
        """Equation (13) with the precomputed M⁻¹: one point on plain floats, many in one pass of the
        compiled loop (``rows_kernel``) or, without it, elementwise in cache-sized chunks; the same
        arithmetic as ``batch_image_to_robot`` (z is computed, ``z_mm`` ignored)."""
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = self._Minv
        t0, t1, t2 = self._t
        dw = 1.0 - t2
        pt = one_point(uv_px)
        if pt is not None:
            du, dv = pt[0] - t0, pt[1] - t1
            return np.array(
                [[a0 * du + a1 * dv + a2 * dw, b0 * du + b1 * dv + b2 * dw, c0 * du + c1 * dv + c2 * dw]]
            )
        uv = as_uv(uv_px, check_finite=False)
        rows = rows_kernel()
        if rows is not None:  # one compiled pass, equal to the chunks below bit for bit
            out = np.empty((len(uv), 3))
            if not rows.affine3_rows(np.ascontiguousarray(uv), self._rows_m, t0, t1, out):
                refuse_non_finite(uv)
            return out
        if len(uv) >= CV_MIN_POINTS:
            cv2 = opencv()
            if cv2 is not None:  # equation (13) is affine in (u, v): one 3 → 3 transform into the rows
                out = np.empty((len(uv), 3))
                opencv_affine_rows_into(cv2, uv, self._affine3, out)
                return out
        refuse_non_finite(uv)
        out = np.empty((len(uv), 3))
        for s in range(0, len(uv), MAP_CHUNK):
            chunk = uv[s : s + MAP_CHUNK]
            du = chunk[:, 0] - t0
            dv = chunk[:, 1] - t1
            t = np.empty(len(chunk))
            for i, (g0, g1, g2) in enumerate(self._Minv):
                o = out[s : s + MAP_CHUNK, i]
                np.multiply(du, g0, out=o)
                o += np.multiply(dv, g1, out=t)
                o += g2 * dw
        return out

    @property
    def equation5_rank(self) -> int | None:
        """Numerical rank of equation (5) on the training pairs (9 of 11 on coplanar pairs)."""
        r = self.diagnostics.get("equation5_rank")
        return None if r is None else int(r)

    @property
    def matrix_B(self) -> np.ndarray:
        return self.params.reshape(3, 4).copy()

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """Equation (8) literally: (u, v) = B[:2] · (x, y, z, 1)."""
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        return np.column_stack([xyz, np.ones(len(xyz))]) @ self.matrix_B[:2].T
