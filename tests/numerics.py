"""Tolerances from a problem's conditioning, for tests that compare numbers computed on one machine (or by
one algorithm) with numbers computed on another: not tests, not fixtures.

A BLAS kernel (OpenBLAS picks one per CPU: Haswell, SkylakeX, ...) sums in its own order, with or without
fused multiply-adds, so every product it computes may differ from another kernel's in its last bits. What
that does to an answer is the answer's condition number for rounding times eps: a tolerance below that
holds on one kernel only (CI runs the numerical tests under a second kernel to catch one, .ci/run).

:func:`rounding_condition` measures that condition number where no closed form is at hand (a pipeline
of fits, a lens fit's shallow valley): how far each answer moves, relative to its size, when every input
number is perturbed by a couple of units in the last place — the size of the differences a kernel makes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

EPS = float(np.finfo(float).eps)

# a kernel's answer differs from another's by a few roundings per operation where a perturbation of the
# inputs by ULPS is one rounding at the start: K covers that, and the response's spread between random
# perturbations (a factor ~2 between trials of the conveyor fit)
ULPS = 2.0
K = 16.0


def rounding_condition(
    compute: Callable[..., Mapping[str, object]],
    inputs: Mapping[str, np.ndarray],
    *,
    trials: int = 3,
    seed: int = 0,
) -> dict[str, float]:
    """Each answer's relative condition number for rounding, in units of eps: the largest, over ``trials``
    random perturbations of every float in ``inputs`` by up to ``ULPS`` units in the last place,
    of ``‖Δy‖ / (‖y‖ · ULPS · eps)`` for each ``y`` in ``compute(**inputs)`` (norm-wise, so a vector's small
    components are judged against the vector). At least 1: an answer never has less than its own
    rounding."""
    base = {k: np.ravel(np.asarray(v, float)) for k, v in compute(**inputs).items()}
    kappa = dict.fromkeys(base, 1.0)
    rng = np.random.default_rng(seed)
    for _ in range(trials):
        moved = {}
        for name, a in inputs.items():
            a = np.asarray(a, float)
            moved[name] = a * (1.0 + ULPS * EPS * rng.uniform(-1.0, 1.0, a.shape))
        out = compute(**moved)
        for k, y in base.items():
            dy = np.linalg.norm(np.ravel(np.asarray(out[k], float)) - y)
            kappa[k] = max(kappa[k], float(dy / (np.linalg.norm(y) * ULPS * EPS)))
    return kappa


def assert_within_rounding(got, want, kappa: float, what: str = "") -> None:
    """``‖got − want‖ ≤ K · kappa · eps · ‖want‖``: equal as far as the problem's conditioning
    (``kappa``, from :func:`rounding_condition`) lets two machines' roundings agree."""
    got, want = np.ravel(np.asarray(got, float)), np.ravel(np.asarray(want, float))
    tol = K * kappa * EPS * float(np.linalg.norm(want))
    err = float(np.linalg.norm(got - want))
    assert err <= tol, f"{what}: ‖Δ‖ = {err:.3g} > {tol:.3g} (K {K:g} × κ {kappa:.3g} × eps × ‖want‖)"
