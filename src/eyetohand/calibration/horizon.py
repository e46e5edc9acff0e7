"""A mapping's horizon: where a model's answer is a finite number that means nothing.

Beyond the calibrated hull (in its margin, or beyond it when allowed) a point is refused when the
local map flips handedness there (a homography's det J = det H / w³ changes sign with w) or its scale
explodes (beyond ``HORIZON_SCALE_RATIO`` × the region centre's). :func:`beyond_horizon` tests points
one by one by central differences; :func:`horizon_clear` proves, once per calibration, that no point
within the margin can fail that test, from the model's own bound on its Jacobian
(:meth:`~eyetohand.models.Model.jacobian_det_range`), so the guarded many-point path need not test
each point of the margin ring.
"""

from __future__ import annotations

import math

import numpy as np

from eyetohand.geometry import JACOBIAN_STEP_PX, CalibratedRegion, grown_polygon, local_jacobian
from eyetohand.models import Model

HORIZON_SCALE_RATIO = 1e3
"""A point whose local scale is this many times the region centre's (or more) is beyond the horizon."""
PROOF_FACTOR = 10.0
"""``horizon_clear`` proves the scale within ``HORIZON_SCALE_RATIO`` / this: room for the central
differences' error, far smaller where w is this far from 0."""


def beyond_horizon(xy_map, ref_jacobian: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """(N,) True for the (N, 2) pixels on or beyond the horizon of ``xy_map`` ((M, 2) px → (M, 2) mm):
    the sign of the local Jacobian's determinant differs from ``ref_jacobian``'s (the region centre's),
    or its scale is ``HORIZON_SCALE_RATIO`` times that or more, or it is not finite."""
    with np.errstate(all="ignore"):
        det = np.linalg.det(local_jacobian(xy_map, uv_px))
        ref = np.linalg.det(ref_jacobian)
        ratio = np.sqrt(np.abs(det / ref))
    return ~np.isfinite(det) | (np.sign(det) != np.sign(ref)) | ~(ratio < HORIZON_SCALE_RATIO)


def horizon_clear(model: Model, region: CalibratedRegion, ref_jacobian: np.ndarray) -> bool:
    """Whether no pixel within the region's margin can be :func:`beyond_horizon`: the model bounds its
    Jacobian's determinant over a polygon around the hull grown by the margin and the differences'
    step, and the bound has the centre's sign throughout and a scale below ``HORIZON_SCALE_RATIO`` /
    ``PROOF_FACTOR``. False when the model gives no bound (each point is then tested)."""
    polygon = grown_polygon(region.hull_px, region.margin_px + 2 * JACOBIAN_STEP_PX, circumscribed=True)
    bound = model.jacobian_det_range(polygon)
    if bound is None:
        return False
    lo, hi = bound
    ref = float(np.linalg.det(ref_jacobian))
    if not (math.isfinite(ref) and math.isfinite(lo) and math.isfinite(hi) and ref != 0.0):
        return False
    if not (lo * ref > 0.0 and hi * ref > 0.0):
        return False
    worst = max(abs(lo), abs(hi)) / abs(ref)
    return math.sqrt(worst) < HORIZON_SCALE_RATIO / PROOF_FACTOR
