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
    points = np.asarray(points, dtype=float)
    d = points.shape[-1]
    out = points @ T[:d, :d].T + T[:d, d]
    w = points @ T[d, :d] + T[d, d]
    return out / w[..., None]


def spread_ratio(points: np.ndarray) -> float:
    """Smallest over largest singular value of the centred points: 0 for collinear (2-D) or
    coplanar (3-D) sets, 1 for a perfectly isotropic spread."""
    points = np.asarray(points, dtype=float)
    if len(points) < 2:
        return 0.0
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return float(s[-1] / s[0]) if s[0] > 0 else 0.0
