"""Finite differences over batched functions: every step of a Jacobian in one vectorised call."""

from __future__ import annotations

import numpy as np


def batch_jacobian(fun_batch, p: np.ndarray, step: np.ndarray | None = None) -> np.ndarray:
    """Forward-difference Jacobian (M, D) of a residual function, all D steps in one call:
    ``fun_batch`` maps (B, D) parameter rows to (B, M) residuals. Default step: SciPy's
    2-point rule, 1.5e-8 · max(|p|, 1)."""
    p = np.asarray(p, float)
    h = 1.5e-8 * np.maximum(np.abs(p), 1.0) if step is None else np.asarray(step, float)
    r = fun_batch(np.vstack([p, p + np.diag(h)]))
    return ((r[1:] - r[0]) / h[:, None]).T
