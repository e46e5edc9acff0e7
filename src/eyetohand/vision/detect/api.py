"""The detection's entry points: :func:`detect_target` (the one circle, or why not),
:func:`detect_circles` (every circle) and :func:`annotate` (the result drawn on the image); the search
at its scale (and again at full scale for a circle too small for it), every candidate refined, the
options checked."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from eyetohand.core import InputError
from eyetohand.vision.detect.quality import DIAMETER_WINDOW, Detection, _distinct, _one_of, _why_none
from eyetohand.vision.detect.read import MIN_SIZE_PX, load_image, noise_sigma
from eyetohand.vision.detect.refine import _refine
from eyetohand.vision.detect.search import _Cand, _candidates, _search_scale


def _check_options(polarity, diameter_px, roi, shape, name):
    if polarity not in ("auto", "dark", "bright"):
        raise InputError(f"polarity: expected auto, dark or bright, got {polarity!r}")
    if diameter_px is not None and not (np.isfinite(diameter_px) and diameter_px > 0):
        raise InputError(f"diameter_px: expected a positive number of px, got {diameter_px!r}")
    H, W = shape
    if diameter_px is not None and diameter_px > max(W, H):
        raise InputError(f"{name}: diameter_px {diameter_px:g} px is larger than the {W}x{H} image")
    if roi is None:
        return 0, 0
    try:
        x, y, w, h = (int(v) for v in roi)
    except (TypeError, ValueError):
        raise InputError(f"roi: expected (x, y, w, h) in px, got {roi!r}") from None
    if w < MIN_SIZE_PX or h < MIN_SIZE_PX or x < 0 or y < 0 or x + w > W or y + h > H:
        raise InputError(
            f"{name}: roi {roi!r} is not inside the {W}x{H} image (or smaller than {MIN_SIZE_PX} px)"
        )
    return x, y


def _search(image, polarity, diameter_px, roi, name=None, refine="intensity"):
    img, name, full = load_image(image, name)
    x0, y0 = _check_options(polarity, diameter_px, roi, img.shape, name)
    if refine not in ("intensity", "edge"):
        raise InputError(f"refine: expected intensity or edge, got {refine!r}")
    if roi is not None:
        img = img[y0 : y0 + int(roi[3]), x0 : x0 + int(roi[2])]
    sigma = noise_sigma(img)
    f = _search_scale(img.shape, diameter_px)
    found, failed, rejected = _found(img, sigma, polarity, diameter_px, f, full, refine, False)
    if not found and f > 1 and diameter_px is None:  # a circle too small for the downscaled search?
        found, failed, rejected = _found(img, sigma, polarity, diameter_px, 1, full, refine, False)
    found = _distinct(found)  # the same circle reached from two candidates counts once
    if roi is not None:
        found = [_shifted(d, x0, y0) for d in found]
        rejected = [
            _Cand(c.x + x0, c.y + y0, c.cov, c.diameter, c.polarity, c.contrast, c.levels, c.roundness, c.cut)
            for c in rejected
        ]
    return img, sigma, found, failed, rejected


def _found(img, sigma, polarity, diameter_px, f, full, refine, everywhere):
    """Refined candidates of the search at 1/``f`` scale: (found, failed, rejected). When the search
    in windows finds nothing it is repeated everywhere, so that every refusal is the whole image's."""
    cands, rejected, everywhere = _candidates(img, sigma, polarity, diameter_px, f, everywhere)
    found: list[Detection] = []
    failed: list[Detection] = []
    lo, hi = DIAMETER_WINDOW
    for c in cands:
        d = _refine(img, c, sigma, full, refine)
        if d.ok and diameter_px is not None and not (lo < d.diameter_px / diameter_px < hi):
            continue
        (found if d.ok else failed).append(d)
    if not found and not everywhere:
        return _found(img, sigma, polarity, diameter_px, f, full, refine, True)
    return found, failed, rejected


