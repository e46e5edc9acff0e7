"""Accuracy statistics of a calibration on pairs: per point residuals (mm) and their summary.

``error_mm`` is the 3-D norm of (dx, dy, dz); for every model but the paper's, z is the object height
given with the pair, so dz = 0 and the error is the in-plane error.

Outliers: a Bonferroni-corrected test against a robust noise scale, so that a clean set raises a
flag rarely (measured, ``benchmarks/bench_outliers.py``), not on every third set as a median + 3 MAD
rule does. With c the coordinates that carry residuals (2 in-plane, 3 for a model that computes z)
and Gaussian noise of σ per coordinate, e²/σ² follows χ²(c). σ² is estimated robustly as median(e²)
/ median(χ²(c)) (a bad pair barely moves a median), and a pair is flagged when its e²/σ² exceeds the
χ²(c) quantile of 1 − α/N with α = ``OUTLIER_ALPHA`` = 0.01 % (N the set's size): each set of N
clean pairs of pure noise then raises a flag with probability about α; α is that small because real
residuals are not pure noise (a lens term a model lacks makes corner residuals systematic), and with
it the measured false-alarm rate on simulated clean sets stays under 1 % while a 1 mm bad pair — 30
to 100 noise sigmas — is still found. The errors are studentized first when the pairs' leverages h
are known (:func:`eyetohand.solve.uncertainty.pair_leverage`, the hat matrix's c × c block H of each
pair): a training residual r becomes √(rᵀ(I − H)⁻¹r) (the fit follows a pair of high leverage,
shrinking its residual) and a held-out one √(rᵀ(I − H)r) (left out, such a pair is extrapolated to)
— without this a 25-pair set's corner pairs raise a false alarm in a quarter of clean sets. Training
and check errors are tested, each set on its own; leave-one-out errors are not flagged: to first
order the studentized training residual *is* the studentized left-out one, and beyond first order a
left-out corner pair is an extrapolation whose error the model's structure, not the noise, sets
(flagging those raised a false alarm in 16 % of clean 25-pair sets). Sets of fewer than
``OUTLIER_MIN_PAIRS`` pairs are not tested (a median of four says nothing about the noise).

Mixed-up conventions (:func:`convention_mixup`): check pairs with u and v (or x and y) swapped, a sign
of x or y flipped, or robot coordinates in metres give errors of tens to thousands of mm where the
calibration holds hundredths; they are named, not fitted. The rule: with a reference set (leave-one-
out errors, else training) of RMS s on m pairs and c coordinates carrying residuals, a set of n
pairs of RMS r is *far off* when both (1) r > ``MIXUP_RATIO`` · s (5: 25 times the mean square; a
check set measured later or nearer the region's edge is 1–3 times worse, a mix-up 100–10 000 times)
and (2) the ratio of mean squares r²/s² exceeds the F(c n, c m) quantile of 1 − ``MIXUP_P`` (0.1 %),
the test that the two sets' errors have the same σ (each squared error a σ² χ² variable, s² itself an
estimate on c m dof), which (1) leaves binding only for sets of a few pairs. Then each mix-up is
undone in turn; one *explains* the errors when, undone, the set is no longer far off and its RMS is at
least ``MIXUP_RATIO`` times smaller than as given; the one of smallest RMS is named.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from eyetohand.core import InputError, PointError, PointPairs, Stats
from eyetohand.models import Model

OUTLIER_ALPHA = 1e-4
OUTLIER_MIN_PAIRS = 8
_FLOOR_MM = 1e-9


def _chi2_sf(x: float, dof: int) -> float:
    """P(χ² > x) for an integer number of degrees of freedom, in closed form (all terms positive):
    e^(−x/2) Σ_{j<dof/2} (x/2)^j / j! for even dof; erfc(√(x/2)) + e^(−x/2) Σ_{j=1}^{(dof−1)/2}
    (x/2)^(j−½) / Γ(j+½) for odd."""
    h = 0.5 * x
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for j in range(1, dof // 2):
            term *= h / j
            total += term
        return math.exp(-h) * total
    total = 0.0
    if dof > 1:
        term = math.sqrt(h) / math.gamma(1.5)
        total = term
        for j in range(2, (dof + 1) // 2):
            term *= h / (j - 0.5)
            total += term
    return math.erfc(math.sqrt(h)) + math.exp(-h) * total


def _chi2_isf(q: float, dof: int) -> float:
    """x with P(χ²_dof > x) = q (0 < q < 1, integer dof ≥ 1): Newton on log P, kept inside a
    bracket. SciPy's ``2 gammainccinv(dof/2, q)`` to 1e-12 relative (tests/test_speed_paths.py),
    without importing SciPy (~0.2 s) on every calibration load."""
    if dof == 2:
        return -2.0 * math.log(q)
    lo, hi = 0.0, 2.0 * dof + 2.0
    while _chi2_sf(hi, dof) > q:
        lo, hi = hi, 2.0 * hi
    log_q = math.log(q)
    log_norm = 0.5 * dof * math.log(2.0) + math.lgamma(0.5 * dof)  # of the density
    x = 0.5 * (lo + hi)
    for _ in range(100):
        s = _chi2_sf(x, dof)
        if s > q:
            lo = x
        else:
            hi = x
        pdf = math.exp((0.5 * dof - 1.0) * math.log(x) - 0.5 * x - log_norm)
        new = x + (math.log(s) - log_q) * s / pdf if s > 0.0 and pdf > 0.0 else 0.5 * (lo + hi)
        if not lo < new < hi:
            new = 0.5 * (lo + hi)
        if abs(new - x) <= 4e-16 * x:
            return new
        x = new
    return x


def _median(x: np.ndarray) -> float:
    """``np.median`` of finite values, bit for bit (the middle one, or the mean of the middle two as
    ``(a + b) / 2``), without NumPy's NaN check, which imports ``numpy.ma`` (~13 ms of every
    ``eyetohand apply``, which re-proves a file's outlier flags on load)."""
    n = len(x)
    if n == 0:
        return math.nan
    k = n // 2
    if n % 2:
        return float(np.partition(x, k)[k])
    part = np.partition(x, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2)


