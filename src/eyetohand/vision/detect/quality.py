"""Judging what the search and the refinement found: the :class:`Detection` record, its score, and
the rules that refuse (a circle cut by the image border, an edge that is not a clean ellipse, no
circle, two or more equally good ones) with the reason given to the user."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from eyetohand.vision.detect.search import MIN_CONTRAST_SIGMA, _Cand

DIAMETER_WINDOW = (0.7, 1.4)  # an expected diameter keeps circles within these multiples of it
AMBIGUOUS_RATIO = 0.8  # a runner-up scoring this fraction of the best makes the choice ambiguous
MAX_RMS_REL = 0.02  # edge points' rms distance from the ellipse, as a fraction of its mean radius
MIN_VALID_RAYS = 0.85  # share of the profiles that must lie inside the image, and fit the ellipse


class Miss(enum.Enum):
    """Why a search found no target (:attr:`Detection.miss`), for a caller that acts on the kind (the
    collection's refusal codes): the words stay in :attr:`Detection.reason`."""

    NOT_FOUND = "not found"  # no candidate, none round, none clean, no contrast
    CUT_BY_BORDER = "cut by the image border"  # the only circle-like region leaves the image
    AMBIGUOUS = "ambiguous"  # more than one equally good circle


@dataclass(frozen=True)
class Detection:
    """The result of a search. Positions in px, OpenCV convention (pixel centres at integers).

    ``ok`` False: ``u``, ``v`` and ``diameter_px`` are None and ``reason`` says why. ``ellipse`` is
    ((cx, cy), (major, minor) full axis lengths, angle in degrees of the major axis from +u).
    ``score`` (0..1): the fraction of profiles that showed the edge × a factor for the edge points'
    scatter about the ellipse (1 / (1 + (rms / 0.25 px)²)) × min(1, contrast / (20 noise σ)).
    """

    ok: bool
    u: float | None = None
    v: float | None = None
    diameter_px: float | None = None
    ellipse: tuple[tuple[float, float], tuple[float, float], float] | None = None
    score: float = 0.0
    reason: str = ""
    polarity: str | None = None  # "dark" (dark circle on bright) or "bright"
    rms_px: float | None = None  # edge points' rms distance from the fitted ellipse
    n_edge_points: int = 0
    contrast: float | None = None  # grey levels of the input (e.g. 0..255), circle vs surround
    blur_px: float | None = None  # σ (px) of the edge's spread in the intensity fit (blur + pixel)
    method: str | None = None  # "intensity" (model fit, the default) or "edge" (its fallback)
    miss: Miss | None = None  # why not found (``ok`` False), else None; not in :meth:`to_dict`

    def to_dict(self) -> dict:
        return {
            "ok": self.ok,
            "u": self.u,
            "v": self.v,
            "diameter_px": self.diameter_px,
            "ellipse": None
            if self.ellipse is None
            else {
                "centre": list(self.ellipse[0]),
                "axes": list(self.ellipse[1]),
                "angle_deg": self.ellipse[2],
            },
            "score": self.score,
            "reason": self.reason,
            "polarity": self.polarity,
            "rms_px": self.rms_px,
            "n_edge_points": self.n_edge_points,
            "contrast": self.contrast,
            "blur_px": self.blur_px,
            "method": self.method,
        }


# ------------------------------------------------------------------ one candidate's edge


def _cut_by_border(cand: _Cand, inside: np.ndarray) -> Detection | None:
    """The refusal of a candidate whose profiles (``inside`` (n,) bool: those within the image) leave
    the image too often, else None."""
    if inside.mean() < MIN_VALID_RAYS:
        return Detection(
            False,
            reason=f"the circle at ({cand.x:.1f}, {cand.y:.1f}) px is cut by the image border",
            polarity=cand.polarity,
            miss=Miss.CUT_BY_BORDER,
        )
    return None


def _too_few_edges(cand: _Cand, valid: np.ndarray) -> str:
    """Why a candidate's edge points cannot be fitted (``valid`` (n,) bool: the profiles that showed
    the edge), or "" when they can."""
    if valid.mean() < 0.5:
        return (
            f"the edge of the candidate at ({cand.x:.1f}, {cand.y:.1f}) px was found on only "
            f"{100 * valid.mean():.0f} % of its profiles"
        )
    return ""


def _not_clean(centre, frac: float, rms: float, mean_r: float, polarity: str) -> Detection | None:
    """The refusal of an edge-point ellipse (centre px, mean radius ``mean_r`` px) that fits too few
    of the profiles (``frac``) or lies too far from its edge points (``rms`` px), else None."""
    if frac < MIN_VALID_RAYS:
        return Detection(
            False,
            reason=f"the candidate at ({centre[0]:.1f}, {centre[1]:.1f}) px is not a "
            f"clean ellipse: its edge fits on only {100 * frac:.0f} % of the profiles",
            polarity=polarity,
        )
    if rms > MAX_RMS_REL * mean_r:
        return Detection(
            False,
            reason=f"the candidate at ({centre[0]:.1f}, {centre[1]:.1f}) px is not a "
            f"circle: its edge lies {rms:.2f} px rms from the best ellipse",
            polarity=polarity,
        )
    return None


def _score(frac: float, rms: float, contrast: float, sigma: float) -> float:
    """:attr:`Detection.score` before clipping to 0..1: the share of usable profiles × a factor for
    the edge points' scatter × the contrast in 20 noise σ (at most 1)."""
    return frac / (1 + (rms / 0.25) ** 2) * min(1.0, contrast / (20 * max(sigma, 1e-12)))


# ------------------------------------------------------------------ the image's circles


def _distinct(found) -> list[Detection]:
    """``found`` best first, without the same circle reached from two candidates (a weaker one
    centred within a quarter diameter of a better one of the same polarity)."""
    unique: list[Detection] = []
    for d in sorted(found, key=lambda d: -d.score):
        if not any(
            math.hypot(d.u - e.u, d.v - e.v) < 0.25 * min(d.diameter_px, e.diameter_px)
            and e.polarity == d.polarity
            for e in unique
        ):
            unique.append(d)
    return unique


def _why_none(img, sigma, failed, rejected) -> Detection:
    """The refusal of a search that found nothing: its words and its kind."""
    if float(img.max() - img.min()) <= MIN_CONTRAST_SIGMA * max(sigma, 1e-12):
        why = "the image has no contrast above its noise (blank or noise only)"
        return Detection(False, reason=f"no target found: {why}", miss=Miss.NOT_FOUND)
    cut = [c for c in rejected if c.cut]
    if cut:
        c = max(cut, key=lambda c: c.diameter)
        why = f"the only circle-like region, at ({c.x:.0f}, {c.y:.0f}) px, is cut by the image border"
        return Detection(False, reason=f"no target found: {why}", miss=Miss.CUT_BY_BORDER)
    for d in failed:
        return Detection(False, reason=f"no target found: {d.reason}", miss=d.miss or Miss.NOT_FOUND)
    if rejected:
        c = min(rejected, key=lambda c: c.roundness)
        why = (
            f"the best region, at ({c.x:.0f}, {c.y:.0f}) px, is not round "
            f"(boundary radius spread {100 * c.roundness:.0f} %)"
        )
        return Detection(False, reason=f"no target found: {why}", miss=Miss.NOT_FOUND)
    return Detection(
        False, reason="no target found: no solid circle stands out from the background", miss=Miss.NOT_FOUND
    )


def _one_of(found, diameter_px: float | None) -> Detection:
    """The best of the circles ``found`` (at least one), or the refusal when a runner-up scores
    within ``AMBIGUOUS_RATIO`` of it, with a hint at what can choose (``diameter_px`` the expected
    diameter given, if any)."""
    found = sorted(found, key=lambda d: -d.score)
    best = found[0]
    rivals = [d for d in found[1:] if d.score >= AMBIGUOUS_RATIO * best.score]
    if rivals:
        where = ", ".join(f"({d.u:.0f}, {d.v:.0f}) d {d.diameter_px:.0f}" for d in [best, *rivals[:3]])
        sizes = [d.diameter_px for d in [best, *rivals]]
        if diameter_px is None and max(sizes) > DIAMETER_WINDOW[1] / DIAMETER_WINDOW[0] * min(sizes):
            hint = "; give the expected diameter to choose"
        else:  # of one size: no diameter can choose, only the place can
            hint = (
                "; crop or mask the image to one target, or give its region "
                "(roi=(x, y, w, h), detect --roi X Y W H)"
            )
        return Detection(
            False,
            reason=f"ambiguous: {1 + len(rivals)} equally good circles at {where} px{hint}",
            score=best.score,
            miss=Miss.AMBIGUOUS,
        )
    return best
