"""Does model M fit these pairs? K random split-half refits, each half compared with the other by
:func:`~eyetohand.calibration.diff.diff` (mrcal's cross-validation, for a robot-frame map).

Two halves of one data set are independent calibrations of one cell: with no model error they
differ by about their combined uncertainty. But each half's ``sigma`` is scaled by the noise its
own residuals show, and a model that lacks a term (perspective, a lens) turns what it cannot follow
into residual "noise": the halves then differ by more, and their sigma grows by as much — the ratio
stays ≈ 1 and says nothing (measured: an affine map of a tilted, distorted camera, 0.37 mm of
"noise" where the pairs carry 0.01 mm, split halves at mean squared ratio 0.7–1.1). So the halves'
uncertainties are put on one **reference noise**: the residual noise of ``auto``'s model fitted on
all the pairs (the model the data support; its noise is what the detector and robot really add).
Each half's covariance is rescaled to it (``C · s_ref² / s_half²``) and carries the reference fit's
dof for the test. Model M is then ``model error`` when the halves differ significantly (``diff``'s
raw layer at ``ALPHA``) in most splits — the median p-value over the K splits below ``ALPHA`` — and
``consistent`` otherwise. With ``auto`` (or the model it picks) the reference is its own noise, and
the test is of the halves' agreement only.

The pairs needed for a tolerance: a calibration's map error scales as 1/sqrt(n), so the combined
sigma of two calibrations of m pairs each, from the halves' (n/2 pairs each), is
``sigma_half · sqrt(n / 2 / m)``; ``pairs_for_tolerance`` is the least m that brings the halves' 95th
percentile of combined sigma (median over splits) to ``tolerance_mm``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace

import numpy as np

from eyetohand.calibration.diff import ALPHA, Difference, Verdict, diff
from eyetohand.calibration.file import Calibration
from eyetohand.calibration.fit import calibrate
from eyetohand.calibration.request import AUTO, resolve_model
from eyetohand.calibration.verify import check_tolerance
from eyetohand.core import DegenerateError, InputError, PointPairs
from eyetohand.solve import check_seed

MIN_HALF = 6
MAX_K = 500


@dataclass(frozen=True)
class CrossValidation:
    """The K split-half comparisons of ``model`` on n pairs, and what they say."""

    model: str
    reference_model: str
    reference_noise_mm: float
    model_noise_mm: float
    n_pairs: int
    splits: tuple[Difference, ...]
    verdict: Verdict
    reason: str
    tolerance_mm: float | None
    pairs_for_tolerance: int | None
    alpha: float = ALPHA

    @property
    def p_values(self) -> np.ndarray:
        return np.array([d.layers[0].p_value for d in self.splits])

    @property
    def ratio_median(self) -> float:
        """Median over the splits of each split's median ratio."""
        return float(np.median([d.ratio_median for d in self.splits]))

    @property
    def q_median(self) -> float:
        return float(np.median([d.layers[0].q for d in self.splits]))

    @property
    def rejected(self) -> int:
        return int((self.p_values < self.alpha).sum())

    @property
    def rms_mm(self) -> float:
        return float(np.median([d.rms_mm for d in self.splits]))

    @property
    def sigma_p95_mm(self) -> float:
        """Median over the splits of the 95th percentile of the halves' combined sigma (mm)."""
        return float(np.median([np.percentile(d.sigma_mm, 95) for d in self.splits]))

    def to_dict(self) -> dict:
        return {
            "verdict": str(self.verdict),
            "reason": self.reason,
            "model": self.model,
            "reference_model": self.reference_model,
            "reference_noise_mm": self.reference_noise_mm,
            "model_noise_mm": self.model_noise_mm,
            "pairs": self.n_pairs,
            "k": len(self.splits),
            "rejected": self.rejected,
            "p_value_median": float(np.median(self.p_values)),
            "ratio_median": self.ratio_median,
            "q_median": self.q_median,
            "rms_mm": self.rms_mm,
            "sigma_p95_mm": self.sigma_p95_mm,
            "tolerance_mm": self.tolerance_mm,
            "pairs_for_tolerance": self.pairs_for_tolerance,
            "alpha": self.alpha,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def summary(self) -> str:
        lines = [
            f"verdict: {self.verdict} — {self.reason}",
            f"model {self.model} on {self.n_pairs} pairs: {len(self.splits)} split halves, "
            f"{self.rejected} differ significantly (p < {self.alpha:g}); median p "
            f"{float(np.median(self.p_values)):.2g}",
            f"halves differ by RMS {self.rms_mm:.4g} mm (median over splits); ratio to combined sigma: "
            f"median {self.ratio_median:.3g}, mean squared {self.q_median:.3g} (≈ 1 when the model fits)",
            f"residual noise: {self.model} {self.model_noise_mm:.4g} mm, reference "
            f"{self.reference_model} {self.reference_noise_mm:.4g} mm",
            f"combined sigma of two half calibrations (p95): {self.sigma_p95_mm:.4g} mm",
        ]
        if self.tolerance_mm is not None:
            need = (
                "n/a: more pairs do not cure a model error"
                if self.pairs_for_tolerance is None
                else f"{self.pairs_for_tolerance} (sigma ~ 1/sqrt(n))"
            )
            lines.append(f"pairs for a combined sigma under {self.tolerance_mm:g} mm: {need}")
        return "\n".join(lines)


def split_halves(pairs: PointPairs, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two random halves (sorted indices), each with its share of every height and tool angle: the pairs
    grouped by (z to 1 µm, angle), each group shuffled, and the groups dealt alternately to the halves
    (a half with one height only, or without the turned pairs, would not fit the same model)."""
    z = np.round(pairs.xyz_mm[:, 2], 3)
    ang = np.zeros(len(z)) if pairs.angle_deg is None else np.round(np.asarray(pairs.angle_deg, float), 6)
    keys = np.unique(np.column_stack([z, ang]), axis=0, return_inverse=True)[1].reshape(-1)
    dealt = np.concatenate([rng.permutation(np.flatnonzero(keys == g)) for g in range(int(keys.max()) + 1)])
    return np.sort(dealt[0::2]), np.sort(dealt[1::2])


def _rescaled(cal: Calibration, noise_mm: float, dof: int) -> Calibration:
    """The calibration with its uncertainty put on the reference noise (covariance ∝ noise²)."""
    unc = cal.uncertainty
    if unc is None:  # every fit of this version records one
        raise InputError("a split half's fit recorded no uncertainty")
    f = (noise_mm / unc.noise_mm) ** 2 if unc.noise_mm > 0 else 1.0
    return replace(cal, uncertainty=replace(unc, covariance=unc.covariance * f, noise_mm=noise_mm, dof=dof))


def crossval(
    pairs: PointPairs,
    model: str = "auto",
    *,
    k: int = 20,
    seed: int | None = 0,
    tolerance_mm: float | None = None,
    image_size: tuple[int, int] | None = None,
) -> CrossValidation:
    """K random split-half refits of ``model`` on ``pairs`` (see the module's text; the halves keep
    every height and tool angle: :func:`split_halves`)."""
    choice = resolve_model(model)  # an unknown name refused in the library's words, listing the choices
    if not (isinstance(k, int) and not isinstance(k, bool) and 1 <= k <= MAX_K):
        raise InputError(f"k: expected a whole number of splits from 1 to {MAX_K}, got {k!r}")
    if tolerance_mm is not None:
        tolerance_mm = check_tolerance(tolerance_mm)  # verify's rule and words (a bool or text refused too)
    seed = check_seed(seed)
    n = len(pairs.uv_px)
    if n < 2 * MIN_HALF:
        raise InputError(f"crossval needs at least {2 * MIN_HALF} pairs (two halves of {MIN_HALF}), got {n}")
    reference = calibrate(pairs, "auto", image_size=image_size, loo=False)
    name = reference.model_name if choice is AUTO else choice.name
    full = (
        reference
        if name == reference.model_name
        else calibrate(pairs, name, image_size=image_size, loo=False)
    )
    ref_unc, full_unc = reference.uncertainty, full.uncertainty
    if ref_unc is None or full_unc is None:
        raise InputError("the fit recorded no uncertainty")
    rng = np.random.default_rng(seed)
    splits = []
    for i in range(k):
        halves = split_halves(pairs, rng)
        try:
            a, b = (
                _rescaled(
                    calibrate(pairs.subset(h), name, image_size=image_size, loo=False),
                    ref_unc.noise_mm,
                    ref_unc.dof,
                )
                for h in halves
            )
            splits.append(diff(a, b))
        except (InputError, DegenerateError) as exc:
            sizes = f"{len(halves[0])} and {len(halves[1])}"
            raise InputError(f"split {i + 1}: halves of {sizes} pairs cannot be compared: {exc}") from None
    p_med = float(np.median([d.layers[0].p_value for d in splits]))
    if p_med < ALPHA:
        verdict = Verdict.MODEL_ERROR
        reason = (
            f"the halves differ by more than their uncertainty allows in most splits (median p {p_med:.2g}): "
            f"{name} leaves {full_unc.noise_mm:.3g} mm of residual where {reference.model_name} leaves "
            f"{ref_unc.noise_mm:.3g} mm"
        )
    else:
        verdict = Verdict.CONSISTENT
        reason = f"independent halves agree within their combined uncertainty (median p {p_med:.2g})"
    need = None
    if tolerance_mm is not None and verdict is Verdict.CONSISTENT:  # more pairs do not cure a model error
        sig = float(np.median([np.percentile(d.sigma_mm, 95) for d in splits]))
        need = max(int(math.ceil((n // 2) * (sig / tolerance_mm) ** 2)), 1)
    return CrossValidation(
        name,
        reference.model_name,
        ref_unc.noise_mm,
        full_unc.noise_mm,
        n,
        tuple(splits),
        verdict,
        reason,
        tolerance_mm,
        need,
    )