def _percentile(x: np.ndarray, q: float) -> float:
    """``np.percentile(x, q)`` of a 1-D array (NumPy's default "linear" method), bit for bit: NumPy's
    own partitions through ``np.unique``, which imports ``numpy.ma`` as :func:`_median` says. Arrays
    with a NaN, or empty, go to NumPy (its NaN and its error)."""
    n = len(x)
    if n == 0 or not np.isfinite(x).all():
        return float(np.percentile(x, q))
    virtual = (n - 1) * np.true_divide(q, 100)
    if virtual >= n - 1:
        return float(np.max(x))
    lo = int(np.floor(virtual))
    gamma = virtual - lo
    part = np.partition(x, (lo, lo + 1))
    a, b = part[lo], part[lo + 1]
    diff = b - a
    return float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)


def outlier_threshold_mm(errors_mm: np.ndarray, n_coords: int = 2, alpha: float = OUTLIER_ALPHA) -> float:
    """The error (mm) above which a pair of this set is flagged (see the module docstring)."""
    e = np.asarray(errors_mm, float)
    e = e[np.isfinite(e)]
    sigma2 = _median(e * e) / _chi2_isf(0.5, n_coords)
    return float(np.sqrt(max(sigma2, _FLOOR_MM**2) * _chi2_isf(alpha / max(len(e), 1), n_coords)))


def outlier_mask(errors_mm: np.ndarray, n_coords: int = 2, alpha: float = OUTLIER_ALPHA) -> np.ndarray:
    """True where an error exceeds :func:`outlier_threshold_mm` (none below ``OUTLIER_MIN_PAIRS``)."""
    e = np.asarray(errors_mm, float)
    if int(np.isfinite(e).sum()) < OUTLIER_MIN_PAIRS:
        return np.zeros(len(e), bool)
    return e > outlier_threshold_mm(e, n_coords, alpha)


