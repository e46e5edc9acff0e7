"""Robot-space objectives over residuals (predicted − actual, mm), vectorised over a swarm.

A registry, name → :class:`Objective`, each with the facts its callers act on (they ask the
objective, never compare its name):

- ``l2``: the paper's equation (16), the 2-norm of all stacked residuals (mm);
- ``linf``: the largest point error (mm): what a user with a tolerance cares about;
- ``huber``: sum of Huber losses of the point errors (mm²), robust to a bad pair. Its threshold
  ``delta_mm`` defaults to 3 robust sigmas (1.4826 × median) of the starting fit's point errors.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from eyetohand.core import InputError


def _l2(r: np.ndarray, delta_mm: float) -> np.ndarray:
    # the sum of squares in one pass (einsum's sum of products, no BLAS), whatever r's strides
    return np.sqrt(np.einsum("...nk,...nk->...", r, r))


def _point_errors(r: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...k,...k->...", r, r))  # (P, N)


def _linf(r: np.ndarray, delta_mm: float) -> np.ndarray:
    return _point_errors(r).max(axis=-1)


def _huber(r: np.ndarray, delta_mm: float) -> np.ndarray:
    point = _point_errors(r)
    quad = 0.5 * point * point
    lin = delta_mm * (point - 0.5 * delta_mm)
    return np.where(point <= delta_mm, quad, lin).sum(axis=-1)


@dataclass(frozen=True)
class Objective:
    """A robot-space objective: ``values(residuals, delta_mm)`` of (P, N, 3) residuals → (P,), with
    the facts its callers act on."""

    name: str
    _values: Callable[[np.ndarray, float], np.ndarray]
    fitness_unit: str
    """The unit of its value (the fitness a fit reports): "mm", or "mm²" for the Huber loss."""
    fitness_label: str
    """What its value is, for a plot's axis."""
    held_out_what: str
    """What its held-out score per pair is called (``auto``'s report)."""
    smooth: bool = False
    """Differentiable in the residuals: least-squares solvers (lm) can minimise it."""
    least_squares: bool = False
    """The plain sum of squares (equation 16): LM's own routine; leave-one-out by Gauss–Newton; the
    held-out score is the RMS."""
    robust: bool = False
    """Has a Huber threshold ``delta_mm`` (recorded in the fit as ``huber_delta_mm``); its held-out
    score is the mean loss per pair."""

    def values(self, residuals: np.ndarray, delta_mm: float = 1.0) -> np.ndarray:
        """Objective of (P, N, 3) residuals → (P,). Non-finite residuals give +inf."""
        out = self._values(np.asarray(residuals, float), delta_mm)
        return np.where(np.isfinite(out), out, np.inf)

    def held_out_score(self, residuals_mm: np.ndarray, delta_mm: float) -> float:
        """A held-out residual set (N, 3) scored per pair: RMS (least squares), else the objective's
        value, per pair for a robust loss (a sum) and as it is for the largest error."""
        r = np.asarray(residuals_mm, float)
        if self.least_squares:
            return float(np.sqrt(np.mean((r * r).sum(axis=1))))
        return float(self.values(r[None], delta_mm)[0] / (len(r) if self.robust else 1))


REGISTRY: dict[str, Objective] = {
    o.name: o
    for o in (
        Objective(
            "l2",
            _l2,
            "mm",
            "best fitness, eq. (16): ‖residuals‖₂ [mm]",
            "held-out RMS",
            smooth=True,
            least_squares=True,
        ),
        Objective("linf", _linf, "mm", "best fitness: largest point error [mm]", "largest held-out error"),
        Objective(
            "huber",
            _huber,
            "mm²",
            "best fitness: Σ Huber loss [mm²]",
            "held-out Huber loss",
            smooth=True,
            robust=True,
        ),
    )
}
OBJECTIVES = tuple(REGISTRY)
SMOOTH_OBJECTIVES = tuple(o.name for o in REGISTRY.values() if o.smooth)


def get_objective(name: str | Objective) -> Objective:
    """The objective called ``name`` (an :class:`Objective` is its own); an unknown name lists the
    valid choices."""
    if isinstance(name, Objective):
        return name
    try:
        return REGISTRY[name]
    except (KeyError, TypeError):
        raise InputError(f"unknown objective {name!r}; choose one of: {', '.join(OBJECTIVES)}") from None


def find_objective(name: str) -> Objective | None:
    """The objective called ``name``, or None for a name this version does not know (a file's
    record read as it is)."""
    return REGISTRY.get(name) if isinstance(name, str) else None


def check_objective(name: str) -> str:
    """``name`` when it names an objective (:func:`get_objective`'s refusal otherwise)."""
    return get_objective(name).name


def huber_delta_mm(point_errors_mm: np.ndarray) -> float:
    """Default Huber threshold: 3 robust sigmas of the given point errors (at least 1 µm)."""
    return max(3.0 * 1.4826 * float(np.median(point_errors_mm)), 1e-3)


def objective_values(residuals: np.ndarray, objective: str | Objective, delta_mm: float = 1.0) -> np.ndarray:
    """Objective for (P, N, 3) residuals → (P,). Non-finite residuals give +inf."""
    return get_objective(objective).values(residuals, delta_mm)
