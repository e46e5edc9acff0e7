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


def test_best_new_point_is_the_woodbury_update():
    """The candidates' scores equal the covariance updated by the new pair's information, computed
    directly: C' = (C⁻¹ + J_pᵀ J_p / s²)⁻¹; the chosen one lowers the mean sigma_mm more than a pair
    at the region's centre, where there is data already."""
    from eyetohand.solve import best_new_point, param_jacobian

    cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False)
    unc, model, z = cal.uncertainty, cal.model, cal.region.plane_z_mm
    hull = cal.region.hull_px
    targets = hull.mean(axis=0) + 0.8 * (hull - hull.mean(axis=0))  # inside the region
    cands = np.vstack([hull.mean(axis=0), hull[0] + [30.0, 30.0], hull[2] - [40.0, 0.0]])
    k, means = best_new_point(unc, model, cands, z, targets, z)
    C = unc.covariance
    s2 = unc.noise_mm**2
    for i, p in enumerate(cands):
        Jp = param_jacobian(model, p[None], np.array([z]))[0]
        Cn = np.linalg.pinv(np.linalg.pinv(C) + Jp.T @ Jp / s2)
        Jq = param_jacobian(model, targets, np.full(len(targets), z))
        direct = np.sqrt(np.einsum("ncd,de,nce->n", Jq, Cn, Jq) + unc.n_coords * s2).mean()
        assert means[i] == pytest.approx(direct, rel=1e-3), (i, means[i], direct)
    before = unc.sigma_mm(model, targets, z).mean()
    assert means[k] < means[0] < before  # the centre helps least; any pair helps


def test_report_trust_map_marks_where_to_add(tmp_path):
    from eyetohand.reports import write_report

    pairs = load_pairs(PAPER / "calibration_points.csv")
    cal = calibrate(pairs, "homography", "lm", check=load_pairs(PAPER / "check_points.csv"))
    index = write_report(tmp_path / "r", cal)
    html = index.read_text()
    assert "sigma_map.png" in html and "The star marks where one more training pair helps most" in html
    from helpers import keep_screenshot

    keep_screenshot(tmp_path / "r" / "sigma_map.png")
