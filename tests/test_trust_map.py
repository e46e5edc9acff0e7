"""The report's pictures of where a calibration can be trusted (issue 30 part 4, and part 5's margin).

- the dashed "refused beyond" line is the true boundary of the region's rule: the hull grown by the
  margin (Minkowski sum with a disc), every point on the drawn line at margin ± 0.5 px from the hull;
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import PAPER

from eyetohand import calibrate, load_pairs
from eyetohand.reports import grown_hull


def _on_line(poly: np.ndarray, per_segment: int = 20) -> np.ndarray:
    """Points along the closed polyline, ``per_segment`` per segment (its vertices and between them)."""
    closed = np.vstack([poly, poly[:1]])
    t = np.linspace(0.0, 1.0, per_segment, endpoint=False)[:, None]
    return np.vstack([a + t * (b - a) for a, b in zip(closed[:-1], closed[1:], strict=True)])


def _old_grown(hull: np.ndarray, margin_px: float) -> np.ndarray:
    """What the report drew before: vertices pushed out along the direction from the centroid."""
    d = hull - hull.mean(axis=0)
    return hull + margin_px * d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("source", ["paper", "square", "thin"])
def test_refused_beyond_line_is_the_margin(source):
    if source == "paper":
        cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False)
        region = cal.region
    else:
        from eyetohand.geometry import CalibratedRegion

        uv = (
            np.array([[0, 0], [400, 0], [400, 400], [0, 400], [200, 200]], float)
            if source == "square"
            else np.array([[0, 0], [900, 40], [910, 60], [5, 30], [300, 20]], float)
        )
        region = CalibratedRegion.from_pairs(uv, np.zeros((len(uv), 3)), plane_z_mm=0.0)
    line = grown_hull(region.hull_px, region.margin_px)
    d = region.outside_px(_on_line(line))
    assert np.abs(d - region.margin_px).max() <= 0.5, (d.min(), d.max(), region.margin_px)
    # the hull's own direction makes no difference
    again = grown_hull(region.hull_px[::-1], region.margin_px)
    assert np.abs(region.outside_px(_on_line(again)) - region.margin_px).max() <= 0.5
    # the approximation it replaces drew the line inside the limit (where mappings are still answered)
    old = region.outside_px(_on_line(_old_grown(region.hull_px, region.margin_px)))
    assert old.min() < region.margin_px - 0.5
