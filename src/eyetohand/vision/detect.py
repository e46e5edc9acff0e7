"""Find the target's solid circle in an image, with sub-pixel accuracy.

Three stages:

1. **Candidates** on a downscaled copy (area averaging, so a 2448×2048 image is searched at 612×512):
   the image is cut at up to 20 grey levels (10 spread between its darkest and brightest pixel, 10
   between its 0.5th and 99.5th percentiles); at each level the connected dark (and bright) regions
   are kept when they are big enough, fill their bounding box like an ellipse, have no hole (solid),
   keep off the image border, are round once their second moments are whitened, and stand out from
   the ring around them by at least 6 noise σ. A region found at two or more levels in the same place
   is a candidate. Uneven light only moves the levels at which a region appears, not whether it
   does. Only windows around what the same search with looser bounds (and every other level) finds
   on a copy downscaled 2× more are labelled (the whole image when that finds nothing, or when the
   windows give no circle).
2. **Edge points** at full resolution around each candidate: the image is sampled (bilinear) along
   one radial profile per boundary pixel, from inside to outside the candidate's ellipse; each
   profile's edge is the centroid of its gradient above a quarter of its peak (exact for a
   symmetrically blurred edge, whatever the blur). An ellipse is fitted to the edge points (normalised
   algebraic conic, then points farther than 3.5 robust σ from it dropped), and the profiles are cast
   again from the new centre. This ellipse decides whether the candidate is a circle (share of usable
   profiles, rms distance of the edge points).
3. **Intensity model** (``refine="intensity"``, the default): the pixels within a few px of that
   ellipse's edge are fitted with a blurred solid ellipse under smooth light,
   ``I = (1 + gx·x + gy·y) · (a_in + (a_out(φ) − a_in) · Φ(d / s))`` — ``d`` the signed distance from
   the ellipse, ``Φ`` the normal CDF, ``s`` the edge spread (blur and pixel), ``a_out(φ)`` the outer
   level with 4 angular harmonics — by robust (soft-L1) least squares over the 18 parameters
   (Levenberg–Marquardt on the 18 × 18 normal equations, analytic Jacobian). It uses every pixel of
   the edge band at its own noise (the edge points average differentiated, interpolated samples),
   which halves the error on the benchmark's renders; a fit that fails or moves more than 0.5 px from
   the edge points' ellipse is dropped and that ellipse kept (``Detection.method`` says which). The
   centre reported is the fitted ellipse's: the centre of the *imaged ellipse*, not the image of the
   circle's centre — they differ by the perspective bias of a tilted view (see
   :mod:`eyetohand.vision.render`).

Everything is vectorised over profiles and samples. ``detect_target`` wants exactly one circle; it
refuses (``ok=False`` with a ``reason``, never a guessed centre) when there is none, when two or more
candidates are equally good, or when the circle is cut by the image border. ``detect_circles`` returns
every circle (dot grids). Files that cannot be read as images raise
:class:`~eyetohand.core.errors.InputError`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from eyetohand.core import InputError

MIN_SIZE_PX = 8  # an image smaller than this in either direction is refused
N_LEVELS = 10  # grey levels of the candidate search, twice: over the full range and the bulk
MIN_COARSE_DIAMETER = 10.0  # px at the search scale
MIN_CONTRAST_SIGMA = 6.0  # a candidate's contrast against its ring, in noise σ
DIAMETER_WINDOW = (0.7, 1.4)  # an expected diameter keeps circles within these multiples of it
AMBIGUOUS_RATIO = 0.8  # a runner-up scoring this fraction of the best makes the choice ambiguous
MAX_RMS_REL = 0.02  # edge points' rms distance from the ellipse, as a fraction of its mean radius
MIN_VALID_RAYS = 0.85
RING_UNIFORMITY = 1.0  # contrast against the ring around a region must exceed this × the ring's IQR


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


# ------------------------------------------------------------------ reading


def check_complete(data: bytes, name: str) -> None:
    """Refuse truncated PNG and JPEG files before the decoder prints its own complaints."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        if b"IEND" not in data[-32:]:
            raise InputError(f"{name}: truncated PNG file (no IEND chunk at the end)")
    elif data.startswith(b"\xff\xd8"):
        if b"\xff\xd9" not in data[-1024:]:
            raise InputError(f"{name}: truncated JPEG file (no end-of-image marker)")


