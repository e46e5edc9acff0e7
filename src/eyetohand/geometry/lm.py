"""Levenberg–Marquardt with a user Jacobian: MINPACK's ``lmder`` as ``scipy.optimize.least_squares(
method="lm", x_scale="jac")`` runs it — the same call, so the same iterates, evaluations and answer —
without least_squares' per-call set-up (its function wrappers, input checks and a Jacobian at the
solution only to report the gradient): a fifth to a third of a 25-pair homography fit's time
(docs/performance.md).

SciPy's ``leastsq`` is the public door to that routine; it evaluates the function and the Jacobian
at the start once more to check their shapes, so both are remembered for their last argument here
(as least_squares' own wrappers do) and MINPACK's first calls reuse them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

# least_squares' words for MINPACK's exit codes (scipy/optimize/_lsq/least_squares.py), which fits
# have always recorded: a calibration file says what stopped its fit in the same words as before
_MESSAGES = {
    0: "Improper input parameters status returned from `leastsq`",
    1: "`ftol` termination condition is satisfied.",
    2: "`xtol` termination condition is satisfied.",
    3: "Both `ftol` and `xtol` termination conditions are satisfied.",
    4: "`gtol` termination condition is satisfied.",
    5: "The maximum number of function evaluations is exceeded.",
}
CONVERGED = frozenset({1, 2, 3, 4})  # MINPACK's codes for a tolerance met (5: out of evaluations)


@dataclass(frozen=True)
class LMResult:
    """``x`` the solution, ``fun`` its residuals, ``nfev`` MINPACK's evaluation count, ``message``
    why it stopped (least_squares' words), ``converged`` whether a tolerance stopped it (False: it ran
    out of evaluations, ``100 D``, or MINPACK refused its input): a caller decides on this, never on
    the words."""

    x: np.ndarray
    fun: np.ndarray
    nfev: int
    message: str
    converged: bool


def _last(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    """``fn`` remembered for its last argument (a copy of it: MINPACK reuses its buffers). A repeat
    answers a copy: MINPACK keeps the first array it is given as its residual buffer and writes into
    it, which must not reach the remembered value."""
    memo: list = [None, None]

    def call(x: np.ndarray) -> np.ndarray:
        if memo[0] is not None and np.array_equal(x, memo[0]):
            return memo[1].copy()
        value = fn(x)
        memo[0], memo[1] = np.array(x, copy=True), value
        return value

    return call


def levenberg_marquardt(
    fun: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    jac: Callable[[np.ndarray], np.ndarray],
    *,
    tol: float = 1e-8,
) -> LMResult:
    """Minimise ``sum(fun(x)**2)`` from ``x0``; ``jac(x)`` is the (M, D) Jacobian of ``fun``'s (M,)
    residuals. Raises ValueError, as least_squares does, when the residuals at ``x0`` are not
    finite. ``tol`` is ``ftol``, ``xtol`` and ``gtol`` at once (least_squares' defaults: 1e-8);
    at most ``100 D`` evaluations, as least_squares allows."""
    from scipy.optimize import leastsq  # lazily: SciPy costs ~0.4 s of start-up

    x0 = np.array(x0, dtype=float)  # MINPACK works in this copy
    fun = _last(fun)
    if not np.isfinite(fun(x0)).all():
        raise ValueError("Residuals are not finite in the initial point.")  # least_squares' refusal
    x, _cov, info, _mesg, ier = leastsq(
        fun,
        x0,
        Dfun=_last(jac),
        full_output=True,
        col_deriv=False,
        ftol=tol,
        xtol=tol,
        gtol=tol,
        maxfev=100 * x0.size,
        factor=100.0,
        diag=None,
    )
    words = _MESSAGES.get(ier, f"MINPACK code {ier}")
    return LMResult(np.asarray(x, float), info["fvec"], int(info["nfev"]), words, ier in CONVERGED)
