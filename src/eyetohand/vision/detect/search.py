"""Stage 1 of the detection: candidate circles on a downscaled copy of the image (see the package
docstring): the regions of the image cut at up to 20 grey levels that are big enough, fill their
bounding box like an ellipse, are solid, round and contrasted, found at two or more levels in the
same place; only windows around what a looser search on a copy downscaled 2× more finds are labelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

N_LEVELS = 10  # grey levels of the candidate search, twice: over the full range and the bulk
MIN_COARSE_DIAMETER = 10.0  # px at the search scale
MIN_CONTRAST_SIGMA = 6.0  # a candidate's contrast against its ring, in noise σ
RING_UNIFORMITY = 1.0  # contrast against the ring around a region must exceed this × the ring's IQR


@dataclass
class _Cand:
    x: float  # full-resolution px
    y: float
    cov: np.ndarray  # 2x2 second moments (full-resolution px²)
    diameter: float
    polarity: str
    contrast: float
    levels: int = 1
    roundness: float = 0.0  # relative spread of the whitened boundary radius
    cut: bool = False


def _search_scale(shape, diameter_px) -> int:
    h, w = shape
    if diameter_px is not None:
        return int(np.clip(diameter_px // 16, 1, 8))
    return int(np.clip(min(h, w) // 480, 1, 4))


def _regions(mask: np.ndarray, min_d: float, shape=None, offset=(0, 0)):
    """Labels and the cheap statistics of the regions of ``mask`` that could be an ellipse:
    ((labels, x, y of their window), rows (k, 6): label, x0, y0, w, h, area; centroids (k, 2)).
    ``mask`` may be a window at ``offset`` (x, y) of an image of ``shape``: rows and centroids are
    then in the image's coordinates, and regions touching a side of the window inside the image are
    dropped (they may continue beyond it)."""
    import cv2

    h, w = mask.shape
    H, W = mask.shape if shape is None else shape
    mask = mask.view(np.uint8)
    # label only the bounding box of the mask's pixels: at the extreme levels a small part of the image
    bx, by, bw_, bh_ = cv2.boundingRect(mask)
    if bw_ == 0 or bh_ == 0:
        return (None, 0, 0), np.zeros((0, 6), np.int64), np.zeros((0, 2))
    n, lab, stats, cents = cv2.connectedComponentsWithStats(
        mask[by : by + bh_, bx : bx + bw_], connectivity=8
    )
    stats[:, 0] += bx
    stats[:, 1] += by
    x, y, bw, bh, area = (stats[1:, i] for i in range(5))
    ox, oy = offset
    fill = area / (bw * bh)
    # an ellipse of axis ratio >= 0.4 fills 0.6–0.8 of its bounding box (a square 0.5 or 1)
    keep = (area >= math.pi / 4 * min_d**2) & (fill > 0.6) & (fill < 0.9) & (bw < 0.9 * W) & (bh < 0.9 * H)
    keep &= np.maximum(bw, bh) < 2.5 * np.minimum(bw, bh)
    if (h, w) != (H, W):
        keep &= ((x > 0) | (ox == 0)) & ((y > 0) | (oy == 0))
        keep &= ((x + bw < w) | (ox + w == W)) & ((y + bh < h) | (oy + h == H))
    idx = np.nonzero(keep)[0]
    rows = np.column_stack([idx + 1, x[idx] + ox, y[idx] + oy, bw[idx], bh[idx], area[idx]])
    return (lab, ox + bx, oy + by), rows, cents[idx + 1] + [ox + bx, oy + by]


def _examine(coarse, lab, row, f: int, polarity: str, uniformity: float = RING_UNIFORMITY) -> _Cand | None:
    """Shape and contrast of one region (``row`` from :func:`_regions`, ``lab`` (labels, x, y) the
    labels of its window at x, y); None when it has a hole."""
    import cv2

    H, W = coarse.shape
    lab, ox, oy = lab
    i, x0, y0, bw, bh, area = (int(v) for v in row)
    x1, y1 = x0 + bw, y0 + bh
    cut = x0 == 0 or y0 == 0 or x1 == W or y1 == H
    m = (lab[y0 - oy : y1 - oy, x0 - ox : x1 - ox] == i).astype(np.uint8)
    contours, _ = cv2.findContours(np.pad(m, 1), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if len(contours) != 1:  # a hole: not a solid circle
        return None
    mo = cv2.moments(m, binaryImage=True)
    cx, cy = mo["m10"] / mo["m00"], mo["m01"] / mo["m00"]
    cov = np.array([[mo["mu20"], mo["mu11"]], [mo["mu11"], mo["mu02"]]]) / mo["m00"]
    ev, evec = np.linalg.eigh(cov)
    if ev[0] <= 0:
        return None
    pts = contours[0].reshape(-1, 2) - 1 - np.array([cx, cy])
    wpts = (pts @ evec) / np.sqrt(ev)
    r = np.hypot(wpts[:, 0], wpts[:, 1])
    roundness = float(r.std() / r.mean())
    rad = math.sqrt(area / math.pi)
    # contrast: the region's mean against a ring 1.3–1.7 radii out
    R = int(math.ceil(1.7 * rad)) + 1
    icx, icy = int(round(x0 + cx)), int(round(y0 + cy))
    ys, xs = slice(max(icy - R, 0), min(icy + R + 1, H)), slice(max(icx - R, 0), min(icx + R + 1, W))
    yy, xx = np.ogrid[ys, xs]
    dd = (xx - (x0 + cx)) ** 2 + (yy - (y0 + cy)) ** 2
    ring = coarse[ys, xs][(dd >= (1.3 * rad) ** 2) & (dd <= (1.7 * rad) ** 2)]
    if ring.size < 8:
        return None
    q25, q50, q75 = np.percentile(ring, [25, 50, 75])
    contrast = float(q50 - coarse[y0:y1, x0:x1][m.astype(bool)].mean())
    if polarity == "bright":
        contrast = -contrast
    if contrast < uniformity * (q75 - q25):  # the surround is not one background (a gap between dots)
        return None
    return _Cand(
        (x0 + cx + 0.5) * f - 0.5,
        (y0 + cy + 0.5) * f - 0.5,
        cov * f * f,
        2 * rad * f,
        polarity,
        contrast,
        roundness=roundness,
        cut=cut,
    )


def _candidates(img, sigma, polarity, diameter_px, f: int, everywhere: bool = False):
    """Candidates (round, solid, contrasted, found at >= 2 levels) and rejected regions (cut by the
    border or not round), at full-resolution coordinates; searched at 1/``f`` scale. Unless
    ``everywhere``, only in windows around what a looser search at 1/(2 ``f``) scale finds (see
    :func:`_windows`); also returns whether the search covered the whole image."""
    import cv2

    if f > 1:
        h, w = img.shape
        coarse = cv2.resize(img[: h - h % f, : w - w % f], (w // f, h // f), interpolation=cv2.INTER_AREA)
    else:
        coarse = cv2.GaussianBlur(img, (0, 0), 0.8)
    lo, hi = float(coarse.min()), float(coarse.max())
    if hi - lo < MIN_CONTRAST_SIGMA * sigma or hi - lo <= 0:
        return [], [], True
    # levels spread over the full range (a small target's extreme grey) and over the bulk of the pixels
    p_lo, p_hi = np.percentile(coarse[::2, ::2], [0.5, 99.5])
    steps = (np.arange(N_LEVELS) + 0.5) / N_LEVELS
    levels = np.sort(np.concatenate([lo + (hi - lo) * steps, p_lo + (p_hi - p_lo) * steps]))
    gap = 0.5 * (hi - lo) / N_LEVELS  # levels closer than half a full-range step add nothing
    keep = np.ones(len(levels), bool)
    last = -np.inf
    for i, t in enumerate(levels):
        keep[i] = t - last >= gap
        last = t if keep[i] else last
    levels = levels[keep]
    min_d = MIN_COARSE_DIAMETER if diameter_px is None else max(6.0, 0.5 * diameter_px / f)
    pols = [p for p in ("dark", "bright") if polarity in ("auto", p)]
    windows = None if everywhere else _windows(coarse, levels, pols, min_d, sigma, f)
    if not windows:  # nothing at the coarser scale (or too small an image): search everywhere
        windows, everywhere = [(0, 0, coarse.shape[1], coarse.shape[0])], True
    cands, rejected = _grouped(coarse, windows, levels, pols, min_d, sigma, f)
    return cands, rejected, everywhere


def _windows(coarse, levels, pols, min_d: float, sigma: float, f: int):
    """Where the search at ``coarse``'s scale can find something: windows (x0, y0, x1, y1) of
    ``coarse`` around every candidate and rejected region of the same search on a copy downscaled 2×
    more, with looser bounds (half the diameter less a pixel, half the contrast and ring
    uniformity) at every other level (a circle spans many levels; half the labellings, the same
    windows on every render measured); overlapping windows merged. Labelling a few windows instead of
    the whole image at every level is what makes the search fast (the coarser copy has a quarter of
    the pixels). None when the image is too small for this to pay."""
    import cv2

    H, W = coarse.shape
    if min(H, W) < 192 or min_d < 8:
        return None
    loc = cv2.resize(coarse[: H - H % 2, : W - W % 2], (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    cands, rejected = _grouped(
        loc, [(0, 0, W // 2, H // 2)], levels[::2], pols, 0.5 * min_d - 1, sigma, 2 * f, loose=True
    )
    boxes = []
    for c in cands + rejected:
        x, y = (c.x + 0.5) / f - 0.5, (c.y + 0.5) / f - 0.5  # coarse px
        r = 0.5 * c.diameter / f * 1.3 + 4  # room for the region's growth at the finer levels
        boxes.append(
            np.array(
                [
                    max(int(x - r), 0),
                    max(int(y - r), 0),
                    min(int(math.ceil(x + r)) + 1, W),
                    min(int(math.ceil(y + r)) + 1, H),
                ]
            )
        )
    merged: list[np.ndarray] = []
    for box in boxes:
        grown = True
        while grown:
            grown = False
            for i, o in enumerate(merged):
                if box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3]:
                    box = np.concatenate([np.minimum(box[:2], o[:2]), np.maximum(box[2:], o[2:])])
                    merged.pop(i)
                    grown = True
                    break
        merged.append(box)
    return [tuple(int(v) for v in o) for o in merged]


def _grouped(coarse, windows, levels, pols, min_d: float, sigma: float, f: int, loose: bool = False):
    """The regions of ``coarse`` (in ``windows``) at every level, grouped across levels and examined:
    (candidates, rejected) at full-resolution coordinates. ``loose``: half the contrast and ring
    uniformity (the coarser search of :func:`_windows`)."""
    labels: list[np.ndarray] = []
    label_pol: list[str] = []
    row_parts: list[np.ndarray] = []
    cent_parts: list[np.ndarray] = []
    key_parts: list[np.ndarray] = []
    for x0, y0, x1, y1 in windows:
        win = coarse[y0:y1, x0:x1]
        for t in levels:
            for pol in pols:
                lab, r, c = _regions(win < t if pol == "dark" else win > t, min_d, coarse.shape, (x0, y0))
                if len(r):
                    labels.append(lab)
                    label_pol.append(pol)
                    row_parts.append(r)
                    cent_parts.append(c)
                    key_parts.append(np.full(len(r), len(labels) - 1))
    if not row_parts:
        return [], []
    rows, cents, keys = np.vstack(row_parts), np.vstack(cent_parts), np.concatenate(key_parts)
    pol_of = np.array(label_pol)[keys]
    diam = 2 * np.sqrt(rows[:, 5] / math.pi)
    # group the same region seen at several levels: smallest first (a region's core at its extreme
    # level), larger ones join the nearest core they are centred on — a blob that merged two regions
    # at a mid level is centred on neither and stays alone
    order = np.argsort(diam, kind="stable")
    n = len(order)
    gx, gy, gd = np.empty(n), np.empty(n), np.empty(n)  # the groups' cores: centre and diameter
    gp = np.empty(n, dtype=pol_of.dtype)
    members: list[list[int]] = []
    for j in order:
        k = len(members)
        if k:
            dist = np.hypot(gx[:k] - cents[j, 0], gy[:k] - cents[j, 1])
            near = (dist < 0.25 * gd[:k]) & (diam[j] / gd[:k] < 1.6) & (gp[:k] == pol_of[j])
            if near.any():
                members[int(np.argmin(np.where(near, dist, np.inf)))].append(j)
                continue
        gx[k], gy[k], gd[k], gp[k] = cents[j, 0], cents[j, 1], diam[j], pol_of[j]
        members.append([j])
    cands: list[_Cand] = []
    rejected: list[_Cand] = []
    for mem in members:
        if len(mem) < 2:
            continue
        mem = sorted(mem, key=lambda j: keys[j])
        j = mem[len(mem) // 2]  # the middle level
        c = _examine(coarse, labels[keys[j]], rows[j], f, pol_of[j], RING_UNIFORMITY * (0.5 if loose else 1))
        if c is None or c.contrast < MIN_CONTRAST_SIGMA * sigma * (0.5 if loose else 1):
            continue
        c.levels = len(mem)
        (rejected if c.cut or c.roundness > 0.12 else cands).append(c)
    return cands, rejected
