"""Pairs measured against a calibration (``evaluate``, ``verify``): where they lie, and whether their
columns mean what the calibration's did.

Two guards, one set of words for the CLI and HTTP:

- **Region and heights** — the rule of :meth:`Calibration.map` (:mod:`eyetohand.geometry.region`): a
  pair whose pixel lies beyond the training points' hull and its margin, or whose height lies beyond
  the calibrated range (a single-height model: off its plane), is where the calibration answers no
  mapping; its error would measure an extrapolation. They are counted and named by id, and refused
  unless ``allow_outside`` (then a warning says how many were evaluated anyway).
- **Conventions** — errors far above what the calibration holds (leave-one-out, else training) are
  tested against the usual mix-ups (:func:`eyetohand.solve.convention_mixup`: u↔v, x↔y, a sign of x or
  y, metres for mm) and the one that explains them is named, as a warning, and in the region refusal
  (swapped u and v usually put the pairs outside the region, so the refusal is where it is seen).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eyetohand.calibration.circles import as_fitted
from eyetohand.calibration.file import Calibration
from eyetohand.core import InputError, PointPairs, Stats
from eyetohand.geometry import PLANE_TOLERANCE_MM
from eyetohand.models import HeightRule
from eyetohand.solve import Mixup, convention_mixup, mapped_residuals, stats_from_residuals

MAX_IDS_SHOWN = 8
ALLOW_OUTSIDE_WORDS = "allow_outside evaluates them anyway"


def mixup(cal: Calibration, pairs: PointPairs) -> Mixup | None:
    """The mixed-up convention that explains ``pairs``' errors, or None (the rule:
    :mod:`eyetohand.solve.evaluate`); the reference is the calibration's leave-one-out errors, else
    its training errors."""
    reference = cal.loo if cal.loo is not None else cal.train
    return convention_mixup(cal.model, pairs, reference)


@dataclass(frozen=True)
class Coverage:
    """Which pairs lie outside the calibrated region (image) and outside its heights, as words."""

    n: int
    region_ids: tuple[str, ...]
    height_ids: tuple[str, ...]
    region_words: str  # "(the farthest 35 px beyond the training points' hull, margin 20.3 px)"
    height_words: str

    @property
    def n_outside(self) -> int:
        return len(set(self.region_ids) | set(self.height_ids))

    def describe(self) -> str:
        """``3 of 20 pairs lie outside the calibrated region (ids 4, 7, 9; …)``, and/or the heights."""
        parts = []
        if self.region_ids:
            parts.append(
                f"{len(self.region_ids)} of {self.n} pairs lie outside the calibrated region "
                f"({_ids(self.region_ids)}; {self.region_words})"
            )
        if self.height_ids:
            parts.append(
                f"{len(self.height_ids)} of {self.n} lie outside the calibrated heights "
                f"({_ids(self.height_ids)}; {self.height_words})"
            )
        return " and ".join(parts)

    def to_dict(self) -> dict:
        return {
            "n": self.n,
            "outside_region": list(self.region_ids),
            "outside_heights": list(self.height_ids),
        }


def _ids(ids: tuple[str, ...]) -> str:
    shown = ", ".join(ids[:MAX_IDS_SHOWN]) + (" …" if len(ids) > MAX_IDS_SHOWN else "")
    return f"id{'s' if len(ids) > 1 else ''} {shown}"


def coverage(cal: Calibration, pairs: PointPairs) -> Coverage:
    """Where ``pairs`` lie against the calibrated region and heights (no region recorded: all inside)."""
    region = cal.region
    if region is None:
        return Coverage(len(pairs), (), (), "", "")
    d = region.outside_px(pairs.uv_px)
    out_uv = d > region.margin_px
    out_z = np.zeros(len(pairs), bool)
    height_words = ""
    if cal.model.height_rule is not HeightRule.COMPUTED:
        dz = region.z_outside_mm(pairs.xyz_mm[:, 2], pairs.xyz_mm[:, :2])
        out_z = dz > 0
        if out_z.any():
            if region.plane_z_mm is not None:
                plane = f"z = {region.plane_z_mm:g} mm" + (
                    "" if region.plane_slope is None else " at x = y = 0, tilted"
                )
                height_words = (
                    f"off the calibration plane {plane} by up to {dz.max():.3g} mm, "
                    f"tolerance {PLANE_TOLERANCE_MM:g} mm"
                )
            else:
                lo, hi = region.z_range_mm or (np.nan, np.nan)
                height_words = (
                    f"calibrated {lo:g}..{hi:g} mm, margin {region.z_margin_mm:g} mm; the farthest "
                    f"{dz.max():.3g} mm beyond"
                )
    region_words = ""
    if out_uv.any():
        far, margin = d.max(), region.margin_px
        region_words = f"the farthest {far:.0f} px beyond the training points' hull, margin {margin:.1f} px"
    ids = np.asarray(pairs.ids, dtype=object)
    return Coverage(len(pairs), tuple(ids[out_uv]), tuple(ids[out_z]), region_words, height_words)


def guard(
    pairs: PointPairs, cov: Coverage, *, allow_outside: bool, found: Mixup | None, how: str
) -> str | None:
    """Refuse (:class:`InputError`, the source, the counts, the mix-up when one explains it) pairs
    outside the calibrated region or heights; with ``allow_outside``, the warning saying so instead.
    ``how``: what the caller offers to go on (``"allow_outside evaluates them anyway"``)."""
    if not cov.n_outside:
        return None
    said = cov.describe()
    if allow_outside:
        return f"{pairs.source}: {said}: evaluated anyway (allow_outside), their errors are extrapolation"
    why = f"; {found.reason}" if found is not None else ""
    raise InputError(
        f"{pairs.source}: {said}: the calibration maps no point there{why}; leave them out"
        + (f", or {how}" if how else "")
    )


@dataclass(frozen=True)
class Evaluation:
    """A calibration's errors on pairs (:class:`Stats`) and what was found about the pairs."""

    stats: Stats
    coverage: Coverage
    mixup: Mixup | None
    warnings: tuple[str, ...]

    def to_dict(self) -> dict:
        """The statistics' own keys (as ``calibrate``'s check) and ``warnings``."""
        return {**self.stats.to_dict(), "warnings": list(self.warnings)}


def evaluate_pairs(cal: Calibration, pairs: PointPairs, *, allow_outside: bool = False) -> Evaluation:
    """Statistics of ``cal`` on ``pairs`` (each at its own z), guarded as :meth:`Calibration.map` is
    (module docstring): pairs outside the calibrated region or heights refused unless
    ``allow_outside``; a mixed-up convention named."""
    found = mixup(cal, pairs)
    cov = coverage(cal, pairs)
    outside = guard(pairs, cov, allow_outside=allow_outside, found=found, how=ALLOW_OUTSIDE_WORDS)
    pairs = as_fitted(cal, pairs)  # a circle target's centres corrected as the fit's were
    stats = stats_from_residuals(mapped_residuals(cal.model, pairs), pairs.ids)
    warnings = tuple(w for w in (outside, found.describe() if found else None) if w)
    return Evaluation(stats, cov, found, warnings)


def check_warnings(cal: Calibration) -> list[str]:
    """The mixed-up convention of ``cal``'s check pairs (``calibrate``'s ``check``), as warning lines:
    for the fit's sanity warnings, so that ``calibrate --check`` names it on every interface."""
    if cal.check_pairs is None:
        return []
    found = mixup(cal, cal.check_pairs)
    return [] if found is None else [found.describe()]
