"""Robot-space objectives over residuals (predicted − actual, mm), vectorised over a swarm.

- ``l2``: the paper's equation (16), the 2-norm of all stacked residuals (mm);
- ``linf``: the largest point error (mm): what a user with a tolerance cares about;
- ``huber``: sum of Huber losses of the point errors (mm), robust to a bad pair. Its threshold
  ``delta_mm`` defaults to 3 robust sigmas (1.4826 × median) of the starting fit's point errors.
"""

from __future__ import annotations

import numpy as np

from eyetohand.core import InputError

OBJECTIVES = ("l2", "linf", "huber")
SMOOTH_OBJECTIVES = ("l2", "huber")


def check_objective(name: str) -> str:
    if name not in OBJECTIVES:
        raise InputError(f"unknown objective {name!r}; choose one of: {', '.join(OBJECTIVES)}")
    return name


def huber_delta_mm(point_errors_mm: np.ndarray) -> float:
    """Default Huber threshold: 3 robust sigmas of the given point errors (at least 1 µm)."""
    return max(3.0 * 1.4826 * float(np.median(point_errors_mm)), 1e-3)


def objective_values(residuals: np.ndarray, objective: str, delta_mm: float = 1.0) -> np.ndarray:
    """Objective for (P, N, 3) residuals → (P,). Non-finite residuals give +inf."""
    r = np.asarray(residuals, float)
    if objective == "l2":
        # the sum of squares in one pass (einsum's sum of products, no BLAS), whatever r's strides
        out = np.sqrt(np.einsum("...nk,...nk->...", r, r))
        return np.where(np.isfinite(out), out, np.inf)
    point = np.sqrt(np.einsum("...k,...k->...", r, r))  # (P, N)
    if objective == "linf":
        out = point.max(axis=-1)
    elif objective == "huber":
        quad = 0.5 * point * point
        lin = delta_mm * (point - 0.5 * delta_mm)
        out = np.where(point <= delta_mm, quad, lin).sum(axis=-1)
    else:
        check_objective(objective)
    return np.where(np.isfinite(out), out, np.inf)