def studentized(residuals_mm, leverage, *, held_out: bool) -> np.ndarray:
    """(N,) errors scaled to a common variance by the pairs' hat-matrix blocks ``leverage``
    (N, c, c): √(rᵀ(I − H)⁻¹r) for training residuals, √(rᵀ(I − H)r) for held-out ones."""
    H = np.asarray(leverage, float)
    c = H.shape[-1]
    r = np.asarray(residuals_mm, float)[:, :c]
    M = np.eye(c) - H
    if not held_out:
        w, V = np.linalg.eigh(M)
        M = np.einsum("nij,nj,nkj->nik", V, 1.0 / np.maximum(w, 1e-6), V)
    q = np.einsum("ni,nij,nj->n", r, M, r)
    return np.sqrt(np.maximum(q, 0.0))


def stats_from_residuals(residuals_mm: np.ndarray, ids, *, leverage=None, held_out: bool = False) -> Stats:
    """Stats from (N, 3) residuals (predicted − actual) and the pair ids; ``leverage`` (N, c, c),
    the training pairs' hat-matrix blocks, studentizes the outlier test (``held_out``: these are
    held-out residuals)."""
    r = np.asarray(residuals_mm, float).reshape(-1, 3)
    e = np.linalg.norm(r, axis=1)
    n_coords = max(int((np.abs(r) > 0).any(axis=0).sum()), 1)  # dz = 0 unless the model computes z
    if held_out:
        out = np.zeros(len(e), bool)  # see the module docstring: held-out errors are not flagged
    else:
        out = outlier_mask(e if leverage is None else studentized(r, leverage, held_out=False), n_coords)
    pts = tuple(
        PointError(str(i), float(d[0]), float(d[1]), float(d[2]), float(x), bool(o))
        for i, d, x, o in zip(ids, r, e, out, strict=True)
    )
    return Stats(
        n=len(e),
        rms_mm=float(np.sqrt(np.mean(e**2))),
        mean_mm=float(e.mean()),
        max_mm=float(e.max()),
        p95_mm=_percentile(e, 95.0),
        points=pts,
    )


def mapped_residuals(model, pairs, what: str = "pair") -> np.ndarray:
    """(N, 3) residuals of ``model`` on ``pairs``; a pair it maps to no finite point is refused by id
    (no statistic can be made of it) with :class:`InputError`."""
    with np.errstate(all="ignore"):
        res = model.residuals(pairs.uv_px, pairs.xyz_mm)
    lost = ~np.isfinite(res).all(axis=1)
    if lost.any():
        raise InputError(
            f"{pairs.source}: {what} {pairs.ids[int(np.argmax(lost))]}: the calibration maps it to no "
            f"finite point (beyond its lens's fold or its horizon; {int(lost.sum())} of {len(res)} "
            f"{what}s): check where it was calibrated, or leave such pairs out"
        )
    return res


class Fitted(Protocol):
    """What carries a fitted model: a :class:`~eyetohand.calibration.Calibration`."""

    @property
    def model(self) -> Model: ...


def evaluate(calibration: Fitted | Model, pairs: PointPairs) -> Stats:
    """Stats of ``calibration`` (a Calibration or a model) on ``pairs``, each mapped at its own z."""
    model = calibration if isinstance(calibration, Model) else calibration.model
    return stats_from_residuals(mapped_residuals(model, pairs), pairs.ids)


MIXUP_RATIO = 5.0
MIXUP_P = 0.001


