"""Hartley normalisation: translate points to their centroid and scale them to mean distance sqrt(d).

Every linear solve in eyetohand works on normalised coordinates; the similarity transforms are kept so
that the solution can be mapped back (or, for the models, kept in normalised form and applied around it).
"""

from __future__ import annotations

import numpy as np


def hartley(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Similarity ``T`` ((d+1)×(d+1)) with ``T @ [p, 1]`` centred and of mean norm sqrt(d).

    Returns ``(T, normalised_points)``. Points with no spread at all get scale 1 (the caller decides
    whether that is degenerate).
    """
    points = np.asarray(points, dtype=float)
    d = points.shape[1]
    centroid = points.mean(axis=0)
    mean_dist = np.linalg.norm(points - centroid, axis=1).mean()
    scale = np.sqrt(d) / mean_dist if mean_dist > 0 else 1.0
    T = np.eye(d + 1)
    T[:d, :d] *= scale
    T[:d, d] = -scale * centroid
    return T, (points - centroid) * scale


def apply_h(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a homogeneous (d+1)×(d+1) matrix to (..., d) points (with the perspective divide)."""
    # Elementwise, never BLAS: a matrix product this thin is all call overhead in BLAS, and with
    # several BLAS threads their start-up and busy-waiting cost more than the arithmetic.
    points = np.asarray(points, dtype=float)
    T = np.asarray(T, dtype=float)
    d = points.shape[-1]
    if points.size <= 32 * d:  # up to 32 points: one broadcast product, the fewest calls
        q = (points[..., None, :] * T[:, :d]).sum(axis=-1)
        q += T[:, d]
        return q[..., :d] / q[..., d:]
    cols = [points[..., j] for j in range(d)]
    affine = T[d, d] == 1.0 and not T[d, :d].any()  # e.g. a Hartley similarity: no divide
    if not affine:
        w = cols[0] * T[d, 0]
        for j in range(1, d):
            w += cols[j] * T[d, j]
        w += T[d, d]
    out = np.empty(points.shape)
    for i in range(d):
        o = out[..., i]
        np.multiply(cols[0], T[i, 0], out=o)
        for j in range(1, d):
            o += cols[j] * T[i, j]
        o += T[i, d]
        if not affine:
            o /= w
    return out


def spread_ratio(points: np.ndarray) -> float:
    """Smallest over largest singular value of the centred points: 0 for collinear (2-D) or
    coplanar (3-D) sets, 1 for a perfectly isotropic spread."""
    points = np.asarray(points, dtype=float)
    if len(points) < 2:
        return 0.0
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return float(s[-1] / s[0]) if s[0] > 0 else 0.0