def load_image(image, name: str | None = None) -> tuple[np.ndarray, str, float]:
    """``image`` (path, or array: grey (h, w) or colour (h, w, 3|4) BGR, any numeric dtype) as a grey
    float32 array, with a name for messages and the full-scale value of the input (255, 65535 or 1)."""
    import cv2

    if isinstance(image, (str, os.PathLike)):
        path = Path(image)
        name = name or str(path)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise InputError(f"{name}: no such file") from None
        except IsADirectoryError:
            raise InputError(f"{name}: is a folder, not an image") from None
        except OSError as exc:
            raise InputError(f"{name}: cannot read ({exc.strerror or exc})") from None
        if not data:
            raise InputError(f"{name}: empty file, not an image")
        check_complete(data, name)
        arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if arr is None:
            raise InputError(f"{name}: not an image (PNG, JPEG, BMP or TIFF) or a damaged one")
    else:
        name = name or "<array>"
        arr = np.asarray(image)
        if arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
            raise InputError(f"{name}: expected a numeric image array, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
        raise InputError(f"{name}: expected a grey or colour image, got an array of shape {arr.shape}")
    h, w = arr.shape[:2]
    if h < MIN_SIZE_PX or w < MIN_SIZE_PX:
        raise InputError(
            f"{name}: the image is {w}x{h} px, too small to hold a target "
            f"(at least {MIN_SIZE_PX}x{MIN_SIZE_PX})"
        )
    if arr.dtype == np.uint8:
        full = 255.0
    elif arr.dtype == np.uint16:
        full = 65535.0
    else:
        full = 1.0
    grey: np.ndarray = arr.astype(np.float32, copy=False)
    if grey.ndim == 3:
        grey = cv2.cvtColor(grey, cv2.COLOR_BGRA2GRAY if grey.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if not np.issubdtype(arr.dtype, np.integer) and not np.isfinite(grey).all():
        raise InputError(f"{name}: the image holds NaN or infinite values")
    return np.ascontiguousarray(grey), name, full


def noise_sigma(img: np.ndarray) -> float:
    """Robust σ of the pixel noise (grey levels): the MAD of horizontal neighbour differences / √2,
    on every 16th row."""
    d = np.diff(img[:: max(1, min(16, img.shape[0] // 64))], axis=1).ravel()
    if d.size == 0:
        return 0.0
    lo = d.min()
    if 0 < d.max() - lo < 1 << 18 and np.array_equal(d, np.rint(d)):  # integer grey levels: by counting
        mad = d.dtype.type(_mad_by_counting(np.bincount((d - lo).astype(np.intp)), int(lo)))
    else:
        mad = np.median(np.abs(d - np.median(d)))
    if mad == 0:  # quantised flat image: fall back to the mean absolute difference
        mad = np.mean(np.abs(d)) / 1.2533 / 1.4826
    return float(1.4826 * mad / math.sqrt(2))


def _mad_by_counting(counts: np.ndarray, lo: int) -> float:
    """np.median(|x − np.median(x)|) of integer values x given as a histogram (``counts[i]`` values
    equal to ``lo + i``), by counting: one pass over the values (the histogram) instead of
    np.median's two partitions of the 300 000 differences of a 5 Mpx image (ties averaged as
    np.median does; the deviations from a half-integer median are truncated to integers)."""
    c = np.cumsum(counts)
    n = int(c[-1])
    ia, ib = np.searchsorted(c, [(n - 1) // 2, n // 2], side="right")
    med2 = (2 * (lo + int(ia)) + 2 * (lo + int(ib))) / 2  # 2 × the median
    x2 = 2 * (lo + np.arange(len(counts)))
    dev = np.abs(x2 - med2).astype(np.int64)  # 2 |x − median|, truncated
    c2 = np.cumsum(np.bincount(dev, weights=counts))
    a, b = np.searchsorted(c2, [(n - 1) // 2, n // 2], side="right")
    return (int(a) + int(b)) / 4


# ------------------------------------------------------------------ stage 1: candidates


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


# ------------------------------------------------------------------ stage 2: refinement


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    x0 = np.clip(x0, 0, img.shape[1] - 2)
    y0 = np.clip(y0, 0, img.shape[0] - 2)
    a = img[y0, x0]
    b = img[y0, x0 + 1]
    c = img[y0 + 1, x0]
    d = img[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def fit_ellipse(pts: np.ndarray):
    """Normalised algebraic conic fit to points (N, 2) px. Returns (centre (2,), axes (full lengths,
    major first), angle deg, conic coefficients in the normalised frame, mean, scale), or None when
    the best conic is not an ellipse."""
    m = pts.mean(axis=0)
    s = math.sqrt(((pts - m) ** 2).sum(axis=1).mean())
    if s == 0:
        return None
    x, y = ((pts - m) / s).T
    D = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, c, d, e, f0 = np.linalg.svd(D, full_matrices=False)[2][-1]
    if 4 * a * c - b * b <= 0:
        return None
    cx, cy = np.linalg.solve(np.array([[2 * a, b], [b, 2 * c]]), [-d, -e])
    k = f0 + 0.5 * (d * cx + e * cy)
    ev, evec = np.linalg.eigh(np.array([[a, b / 2], [b / 2, c]]))
    if np.any(-k / ev <= 0):
        return None
    semi = np.sqrt(-k / ev) * s  # semi-axes along evec[:, 0], evec[:, 1]
    j = int(np.argmax(semi))
    ang = math.degrees(math.atan2(evec[1, j], evec[0, j])) % 180.0
    return (
        m + s * np.array([cx, cy]),
        (2 * float(semi.max()), 2 * float(semi.min())),
        ang,
        np.array([a, b, c, d, e, f0]),
        m,
        s,
    )


def _ellipse_distance(fit, pts: np.ndarray) -> np.ndarray:
    """Sampson approximation of each point's distance (px) from a fitted conic."""
    a, b, c, d, e, f0 = fit[3]
    x, y = ((pts - fit[4]) / fit[5]).T
    F = a * x * x + b * x * y + c * y * y + d * x + e * y + f0
    gx, gy = 2 * a * x + b * y + d, b * x + 2 * c * y + e
    return F / np.maximum(np.hypot(gx, gy), 1e-300) * fit[5]


def _shape_matrix(centre_axes_angle) -> np.ndarray:
    """Q with xᵀQx = 1 on the ellipse boundary (x from the centre)."""
    (_, _), (A, B), ang = centre_axes_angle
    t = math.radians(ang)
    Rm = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    return Rm @ np.diag([4 / A**2, 4 / B**2]) @ Rm.T


def _edge_points(img, centre, Q, sign: float, half_window: float, step: float = 0.25):
    """Sub-pixel edge points along radial profiles: (points (n, 2), valid (n,) bool, peak gradients)."""
    h, w = img.shape
    rho_min = 1 / math.sqrt(np.linalg.eigvalsh(Q).max())
    n = int(np.clip(round(2 * math.pi / math.sqrt(np.linalg.eigvalsh(Q).min())), 64, 1440))
    phi = 2 * np.pi * np.arange(n) / n
    e = np.column_stack([np.cos(phi), np.sin(phi)])
    rho = 1 / np.sqrt(np.einsum("ni,ij,nj->n", e, Q, e))
    W = min(half_window, 0.7 * rho_min)
    s = np.arange(-W, W + step / 2, step)
    r = rho[:, None] + s[None, :]
    X = centre[0] + r * e[:, :1]
    Y = centre[1] + r * e[:, 1:]
    inside = (X.min(axis=1) >= 0) & (X.max(axis=1) <= w - 1) & (Y.min(axis=1) >= 0) & (Y.max(axis=1) <= h - 1)
    p = _bilinear(img, X, Y)
    g = sign * np.gradient(p, step, axis=1)
    k = np.argmax(g, axis=1)
    gmax = g[np.arange(n), k]
    above = g > 0.25 * gmax[:, None]
    seg = np.cumsum(~above, axis=1)
    mask = above & (seg == seg[np.arange(n), k][:, None])
    wgt = np.where(mask, g - 0.25 * gmax[:, None], 0.0)
    tot = wgt.sum(axis=1)
    s_edge = (wgt * s[None, :]).sum(axis=1) / np.where(tot > 0, tot, 1)
    # the edge must lie inside the window, away from its ends
    valid = inside & (gmax > 0) & (k > 1) & (k < len(s) - 2) & (np.abs(s_edge) < W - step)
    pts = centre + (rho + s_edge)[:, None] * e
    return pts, valid, gmax, inside


def _refine(img, cand: _Cand, sigma: float, full: float, refine: str = "intensity") -> Detection:
    """Sub-pixel ellipse of a candidate (see the module docstring)."""
    sign = 1.0 if cand.polarity == "dark" else -1.0
    ev, evec = np.linalg.eigh(cand.cov)
    axes = 4 * np.sqrt(np.maximum(ev, 1e-6))  # full axes of the moment-equivalent ellipse
    ang = math.degrees(math.atan2(evec[1, 1], evec[0, 1]))
    ell = ((cand.x, cand.y), (float(axes[1]), float(axes[0])), ang)
    centre = np.array([cand.x, cand.y])
    r0 = cand.diameter / 2
    windows = (max(4.0, 0.25 * r0), max(3.0, min(6.0, 0.2 * r0)), max(3.0, min(6.0, 0.2 * r0)))
    fit = None
    why = ""
    for W in windows:
        pts, valid, gmax, inside = _edge_points(img, centre, _shape_matrix(ell), sign, W)
        if inside.mean() < MIN_VALID_RAYS:
            return Detection(
                False,
                reason=f"the circle at ({cand.x:.1f}, {cand.y:.1f}) px is cut by the image border",
                polarity=cand.polarity,
            )
        if valid.mean() < 0.5:
            why = (
                f"the edge of the candidate at ({cand.x:.1f}, {cand.y:.1f}) px was found on only "
                f"{100 * valid.mean():.0f} % of its profiles"
            )
            fit = None
            break
        use = valid.copy()
        for _ in range(3):
            fit = fit_ellipse(pts[use])
            if fit is None:
                break
            dist = np.abs(_ellipse_distance(fit, pts))
            sd = 1.4826 * np.median(dist[use]) + 1e-6
            new = valid & (dist < max(3.5 * sd, 0.05))
            if (new == use).all():
                break
            use = new
        if fit is None:
            why = f"the edge points of the candidate at ({cand.x:.1f}, {cand.y:.1f}) px fit no ellipse"
            break
        centre = fit[0]
        ell = (tuple(centre), fit[1], fit[2])
    if fit is None:
        return Detection(False, reason=why, polarity=cand.polarity)
    frac = float(use.mean())
    dist = _ellipse_distance(fit, pts[use])
    rms = float(np.sqrt(np.mean(dist**2)))
    (A, B), ang = fit[1], fit[2]
    mean_r = (A + B) / 4
    if frac < MIN_VALID_RAYS:
        return Detection(
            False,
            reason=f"the candidate at ({centre[0]:.1f}, {centre[1]:.1f}) px is not a "
            f"clean ellipse: its edge fits on only {100 * frac:.0f} % of the profiles",
            polarity=cand.polarity,
        )
    if rms > MAX_RMS_REL * mean_r:
        return Detection(
            False,
            reason=f"the candidate at ({centre[0]:.1f}, {centre[1]:.1f}) px is not a "
            f"circle: its edge lies {rms:.2f} px rms from the best ellipse",
            polarity=cand.polarity,
        )
    contrast = float(cand.contrast)
    score = frac / (1 + (rms / 0.25) ** 2) * min(1.0, contrast / (20 * max(sigma, 1e-12)))
    method, blur = "edge", None
    fine = (
        None
        if refine == "edge"
        else _fit_intensity(
            img, ((float(centre[0]), float(centre[1])), (float(A), float(B)), float(ang)), sign, sigma
        )
    )
    if fine is not None:
        (centre, (A, B), ang), blur = fine
        method = "intensity"
    return Detection(
        True,
        float(centre[0]),
        float(centre[1]),
        float(math.sqrt(A * B)),
        ((float(centre[0]), float(centre[1])), (float(A), float(B)), float(ang)),
        float(np.clip(score, 0, 1)),
        "",
        cand.polarity,
        rms,
        int(use.sum()),
        contrast,
        blur,
        method,
    )


def _ellipse_distance_px(p: np.ndarray, dx: np.ndarray, dy: np.ndarray, R: float) -> np.ndarray:
    """Signed distance (px, + outside) of points from the ellipse p = (cx, cy, q11, q12, q22) with
    ``(x − c)ᵀ (q / R²) (x − c) = 1``; ``dx``, ``dy`` from the initial centre. The radial distance
    times the cosine between ray and normal, ``(ρ − 1) ρ / |Q x|``: exact for a circle, and off by the
    square of the ray-normal angle for an ellipse (immaterial for the near-circles seen here)."""
    x, y = dx - p[0], dy - p[1]
    R2 = R * R
    qx = (p[2] * x + p[3] * y) / R2
    qy = (p[3] * x + p[4] * y) / R2
    rho = np.sqrt(np.maximum(x * qx + y * qy, 1e-300))
    return (rho - 1) * rho / np.maximum(np.hypot(qx, qy), 1e-300)


GEO_TOL = 1e-6  # px (and log s): the intensity fit stops when a step moves the ellipse less than this
N_HARMONICS = 4  # angular harmonics of the outer level in the intensity model (a textured surround)
_CHUNK = 256  # rows per product in the normal equations (see _normal_equations)


def _edge_model(
    p: np.ndarray, dx: np.ndarray, dy: np.ndarray, R: float, harmonics: np.ndarray, jacobian: bool = False
):
    """The intensity model of :func:`_fit_intensity` at points (dx, dy) from the initial centre, for the
    parameters p = (cx, cy, q11, q12, q22, a_in, a_out, log s, gx, gy, c1, s1, …, cK, sK): the outer
    level is a_out + Σ c_k cos kφ + s_k sin kφ around the initial centre (``harmonics`` (2K, N) holds
    the cos/sin rows). With ``jacobian`` also ∂I/∂p as a (len(p), N) array, all analytic (the
    geometry's through the distance of :func:`_ellipse_distance_px`)."""
    from scipy.special import ndtr

    s = math.exp(p[7])
    x, y = dx - p[0], dy - p[1]
    R2 = R * R
    qx = (p[2] * x + p[3] * y) / R2
    qy = (p[3] * x + p[4] * y) / R2
    rho2 = np.maximum(x * qx + y * qy, 1e-300)
    rho = np.sqrt(rho2)
    n = np.maximum(np.hypot(qx, qy), 1e-300)
    d = (rho - 1) * rho / n
    Phi = ndtr(d / s)
    g = 1 + (p[8] * dx + p[9] * dy) / R
    outer = p[6] + sum(p[10 + k] * harmonics[k] for k in range(len(harmonics)))  # no BLAS (see below)
    m = p[5] + (outer - p[5]) * Phi
    if not jacobian:
        return g * m
    z = d / s
    k = g * (outer - p[5]) * np.exp(-0.5 * z * z) / (math.sqrt(2 * math.pi) * s)  # ∂I/∂d
    # ∂d = (1 − 1/(2ρ)) ∂ρ² / n − d ∂n / n, with ∂n = (qx ∂qx + qy ∂qy) / n
    a_r = k * (1 - 0.5 / rho) / n
    b_r = k * d / (n * n)
    J = np.empty((len(p), len(d)))
    J[0] = a_r * (-2 * qx) - b_r * (-(p[2] * qx + p[3] * qy) / R2)
    J[1] = a_r * (-2 * qy) - b_r * (-(p[3] * qx + p[4] * qy) / R2)
    J[2] = a_r * (x * x / R2) - b_r * (qx * x / R2)
    J[3] = a_r * (2 * x * y / R2) - b_r * ((qx * y + qy * x) / R2)
    J[4] = a_r * (y * y / R2) - b_r * (qy * y / R2)
    J[5] = g * (1 - Phi)
    J[6] = g * Phi
    J[7] = -k * d  # ∂/∂ log s
    J[8] = m * dx / R
    J[9] = m * dy / R
    J[10:] = (g * Phi)[None, :] * harmonics
    return g * m, J


def _normal_equations(J: np.ndarray, w: np.ndarray, r: np.ndarray):
    """(J W Jᵀ, J W r) for J (P, N), weights w and residuals r (N,), as sums of products over blocks
    of ``_CHUNK`` samples. One (P × N)·(N × P) product is large enough for a multi-threaded BLAS to
    split it over threads, whose start-up and busy-waiting cost 10–80× the product itself on a
    loaded 2-core machine (measured: 0.13 ms with 1 OpenBLAS thread, 2–11 ms with 2); the blocks are
    below any threading threshold, so the time does not depend on the BLAS settings."""
    Jw = J * w
    H = np.zeros((len(J), len(J)))
    for i in range(0, J.shape[1], _CHUNK):
        H += Jw[:, i : i + _CHUNK] @ J[:, i : i + _CHUNK].T
    return H, Jw @ r


def _fit_edge_model(p0, dx, dy, val, R: float, scale: float, f_scale: float = 3.0, max_iter: int = 50):
    """Robust (soft-L1, ``f_scale`` 3 noise σ) least squares of :func:`_edge_model` to the values:
    Levenberg–Marquardt on the iteratively reweighted normal equations (P × P, P = 18), steps scaled
    by the diagonal. Returns the parameters, or None when it does not converge in ``max_iter``
    iterations or meets a singular system."""
    phi = np.arctan2(dy, dx)
    kphi = np.arange(1, N_HARMONICS + 1)[:, None] * phi[None, :]
    harmonics = np.vstack([np.cos(kphi), np.sin(kphi)])
    f2 = f_scale * f_scale

    def cost(res):
        return float(f2 * np.sum(np.sqrt(1 + res * res / f2) - 1))

    p = np.asarray(p0, float).copy()
    model, J = _edge_model(p, dx, dy, R, harmonics, jacobian=True)
    res = (model - val) / scale
    c = cost(res)
    lam = 1e-3
    for _ in range(max_iter):
        w = 1 / np.sqrt(1 + res * res / f2)  # ρ'(z) of soft-L1: the IRLS weights
        H, grad = _normal_equations(J, w, res)
        H /= scale * scale
        grad /= scale
        dg = np.maximum(np.diag(H), 1e-300)
        while True:
            try:
                step = np.linalg.solve(H + lam * np.diag(dg), -grad)
            except np.linalg.LinAlgError:
                return None
            q = p + step
            if not np.isfinite(q).all():
                return None
            # the Jacobian with the trial's value: steps are nearly always accepted, and then the
            # next iteration needs both (one evaluation instead of two)
            m_new, J_new = _edge_model(q, dx, dy, R, harmonics, jacobian=True)
            r_new = (m_new - val) / scale
            c_new = cost(r_new)
            if c_new <= c:
                break
            lam *= 10
            if lam > 1e12:  # no step lowers the cost: converged at a minimum
                return p
        # converged: a step that moves the centre, the axes (q · R / 2 px) and log s by < 1e-6 (the
        # iterations shrink the step ~10× each: what is left is ~1e-7 px), or that changes nothing
        small = (
            max(abs(step[0]), abs(step[1]), 0.5 * R * float(np.abs(step[2:5]).max()), abs(step[7])) <= GEO_TOL
            or np.all(np.abs(step) <= 1e-8 * (np.abs(q) + 1e-8))
            or c - c_new <= 1e-12 * max(c, 1e-300)
        )
        p, c = q, c_new
        lam = max(lam / 10, 1e-9)
        if small:
            return p
        J, res = J_new, r_new
    return None


def _fit_intensity(img, ellipse, sign: float, sigma: float):
    """Refine an ellipse by fitting the pixels within a few px of its edge with a model of a blurred
    solid ellipse under smooth light: ``I = (1 + gx·x + gy·y) · (a_in + (a_out(φ) − a_in) · Φ(d / s))``,
    ``d`` the signed distance from the ellipse, ``Φ`` the normal CDF, ``s`` the edge spread (blur and
    pixel), ``a_out(φ)`` the outer level with ``N_HARMONICS`` angular harmonics. Robust (soft-L1)
    least squares over 18 parameters, seeded by the edge-point fit, in a band of ±5 px (widened to
    ±(3 s + 1.5) px when the edge is wider; a narrower band helps a textured surround but costs
    accuracy on the strip: measured, see docs/detection.md). Returns ((centre, (major, minor),
    angle), s) or None when the fit fails or strays from the seed (the caller keeps the edge-point
    fit)."""
    (cx0, cy0), (A, B), ang = ellipse
    Q0 = _shape_matrix(ellipse)
    R = (A + B) / 4
    h, w = img.shape
    W = min(5.0, 0.6 * R)  # px each side of the edge; small circles keep an inner plateau
    ext = int(math.ceil(max(A, B) / 2 + 12))
    x0, x1 = max(int(cx0) - ext, 0), min(int(cx0) + ext + 1, w)
    y0, y1 = max(int(cy0) - ext, 0), min(int(cy0) + ext + 1, h)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    DX = (xx - cx0).ravel().astype(float)
    DY = (yy - cy0).ravel().astype(float)
    VAL = img[y0:y1, x0:x1].ravel().astype(float)
    p_geo = np.array([0.0, 0.0, Q0[0, 0] * R * R, Q0[0, 1] * R * R, Q0[1, 1] * R * R])
    D_all = _ellipse_distance_px(p_geo, DX, DY, R)
    result = None
    for _ in range(2):  # the second pass widens the band when the edge is wider than assumed
        sel = np.abs(D_all) <= W
        dx, dy, val, d0 = DX[sel], DY[sel], VAL[sel], D_all[sel]
        inner, outer = d0 < -0.5 * W, d0 > 0.5 * W
        if inner.sum() < 8 or outer.sum() < 8:
            return None
        a_in, a_out = float(np.median(val[inner])), float(np.median(val[outer]))
        if sign * (a_out - a_in) <= 0:
            return None
        scale = max(sigma, 1e-3 * abs(a_out - a_in))

        if result is None:
            p0 = np.concatenate([p_geo, [a_in, a_out, math.log(1.0), 0.0, 0.0], np.zeros(2 * N_HARMONICS)])
        else:  # the wider band starts from the narrower band's fit: fewer iterations, the same minimum
            p0 = result
        p = _fit_edge_model(p0, dx, dy, val, R, scale)
        if p is None:
            return None
        s = math.exp(p[7])
        if not np.isfinite(p).all() or not 0.1 < s < 0.5 * R:
            return None
        result = p
        if W >= 3 * s + 1.5 or W >= 0.6 * R:
            break
        W = min(3 * s + 1.5, 0.6 * R)
    if result is None:
        return None
    p = result
    if math.hypot(p[0], p[1]) > max(0.5, 0.02 * R):  # strayed from the edge fit: not trusted
        return None
    Q = np.array([[p[2], p[3]], [p[3], p[4]]]) / (R * R)
    ev, evec = np.linalg.eigh(Q)
    if ev[0] <= 0:
        return None
    major, minor = 2 / math.sqrt(ev[0]), 2 / math.sqrt(ev[1])
    if abs(major / A - 1) > 0.05 or abs(minor / B - 1) > 0.05:
        return None
    angle = math.degrees(math.atan2(evec[1, 0], evec[0, 0])) % 180.0
    return ((cx0 + p[0], cy0 + p[1]), (major, minor), angle), s


# ------------------------------------------------------------------ public API


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
    unique: list[Detection] = []
    for d in sorted(found, key=lambda d: -d.score):  # the same circle reached from two candidates
        if not any(
            math.hypot(d.u - e.u, d.v - e.v) < 0.25 * min(d.diameter_px, e.diameter_px)
            and e.polarity == d.polarity
            for e in unique
        ):
            unique.append(d)
    found = unique
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


def _why_none(img, sigma, failed, rejected) -> str:
    if float(img.max() - img.min()) <= MIN_CONTRAST_SIGMA * max(sigma, 1e-12):
        return "no target found: the image has no contrast above its noise (blank or noise only)"
    cut = [c for c in rejected if c.cut]
    if cut:
        c = max(cut, key=lambda c: c.diameter)
        return (
            f"no target found: the only circle-like region, at ({c.x:.0f}, {c.y:.0f}) px, is cut by the "
            "image border"
        )
    for d in failed:
        return f"no target found: {d.reason}"
    if rejected:
        c = min(rejected, key=lambda c: c.roundness)
        return (
            f"no target found: the best region, at ({c.x:.0f}, {c.y:.0f}) px, is not round "
            f"(boundary radius spread {100 * c.roundness:.0f} %)"
        )
    return "no target found: no solid circle stands out from the background"


def detect_target(
    image,
    *,
    polarity: str = "auto",
    diameter_px: float | None = None,
    roi=None,
    name: str | None = None,
    refine: str = "intensity",
) -> Detection:
    """The one solid circle of ``image`` (path or array): see :class:`Detection` and the module docstring.

    ``polarity``: "dark" circle on bright, "bright" on dark, or "auto". ``diameter_px``: expected
    diameter (keeps circles within 0.7–1.4× of it). ``roi``: (x, y, w, h) px to search in.
    ``refine``: "intensity" (edge points, then the intensity-model fit; the default) or "edge" (stop
    at the edge points' ellipse: the ablation). Raises :class:`InputError` when the file cannot be
    read as an image."""
    img, sigma, found, failed, rejected = _search(image, polarity, diameter_px, roi, name, refine)
    if not found:
        return Detection(False, reason=_why_none(img, sigma, failed, rejected))
    found.sort(key=lambda d: -d.score)
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
        )
    return best


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


__all__ = [
    "Detection",
    "annotate",
    "detect_circles",
    "detect_target",
    "fit_ellipse",
    "load_image",
    "noise_sigma",
]
