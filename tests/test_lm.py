"""eyetohand.geometry.lm: MINPACK's Levenberg–Marquardt without least_squares' set-up must be least_squares(
method="lm", x_scale="jac") itself — the same iterates, evaluation count, answer and words."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares

from eyetohand.calibration.fit import fit_model
from eyetohand.core.pairs import load_pairs
from eyetohand.geometry.lm import levenberg_marquardt
from eyetohand.geometry.numdiff import batch_jacobian

sys.path.insert(0, str(Path(__file__).parent))
from synth import grid_pairs, make_camera  # noqa: E402

PAPER = Path(__file__).resolve().parents[1] / "src/eyetohand/data/paper/calibration_points.csv"


def _problems():
    cam = make_camera(tilt_deg=8, dist=[-0.22, 0.05, 0, 0, 0])
    lens_cell = grid_pairs(cam, 5, heights=(100.0,), noise_px=0.3, span_mm=160)
    two_heights = grid_pairs(make_camera(tilt_deg=10, seed=2), 4, heights=(0.0, 40.0), noise_px=0.2, seed=6)
    return [
        (load_pairs(PAPER), "homography"),
        (lens_cell, "homography"),
        (lens_cell, "homography-radial"),
        (two_heights, "dlt3d"),
        (two_heights, "camera"),
    ]


@pytest.mark.parametrize("case", range(5))
def test_levenberg_marquardt_is_least_squares_lm_bit_for_bit(case):
    """Not the paper model: on its ill-conditioned B (a scale freedom) SciPy's MINPACK reads past the
    end of the Jacobian and is not reproducible — two least_squares runs can differ
    (docs/performance.md)."""
    pairs, name = _problems()[case]
    start, _ = fit_model(pairs, name, "linear")
    uv, xyz = pairs.uv_px, pairs.xyz_mm

    def fun_batch(P):
        return (start.batch_image_to_robot(P, uv, xyz[:, 2]) - xyz).reshape(len(P), -1)

    def fun(p):
        return fun_batch(p[None])[0]

    def jac(p):
        return batch_jacobian(fun_batch, p)

    theirs = least_squares(fun, start.params, jac=jac, method="lm", x_scale="jac")
    ours = levenberg_marquardt(fun, start.params, jac)
    assert ours.nfev == theirs.nfev
    assert ours.message == theirs.message
    assert ours.converged is (theirs.status > 0)  # least_squares' status: 0 = out of evaluations
    np.testing.assert_array_equal(ours.x.view(np.int64), theirs.x.view(np.int64))
    np.testing.assert_array_equal(ours.fun, theirs.fun)
    assert np.abs(ours.x - start.params).max() > 0  # it moved: a fit, not the start handed back
    # and the lm solver is that fit
    fitted, info = fit_model(pairs, name, "lm")
    np.testing.assert_array_equal(fitted.params, theirs.x)
    assert info.message == theirs.message and info.nfev == theirs.nfev


def test_levenberg_marquardt_refuses_a_start_it_cannot_evaluate():
    with pytest.raises(ValueError, match="Residuals are not finite in the initial point"):
        levenberg_marquardt(lambda p: np.array([np.nan, p[0]]), np.zeros(1), lambda p: np.ones((2, 1)))


def test_a_fit_out_of_evaluations_says_so_in_a_flag_as_least_squares_status_does():
    """x**k has its minimum at 0 but LM's steps shrink x by a fixed fraction: no tolerance is met before
    the 100 D evaluations run out. ``converged`` is False exactly where least_squares' status is 0,
    True on the same problem with k = 1 (one step), so no caller reads the words to know."""
    for k, converged in ((1, True), (3, False), (21, False)):

        def fun(x, k=k):
            return np.array([x[0] ** k, 1e-3 * x[1]])

        def jac(x, k=k):
            return np.array([[k * x[0] ** (k - 1), 0.0], [0.0, 1e-3]])

        theirs = least_squares(fun, [1.0, 1.0], jac=jac, method="lm", x_scale="jac")
        ours = levenberg_marquardt(fun, np.array([1.0, 1.0]), jac)
        assert ours.converged is converged is (theirs.status > 0), (k, theirs.status)
        assert ours.nfev == theirs.nfev and (converged or ours.nfev == 200)


def test_levenberg_marquardt_words_are_least_squares_words_for_every_minpack_code():
    """Fits record why they stopped; the words must stay those least_squares gives (its tables)."""
    from scipy.optimize._lsq.least_squares import FROM_MINPACK_TO_COMMON, TERMINATION_MESSAGES

    from eyetohand.geometry.lm import _MESSAGES

    assert set(_MESSAGES) == set(FROM_MINPACK_TO_COMMON)
    for code, words in _MESSAGES.items():
        assert words == TERMINATION_MESSAGES[FROM_MINPACK_TO_COMMON[code]]


def test_the_paper_models_lm_fit_holds_its_gauge_and_is_reproducible():
    """The paper's B has 12 numbers for a 9-coefficient map: lm refines the nine elements of M with
    (b14, b24, b34) held at the start's (full rank), so the fit is the same every time — refining all
    twelve, MINPACK read past its Jacobian and two runs could differ — and its leave-one-out takes
    the batched Gauss-Newton steps (within 1e-7 mm of refits) instead of 16 refits."""
    from eyetohand.calibration.fit import cross_validate, loo_gauss_newton

    pairs = load_pairs(PAPER)
    start, _ = fit_model(pairs, "paper", "linear")
    runs = set()
    heap = []
    for k in range(12):
        heap.append(np.ones(int(np.random.default_rng(k).integers(1, 4000))))  # a different heap each time
        fitted, info = fit_model(pairs, "paper", "lm")
        runs.add((fitted.params.tobytes(), info.nfev))
    assert len(runs) == 1
    assert fitted.gauge_params == (3, 7, 11)
    np.testing.assert_array_equal(fitted.params[[3, 7, 11]], start.params[[3, 7, 11]])
    assert np.abs(fitted.params - start.params).max() > 0
    rms = float(np.sqrt(np.mean((fitted.residuals(pairs.uv_px, pairs.xyz_mm) ** 2).sum(axis=1))))
    assert abs(rms - 0.0264584) < 1e-7  # the least-squares fit: eq. 16 = 4 x RMS = 0.105834 mm
    fast = loo_gauss_newton(fitted, pairs.uv_px, pairs.xyz_mm)
    assert fast is not None
    np.testing.assert_allclose(fast, cross_validate(pairs, "paper", refit=True), rtol=0, atol=1e-7)
