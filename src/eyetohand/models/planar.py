"""Shared pieces of the single-height (planar) models: normalisation frames and the plane height."""

from __future__ import annotations

import numpy as np

from ..normalize import hartley
from .base import check_enough, check_not_collinear, check_single_height


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


def frames(meta) -> tuple[np.ndarray, np.ndarray]:
    """(T_uv, inverse of T_xy) as arrays from a model's meta."""
    return np.asarray(meta["T_uv"], float), np.linalg.inv(np.asarray(meta["T_xy"], float))


def to_robot(xy_n: np.ndarray, Tinv_xy: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Normalised plane points (P, N, 2) → robot (P, N, 3), z taken from ``z_mm`` (N,)."""
    xy = xy_n * Tinv_xy[0, 0] + Tinv_xy[:2, 2]
    z = np.broadcast_to(z_mm, xy.shape[:2])
    return np.concatenate([xy, z[..., None]], axis=-1)