def _shifted(d: Detection, dx: float, dy: float) -> Detection:
    assert d.ellipse is not None and d.u is not None and d.v is not None  # a found target's
    (cx, cy), axes, ang = d.ellipse
    return replace(d, u=d.u + dx, v=d.v + dy, ellipse=((cx + dx, cy + dy), axes, ang))


def detect_target(
    image,
    *,
    polarity: str = "auto",
    diameter_px: float | None = None,
    roi=None,
    name: str | None = None,
    refine: str = "intensity",
) -> Detection:
    """The one solid circle of ``image`` (path or array): see :class:`Detection` and the package docstring.

    ``polarity``: "dark" circle on bright, "bright" on dark, or "auto". ``diameter_px``: expected
    diameter (keeps circles within 0.7–1.4× of it). ``roi``: (x, y, w, h) px to search in.
    ``refine``: "intensity" (edge points, then the intensity-model fit; the default) or "edge" (stop
    at the edge points' ellipse: the ablation). Raises :class:`InputError` when the file cannot be
    read as an image."""
    img, sigma, found, failed, rejected = _search(image, polarity, diameter_px, roi, name, refine)
    if not found:
        return _why_none(img, sigma, failed, rejected)
    return _one_of(found, diameter_px)


def detect_circles(
    image,
    *,
    polarity: str = "auto",
    diameter_px: float | None = None,
    roi=None,
    name: str | None = None,
    refine: str = "intensity",
) -> list[Detection]:
    """Every solid circle of ``image`` (only those found, ``ok`` True), sorted by v then u; options
    as :func:`detect_target`."""
    _, _, found, _, _ = _search(image, polarity, diameter_px, roi, name, refine)
    return sorted(found, key=lambda d: (round(d.v), d.u))


def annotate(image, detection: Detection | list[Detection]) -> np.ndarray:
    """A BGR uint8 copy of ``image`` with the fitted ellipse (green), a cross at the centre (red) and
    its centre (px) and score written beside it (yellow); a failed detection is written on the image
    instead."""
    import cv2

    grey, _, full = load_image(image)
    g8 = np.clip(grey * (255.0 / full) if full != 1.0 else grey * 255.0, 0, 255).astype(np.uint8)
    out = cv2.cvtColor(g8, cv2.COLOR_GRAY2BGR)
    dets = detection if isinstance(detection, list) else [detection]
    S = 16  # sub-pixel drawing: coordinates × 16
    for d in dets:
        if not d.ok:
            cv2.putText(
                out,
                (d.reason or "not found")[:80],
                (10, 30),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.7,
                (0, 0, 255),
                2,
                cv2.LINE_AA,
            )
            continue
        assert d.ellipse is not None  # found: it has its ellipse
        (cx, cy), (A, B), ang = d.ellipse
        c = (int(round(cx * S)), int(round(cy * S)))
        cv2.ellipse(
            out,
            c,
            (int(round(A / 2 * S)), int(round(B / 2 * S))),
            ang,
            0,
            360,
            (0, 255, 0),
            1,
            cv2.LINE_AA,
            4,
        )
        arm = int(max(4, 0.15 * A) * S)
        cv2.line(out, (c[0] - arm, c[1]), (c[0] + arm, c[1]), (0, 0, 255), 1, cv2.LINE_AA, 4)
        cv2.line(out, (c[0], c[1] - arm), (c[0], c[1] + arm), (0, 0, 255), 1, cv2.LINE_AA, 4)
        # the numbers beside the target, kept inside the picture: centre (px) and score
        h, w = out.shape[:2]
        label = f"u {d.u:.2f} v {d.v:.2f} px  score {d.score:.3f}"
        scale = 0.45 if w < 900 else 0.7
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        x = int(min(max(cx + 0.6 * A, 2), max(w - tw - 2, 2)))
        y = int(min(max(cy - 0.6 * B, th + 4), h - 4))
        cv2.putText(out, label, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, label, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 255, 255), 1, cv2.LINE_AA)
    return out
