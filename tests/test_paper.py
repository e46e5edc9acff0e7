"""The paper's data (fit on Table 1, check on its 9 check points): our figures beside its own."""

import numpy as np

from eyetohand import calibrate
from eyetohand.reports.demo import PAPER_STATED_MAX_MM, load_paper


def test_homography_lm_beats_the_papers_best_by_35_percent(paper_pairs):
    train, check = paper_pairs
    cal = calibrate(train, "homography", "lm", check=check)
    assert cal.check.rms_mm <= 0.028
    assert cal.check.max_mm <= 0.057
    assert cal.check.max_mm <= 0.65 * PAPER_STATED_MAX_MM


def test_affine_lm_is_the_psos_optimum_and_within_the_papers_max(paper_pairs):
    train, check = paper_pairs
    cal = calibrate(train, "affine", "lm", check=check)
    # the least-squares affine optimum the README states, equation (16)
    assert abs(cal.fit.fitness - 0.105833) < 1e-5
    assert cal.check.max_mm <= PAPER_STATED_MAX_MM


def test_our_unoptimised_b_beats_table3(paper_pairs):
    """Table 3 (the paper's unoptimised B) has max error 0.365 mm and RMS 0.195 mm; starting B from
    the planar least-squares solution gives the affine optimum already."""
    train, check, published = load_paper()
    cal = calibrate(train, "paper", "linear", check=check, loo=False)
    e_pub = np.linalg.norm(published["table3"] - check.xyz_mm[:, :2], axis=1)
    assert abs(e_pub.max() - 0.365) < 1e-3 and abs(np.sqrt(np.mean(e_pub**2)) - 0.195) < 1e-3
    assert cal.check.max_mm < 0.25 * e_pub.max()


def test_auto_picks_a_model_and_explains(paper_pairs):
    train, check = paper_pairs
    cal = calibrate(train, "auto", check=check)
    sel = cal.selection
    assert sel["chosen"] == cal.model_name
    assert {c["model"] for c in sel["candidates"]} == {"affine", "homography", "homography-radial"}
    assert all(c["cv_rms_mm"] > 0 for c in sel["candidates"])
    assert cal.check.rms_mm <= 0.028