@dataclass(frozen=True)
class Mixup:
    """A mixed-up convention that explains a set's errors: what looks wrong, and the set's RMS error
    (mm) with it undone and as given."""

    source: str
    what: str  # "u and v look swapped"
    undone: str  # "if swapped"
    rms_undone_mm: float
    rms_given_mm: float

    @property
    def reason(self) -> str:
        """The finding without the source: ``u and v look swapped (check RMS 0.0303 mm if swapped,
        63.2 mm as given)``."""
        return (
            f"{self.what} (check RMS {_mm(self.rms_undone_mm)} mm {self.undone}, "
            f"{_mm(self.rms_given_mm)} mm as given)"
        )

    def describe(self) -> str:
        return f"{self.source}: {self.reason}"

    def to_dict(self) -> dict:
        return {
            "what": self.what,
            "rms_undone_mm": self.rms_undone_mm,
            "rms_given_mm": self.rms_given_mm,
            "message": self.describe(),
        }


def _mm(v: float) -> str:
    return f"{v:.3g}" if v < 1000 else f"{v:.0f}"


def _swap_uv(uv, xyz):
    return uv[:, ::-1], xyz


def _swap_xy(uv, xyz):
    return uv, xyz[:, [1, 0, 2]]


def _negate_x(uv, xyz):
    return uv, xyz * np.array([-1.0, 1.0, 1.0])


def _negate_y(uv, xyz):
    return uv, xyz * np.array([1.0, -1.0, 1.0])


def _metres(uv, xyz):
    return uv, xyz * 1000.0


MIXUPS = (
    ("u and v look swapped", "if swapped", _swap_uv),
    ("x and y look swapped", "if swapped", _swap_xy),
    ("x has the wrong sign", "with x negated", _negate_x),
    ("y has the wrong sign", "with y negated", _negate_y),
    ("x, y, z look like metres, not mm", "if × 1000", _metres),
)
"""The mix-ups :func:`convention_mixup` tries: (what looks wrong, how it was undone, the undoing)."""


def far_off(rms_mm: float, n: int, reference: Stats, n_coords: int) -> bool:
    """Whether a set of ``n`` pairs with RMS error ``rms_mm`` is far off the ``reference`` set's (the
    module docstring's rule: ``MIXUP_RATIO`` times its RMS and beyond the F test at ``MIXUP_P``)."""
    ref = max(reference.rms_mm, _FLOOR_MM)
    if not rms_mm > MIXUP_RATIO * ref:  # NaN too: not a finding
        return False
    if not math.isfinite(rms_mm):
        return True
    from scipy import stats

    limit = float(stats.f.isf(MIXUP_P, n_coords * n, n_coords * max(reference.n, 1)))
    return (rms_mm / ref) ** 2 > limit


def _rms(model, uv, xyz) -> tuple[float, int]:
    with np.errstate(all="ignore"):
        r = np.asarray(model.residuals(uv, xyz), float).reshape(-1, 3)
    if not np.isfinite(r).all():
        return math.inf, 2
    c = max(int((np.abs(r) > 0).any(axis=0).sum()), 1)
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))), c


def convention_mixup(model: Fitted | Model, pairs: PointPairs, reference: Stats) -> Mixup | None:
    """The mixed-up convention (``MIXUPS``) that explains why ``pairs``' errors under ``model`` are far
    off the ``reference`` set's (leave-one-out, else training), or None: when they are not far off, or
    no single mix-up explains them (module docstring)."""
    model = model if isinstance(model, Model) else model.model
    given, c = _rms(model, pairs.uv_px, pairs.xyz_mm)
    n = len(pairs)
    if not far_off(given, n, reference, c):
        return None
    best = None
    for what, undone, undo in MIXUPS:
        rms, c_undone = _rms(model, *undo(np.asarray(pairs.uv_px), np.asarray(pairs.xyz_mm)))
        if rms * MIXUP_RATIO > given or far_off(rms, n, reference, c_undone):
            continue
        if best is None or rms < best.rms_undone_mm:
            best = Mixup(pairs.source, what, undone, rms, given)
    return best
