"""The limit harness (benchmarks/limit.py): its oracle reaches the Cramér–Rao bound, and eyetohand's
homography reaches the oracle on a lens-free cell — both within the sampling tolerance of the trials
(docs/limit.md)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from limit import Cell, project, rms_se, run_config, unproject  # noqa: E402

TRIALS = 60


@pytest.fixture(scope="module")
def lens_free():
    """5×5 grid, 0.2 px / 0.02 mm, no lens: the oracle and homography on the same 60 data sets."""
    return run_config(Cell(), 5, 0.2, 0.02, TRIALS, seed=7, models=("homography",))


def test_true_model_round_trips():
    """unproject inverts project (lens, off-centre principal point, two heights) to 1e-9 mm."""
    for heights in ((0.0,), (0.0, -100.0)):
        cell = Cell(k1=-0.08, pp_offset_px=(8.0, -5.0), heights_mm=heights)
        xyz = cell.grid(7)
        uv = project(cell.theta()[None], xyz, cell.f_px)[0]
        back = unproject(cell.theta()[None], uv, xyz[:, 2], cell.f_px)[0]
        assert np.abs(back - xyz[:, :2]).max() < 1e-9


def test_oracle_reaches_the_bound(lens_free):
    """The oracle's RMS check error matches the CRB within 4 standard errors of its own Monte Carlo
    (about 3 % with 60 trials) plus 2 % for the linearisation; its parameter errors whitened by the
    bound's covariance have mean square ≈ 1 (NEES) within 4 standard errors."""
    bound, _, omse, nees, _, _ = run_config(Cell(k1=-0.08), 5, 0.2, 0.02, TRIALS, seed=3, models=())
    o, se = rms_se(omse)
    assert abs(o / bound.rms_mm - 1) < 4 * se / bound.rms_mm + 0.02
    d = len(bound.free)  # NEES/d of a Gaussian estimate: mean 1, s.d. √(2/d) per trial
    assert abs(nees.mean() - 1) < 4 * np.sqrt(2 / d / TRIALS)
    bound, _, omse, *_ = lens_free
    o, se = rms_se(omse)
    assert abs(o / bound.rms_mm - 1) < 4 * se / bound.rms_mm + 0.02


def test_homography_at_the_limit_without_lens(lens_free):
    """eyetohand's homography on a lens-free cell: its check error over the oracle's within 4 paired
    standard errors (+0.5 %) of 1."""
    from limit import ratio_se

    _, _, omse, _, tallies, _ = lens_free
    r, se = ratio_se(np.array(tallies["homography"].mse), omse)
    assert abs(r - 1) < 4 * se + 0.005
