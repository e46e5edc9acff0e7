"""Is it still good? Two calibrations of one camera compared where both answer, in units of what their
uncertainty allows, and the difference taken apart into what a cell engineer can act on.

For each pixel of a grid over the two calibrated regions' intersection (inside both training hulls,
at the heights both allow) and each check point either file carries there, both maps answer a robot
point: the **difference field** is ``d = b(p) − a(p)`` (mm, robot frame). Its RMS, 95th percentile and
maximum are the plain answer.

**The ratio.** Two fits of one cell differ by their own errors only: the map's error at a pixel is
``J_p δθ`` with ``δθ ~ N(0, C)`` (:mod:`eyetohand.solve.uncertainty`), so ``E|d_p|² = σ_a² + σ_b²``
with ``σ² = tr(J_p C J_pᵀ)`` of each map at p. That is each point's ``sigma_mm`` without its last
term (the noise of a *fresh* robot measurement, which a difference of two maps does not contain:
dividing by the full ``sigma_mm`` would shrink the ratio by ~3 and hide a real change). The ratio
``|d_p| / sqrt(σ_a² + σ_b²)`` has median ≈ 0.67–0.83 per point when the two agree (half-normal to
Rayleigh, by how anisotropic the error is); its map shows where they part.

**The layers.** The field is fitted, weighted by ``1 / (σ_a² + σ_b²)``, by a rigid motion in the plane
(shift and rotation about the common region's centre, as mapped by A), then a similarity (a uniform
scale added: a height or unit change), then a plane homography (a perspective change: the camera
tilted, or a model lacking perspective); what the homography leaves is lens or focus. ``dz`` is the
mean difference in z (a plane at another height). The motion reported is the exact rigid motion that
takes A's answers to B's (weighted Procrustes).

**The verdict, from the statistics.** Under "both are fits of one unchanged cell", the field is
``d = G z``, z standard normal, with ``G = [J_b L_b, −J_a L_a]`` at the points (``L Lᵀ = C``). After
projecting out a layer (the weighted least-squares projector ``I − P``), the mean squared ratio
``Q = Σ w_p |r_p|² / N`` is a weighted sum of χ²₁ variables with the squared singular values of
``W^½ (I − P) G / √N`` as weights — computed here for these two files, nothing tuned. Each fit's
noise was estimated on its residual dof, so Q is tested as a scaled F: Satterthwaite's ``g·χ²_h``
over the noise estimate's ``χ²_ν/ν`` (ν by Welch–Satterthwaite from both fits' dof). At ``ALPHA`` =
0.01 %: the raw field consistent → ``consistent``; else consistent after the rigid motion → ``moved``;
else after the similarity → ``scale``; else ``model error`` (the reason says whether a homography
explains it — a perspective change — or not: lens, focus).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from eyetohand.calibration.file import Calibration
from eyetohand.core import InputError
from eyetohand.geometry import PLANE_TOLERANCE_MM
from eyetohand.models import HeightRule
from eyetohand.solve import param_jacobian

ALPHA = 1e-4
"""Significance of every layer's test: a clean pair of calibrations is called changed 1 time in 10 000.
Measured (benchmarks/bench_diff.py, docs/diff.md): the raw layer's p-value is close to uniform on
clean pairs (6 % below 0.05, 1 % below 0.001 over 100 pairs of the default cell), so at 0.001 a
site that re-checks 100 times sees a false alarm with probability ~10 %; at 1e-4, ~1 %. The price:
the threshold on the mean squared ratio grows ~20–25 % (F(15, 80): 2.93 → 3.58), the smallest
difference called ~10 % in mm."""
GRID_SIDE = 24
"""Grid points along the longer side of the common region's bounding box."""
MIN_POINTS = 12
SIGMA_FLOOR_MM = 1e-9


class Verdict(StrEnum):
    CONSISTENT = "consistent"
    MOVED = "moved"
    SCALE = "scale"
    MODEL_ERROR = "model error"


class LayerName(StrEnum):
    RAW = "raw"
    RIGID = "rigid"
    SCALE = "scale"
    HOMOGRAPHY = "homography"


@dataclass(frozen=True)
class Motion:
    """The rigid motion taking A's answers to B's: ``b ≈ R(θ)·(a − c) + c + (dx, dy)``, z + dz, about the
    common region's centre ``c`` (robot x, y as A maps it)."""

    dx_mm: float
    dy_mm: float
    dz_mm: float
    rotation_deg: float
    centre_mm: tuple[float, float]

    @property
    def shift_mm(self) -> float:
        return math.hypot(self.dx_mm, self.dy_mm)

    def apply(self, xyz_mm) -> np.ndarray:
        """(N, 3) A's answers moved as B's would be."""
        p = np.asarray(xyz_mm, float).reshape(-1, 3)
        th = math.radians(self.rotation_deg)
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        c = np.asarray(self.centre_mm)
        out = p.copy()
        out[:, :2] = (p[:, :2] - c) @ R.T + c + [self.dx_mm, self.dy_mm]
        out[:, 2] += self.dz_mm
        return out

    def to_dict(self) -> dict:
        return {
            "dx_mm": self.dx_mm,
            "dy_mm": self.dy_mm,
            "dz_mm": self.dz_mm,
            "rotation_deg": self.rotation_deg,
            "centre_mm": list(self.centre_mm),
        }

    def describe(self) -> str:
        return (
            f"moved {self.shift_mm:.3g} mm (dx {self.dx_mm:+.3g}, dy {self.dy_mm:+.3g} mm) "
            f"at {self.rotation_deg:+.3g}° about ({self.centre_mm[0]:.1f}, {self.centre_mm[1]:.1f}) mm"
            + (f", dz {self.dz_mm:+.3g} mm" if abs(self.dz_mm) > 0 else "")
        )


@dataclass(frozen=True)
class Layer:
    """What is left of the field after removing ``name`` (``raw``: nothing): its RMS (mm), mean squared
    ratio ``q`` and the probability ``p_value`` of a q this large if the two calibrations agree."""

    name: LayerName
    rms_mm: float
    q: float
    p_value: float

    def to_dict(self) -> dict:
        return {"name": str(self.name), "rms_mm": self.rms_mm, "q": self.q, "p_value": self.p_value}


@dataclass(frozen=True)
class Difference:
    """Two calibrations compared at ``uv_px`` (N, 2) and heights ``z_mm`` (N,): ``a_mm``, ``b_mm`` (N, 3)
    their answers, ``sigma_a_mm``, ``sigma_b_mm`` (N,) their maps' own errors there."""

    uv_px: np.ndarray
    z_mm: np.ndarray
    a_mm: np.ndarray
    b_mm: np.ndarray
    sigma_a_mm: np.ndarray
    sigma_b_mm: np.ndarray
    n_grid: int
    motion: Motion
    scale_ppm: float
    layers: tuple[Layer, ...]
    verdict: Verdict
    reason: str
    alpha: float = ALPHA

    @property
    def difference_mm(self) -> np.ndarray:
        return self.b_mm - self.a_mm

    @property
    def distance_mm(self) -> np.ndarray:
        return np.linalg.norm(self.difference_mm, axis=1)

    @property
    def sigma_mm(self) -> np.ndarray:
        """(N,) combined error of the two maps: ``sqrt(σ_a² + σ_b²)``."""
        return np.hypot(self.sigma_a_mm, self.sigma_b_mm)

    @property
    def ratio(self) -> np.ndarray:
        return self.distance_mm / np.maximum(self.sigma_mm, SIGMA_FLOOR_MM)

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.distance_mm**2)))

    @property
    def p95_mm(self) -> float:
        return float(np.percentile(self.distance_mm, 95))

    @property
    def max_mm(self) -> float:
        return float(self.distance_mm.max())

    @property
    def ratio_median(self) -> float:
        return float(np.median(self.ratio))

    @property
    def sigma_median_mm(self) -> float:
        return float(np.median(self.sigma_mm))

    def layer(self, name: LayerName) -> Layer:
        return next(x for x in self.layers if x.name is name)

    def to_dict(self) -> dict:
        return {
            "verdict": str(self.verdict),
            "reason": self.reason,
            "rms_mm": self.rms_mm,
            "p95_mm": self.p95_mm,
            "max_mm": self.max_mm,
            "ratio_median": self.ratio_median,
            "sigma_median_mm": self.sigma_median_mm,
            "moved": self.motion.to_dict(),
            "scale_ppm": self.scale_ppm,
            "layers": [x.to_dict() for x in self.layers],
            "points": len(self.uv_px),
            "grid_points": self.n_grid,
            "alpha": self.alpha,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def summary(self) -> str:
        lines = [
            f"verdict: {self.verdict} — {self.reason}",
            f"difference over {len(self.uv_px)} points ({self.n_grid} grid, "
            f"{len(self.uv_px) - self.n_grid} check): RMS {self.rms_mm:.4g} mm, p95 {self.p95_mm:.4g} mm, "
            f"max {self.max_mm:.4g} mm",
            f"ratio |difference| / combined sigma: median {self.ratio_median:.3g} "
            f"(typically 0.5–1.4 when the two agree; combined sigma median {self.sigma_median_mm:.3g} mm)",
            f"rigid motion A → B: {self.motion.describe()}; scale {self.scale_ppm:+.1f} ppm",
            "layers (RMS left, mean squared ratio, p): "
            + "; ".join(f"{x.name} {x.rms_mm:.3g} mm q {x.q:.3g} p {x.p_value:.2g}" for x in self.layers),
        ]
        return "\n".join(lines)


# ---------------------------------------------------------------- where both answer


def _grid_points(a: Calibration, b: Calibration, side: int) -> np.ndarray:
    ra, rb = _region(a, "A"), _region(b, "B")
    lo = np.maximum(ra.hull_px.min(axis=0), rb.hull_px.min(axis=0))
    hi = np.minimum(ra.hull_px.max(axis=0), rb.hull_px.max(axis=0))
    if not (hi > lo).all():
        raise InputError("A and B share no calibrated region: their training hulls do not overlap")
    step = float(max(hi - lo)) / (side - 1)
    us = np.arange(lo[0], hi[0] + 0.5 * step, step)
    vs = np.arange(lo[1], hi[1] + 0.5 * step, step)
    uv = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
    return _inside_both(a, b, uv)


def _inside_both(a: Calibration, b: Calibration, uv: np.ndarray) -> np.ndarray:
    if len(uv) == 0:
        return uv
    keep = (_region(a, "A").outside_px(uv) == 0) & (_region(b, "B").outside_px(uv) == 0)
    return uv[keep]


def _region(cal: Calibration, name: str):
    if cal.region is None:
        raise InputError(f"{name} records no calibrated region (a pre-0.2 file): recalibrate it")
    return cal.region


def common_heights(a: Calibration, b: Calibration) -> tuple[tuple[float | None, float | None], ...]:
    """The heights both calibrations answer: ``((z_a, z_b), ...)`` — each a plane's own (None: its
    plane) when both are single-height (a different plane shows as dz), or the common z range's low,
    middle and high when one or both calibrated several heights."""
    ra, rb = _region(a, "A"), _region(b, "B")
    if ra.plane_z_mm is not None and rb.plane_z_mm is not None:
        return ((None, None),)
    if ra.plane_z_mm is not None or rb.plane_z_mm is not None:
        plane, other, name = (ra, rb, "B") if ra.plane_z_mm is not None else (rb, ra, "A")
        if plane.plane_slope is not None:
            raise InputError(
                "one calibration's plane is tilted and the other has several heights: no common z"
            )
        z = float(plane.plane_z_mm)
        if not other.z_allowed_one(z):
            raise InputError(f"the plane z = {z:g} mm is outside {name}'s calibrated heights: no common z")
        return ((z, z),)
    (alo, ahi), (blo, bhi) = _z_range(ra), _z_range(rb)
    lo, hi = max(alo, blo), min(ahi, bhi)
    if hi < lo:
        raise InputError(
            f"A's heights {ra.z_range_mm} mm and B's {rb.z_range_mm} mm do not overlap: no common z"
        )
    zs = sorted({lo, 0.5 * (lo + hi), hi})
    return tuple((z, z) for z in zs)


def _z_range(region) -> tuple[float, float]:
    if region.z_range_mm is None:
        raise InputError("a calibrated region records neither a plane nor a z range")
    return float(region.z_range_mm[0]), float(region.z_range_mm[1])


def _check_points(a: Calibration, b: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and heights of the check points either file carries inside both hulls at heights both allow."""
    uvs, zs = [], []
    for cal in (a, b):
        if cal.check_pairs is not None:
            uvs.append(cal.check_pairs.uv_px)
            zs.append(cal.check_pairs.xyz_mm[:, 2])
    if not uvs:
        return np.empty((0, 2)), np.empty(0)
    uv, z = np.vstack(uvs), np.concatenate(zs)
    heights = common_heights(a, b)
    if len(heights) == 1 and heights[0][0] is not None:  # a plane against a z range: at the plane
        z = np.full(len(z), heights[0][0])
    keep = (_region(a, "A").outside_px(uv) == 0) & (_region(b, "B").outside_px(uv) == 0)
    for cal in (a, b):
        r = _region(cal, "")
        if r.plane_z_mm is not None:
            continue  # mapped on its plane
        lo, hi = _z_range(r)
        keep &= (z >= lo - r.z_margin_mm) & (z <= hi + r.z_margin_mm)
    return uv[keep], z[keep]


def _answers(cal: Calibration, uv: np.ndarray, z: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) the calibration's guarded answers and (N, D, 2) its maps' parameter factor ``J L``."""
    if _region(cal, "").plane_z_mm is not None:
        xyz = cal.image_to_robot(uv, part_diameter_mm=0.0)  # the maps compared, not detections
    else:
        xyz = cal.image_to_robot(uv, z, part_diameter_mm=0.0)
    model = cal.model
    zs = xyz[:, 2] if model.height_rule is not HeightRule.COMPUTED else np.zeros(len(uv))
    unc = cal.uncertainty
    if unc is None:
        raise InputError("a calibration records no uncertainty (a pre-0.2 file): recalibrate it")
    w, V = np.linalg.eigh(0.5 * (unc.covariance + unc.covariance.T))
    L = V * np.sqrt(np.maximum(w, 0.0))
    G = param_jacobian(model, uv, zs)[:, :2, :] @ L  # (N, 2, D)
    return xyz, G


# ---------------------------------------------------------------- layers


def _bases(xy: np.ndarray, centre: np.ndarray) -> dict[LayerName, np.ndarray]:
    """(2N, m) linearised effect on the field of each layer's motion at the points (A's x, y)."""
    q = (xy - centre) / max(float(np.abs(xy - centre).max()), 1e-9)
    n = len(q)
    x, y = q[:, 0], q[:, 1]
    one, zero = np.ones(n), np.zeros(n)

    def cols(*pairs):
        return np.column_stack([np.column_stack([px, py]).reshape(-1) for px, py in pairs])

    rigid = [(one, zero), (zero, one), (-y, x)]
    scale = [*rigid, (x, y)]
    homography = [*scale, (y, x), (x, -y), (x * x, x * y), (x * y, y * y)]
    return {
        LayerName.RIGID: cols(*rigid),
        LayerName.SCALE: cols(*scale),
        LayerName.HOMOGRAPHY: cols(*homography),
    }


def _null_p(q: float, M: np.ndarray, split: int, dof_a: int, dof_b: int) -> float:
    """P(Q ≥ q) when the field is only the two fits' errors: ``Q = |M z|²``, z standard normal, of
    which the first ``split`` columns are B's (noise estimated on ``dof_b``), the rest A's."""
    from scipy import stats  # lazily: SciPy costs ~0.4 s of start-up

    lam = np.linalg.svd(M, compute_uv=False) ** 2
    tot = float(lam.sum())
    if tot <= 0:
        return 0.0 if q > 0 else 1.0
    g = float((lam**2).sum()) / tot
    h = tot / g
    tb = float((M[:, :split] ** 2).sum())
    ta = tot - tb
    nu = (ta + tb) ** 2 / (ta**2 / max(dof_a, 1) + tb**2 / max(dof_b, 1))
    return float(stats.f.sf(q / tot, h, nu))


def _procrustes(pa: np.ndarray, pb: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Weighted rigid fit b ≈ R(θ)(a − ca) + cb: ``(centroid of a, θ rad, s)`` with the similarity's scale."""
    ww = w / w.sum()
    ca, cb = ww @ pa, ww @ pb
    A, B = pa - ca, pb - cb
    sxx = float(ww @ (A[:, 0] * B[:, 0] + A[:, 1] * B[:, 1]))
    sxy = float(ww @ (A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]))
    th = math.atan2(sxy, sxx)
    s = math.hypot(sxx, sxy) / float(ww @ (A * A).sum(axis=1))
    return ca, th, s


def _similar(pa: np.ndarray, pb: np.ndarray, w: np.ndarray, *, scaled: bool) -> np.ndarray:
    """(N, 2) A's x, y moved by the weighted best rigid motion (or similarity) onto B's."""
    ca, th, s = _procrustes(pa, pb, w)
    ww = w / w.sum()
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]) * (s if scaled else 1.0)
    return (pa - ca) @ R.T + ww @ pb


def _projective(pa: np.ndarray, pb: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N, 2) A's x, y through the plane homography fitted (weighted, Hartley-normalised DLT) onto B's."""

    def norm(p):
        c = p.mean(axis=0)
        k = math.sqrt(2) / max(float(np.mean(np.linalg.norm(p - c, axis=1))), 1e-12)
        return np.array([[k, 0, -k * c[0]], [0, k, -k * c[1]], [0, 0, 1.0]])

    Ta, Tb = norm(pa), norm(pb)
    a = np.column_stack([pa, np.ones(len(pa))]) @ Ta.T
    b = np.column_stack([pb, np.ones(len(pb))]) @ Tb.T
    n = len(a)
    zero = np.zeros((n, 3))
    rows = (
        np.vstack(
            [
                np.hstack([a, zero, -b[:, :1] * a]),
                np.hstack([zero, a, -b[:, 1:2] * a]),
            ]
        )
        * np.sqrt(np.r_[w, w])[:, None]
    )
    H = np.linalg.svd(rows)[2][-1].reshape(3, 3)
    H = np.linalg.inv(Tb) @ H @ Ta
    q = np.column_stack([pa, np.ones(n)]) @ H.T
    return q[:, :2] / q[:, 2:]


def _motion(pa: np.ndarray, pb: np.ndarray, w: np.ndarray, centre: np.ndarray) -> tuple[Motion, float]:
    """The rigid motion about ``centre`` and the similarity's scale (ppm)."""
    ca, th, s = _procrustes(pa[:, :2], pb[:, :2], w)
    ww = w / w.sum()
    cb = ww @ pb[:, :2]
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    t = cb - ca + (R - np.eye(2)) @ (ca - centre)  # b = R(a − centre) + centre + t
    dz = float(ww @ (pb[:, 2] - pa[:, 2]))
    m = Motion(float(t[0]), float(t[1]), dz, math.degrees(th), (float(centre[0]), float(centre[1])))
    return m, 1e6 * (s - 1.0)


def diff(a: Calibration, b: Calibration, *, grid_side: int = GRID_SIDE, alpha: float = ALPHA) -> Difference:
    """Compare calibration ``b`` with ``a`` where both answer (see the module's text)."""
    if not (isinstance(grid_side, int) and 4 <= grid_side <= 200):
        raise InputError(f"grid_side: expected a whole number from 4 to 200, got {grid_side!r}")
    if not (0 < alpha < 0.5):
        raise InputError(f"alpha: expected a probability between 0 and 0.5, got {alpha!r}")
    if a.image_size is not None and b.image_size is not None and tuple(a.image_size) != tuple(b.image_size):
        raise InputError(
            f"A's image is {a.image_size[0]}x{a.image_size[1]} px and B's "
            f"{b.image_size[0]}x{b.image_size[1]}: not one camera's calibrations"
        )
    for cal, name in ((a, "A"), (b, "B")):
        if cal.uncertainty is None:
            raise InputError(f"{name} records no uncertainty (a pre-0.2 file): recalibrate it")
    grid = _grid_points(a, b, grid_side)
    chk_uv, chk_z = _check_points(a, b)
    uv_parts, z_parts, pa_parts, pb_parts, ga_parts, gb_parts = [], [], [], [], [], []
    n_grid = 0
    for za, zb in common_heights(a, b):
        za_arr = None if za is None else np.full(len(grid), za)
        zb_arr = None if zb is None else np.full(len(grid), zb)
        pa, ga = _answers(a, grid, za_arr)
        pb, gb = _answers(b, grid, zb_arr)
        uv_parts.append(grid)
        z_parts.append(pa[:, 2])
        pa_parts.append(pa)
        pb_parts.append(pb)
        ga_parts.append(ga)
        gb_parts.append(gb)
        n_grid += len(grid)
    if len(chk_uv):
        pa, ga = _answers(a, chk_uv, chk_z)
        pb, gb = _answers(b, chk_uv, chk_z)
        uv_parts.append(chk_uv)
        z_parts.append(pa[:, 2])
        pa_parts += [pa]
        pb_parts += [pb]
        ga_parts += [ga]
        gb_parts += [gb]
    uv = np.vstack(uv_parts)
    if len(uv) < MIN_POINTS:
        raise InputError(
            f"A and B share too little calibrated region: {len(uv)} common points, "
            f"at least {MIN_POINTS} needed"
        )
    pa, pb = np.vstack(pa_parts), np.vstack(pb_parts)
    Ga, Gb = np.concatenate(ga_parts), np.concatenate(gb_parts)
    sa = np.sqrt(np.einsum("ncd,ncd->n", Ga, Ga))
    sb = np.sqrt(np.einsum("ncd,ncd->n", Gb, Gb))
    var = np.maximum(sa**2 + sb**2, SIGMA_FLOOR_MM**2)
    w = 1.0 / var
    n = len(uv)
    w2 = np.repeat(w, 2)
    sw = np.sqrt(w2 / n)
    G = np.concatenate([Gb.reshape(2 * n, -1), -Ga.reshape(2 * n, -1)], axis=1)
    split = Gb.shape[2]
    dof_a, dof_b = a.uncertainty.dof, b.uncertainty.dof  # type: ignore[union-attr]
    centre = (w @ pa[:, :2]) / w.sum()

    fits = {
        LayerName.RAW: pa[:, :2],
        LayerName.RIGID: _similar(pa[:, :2], pb[:, :2], w, scaled=False),
        LayerName.SCALE: _similar(pa[:, :2], pb[:, :2], w, scaled=True),
        LayerName.HOMOGRAPHY: _projective(pa[:, :2], pb[:, :2], w),
    }

    def layer(name: LayerName, B: np.ndarray | None) -> Layer:
        """The exact fit's residual; the null distribution from the layer's linearised projector."""
        r = (pb[:, :2] - fits[name]).reshape(-1)
        Mw = G * sw[:, None]
        if B is not None:
            Qb, _ = np.linalg.qr(B * sw[:, None])  # the weighted projector is Qb Qbᵀ
            Mw = Mw - Qb @ (Qb.T @ Mw)
        q = float((sw * r) @ (sw * r))
        rms = float(np.sqrt(np.mean(r.reshape(-1, 2) ** 2) * 2))
        return Layer(name, rms, q, _null_p(q, Mw, split, dof_a, dof_b))

    bases = _bases(pa[:, :2], centre)
    layers = (layer(LayerName.RAW, None), *(layer(k, v) for k, v in bases.items()))
    motion, scale_ppm = _motion(pa, pb, w, centre)
    verdict, reason = _verdict(layers, motion, scale_ppm, alpha)
    if verdict is Verdict.CONSISTENT and abs(motion.dz_mm) > PLANE_TOLERANCE_MM:
        # two planes' heights are the commanded z of their pairs, exact: a different one is a move
        verdict, reason = Verdict.MOVED, f"the plane is {motion.dz_mm:+.3g} mm higher in B; x, y agree"
    if verdict is Verdict.CONSISTENT:
        noisier = _noisier(a, b, alpha)
        if noisier:
            verdict, reason = Verdict.MODEL_ERROR, noisier
    return Difference(
        uv, np.concatenate(z_parts), pa, pb, sa, sb, n_grid, motion, scale_ppm, layers, verdict, reason, alpha
    )


def _noisier(a: Calibration, b: Calibration, alpha: float) -> str | None:
    """Why one file's residual noise is significantly larger than the other's (two-sided F test on
    their dof at ``alpha``), or None. A model that lacks a term turns what it cannot follow into
    residual noise, and its sigma grows with it: two such maps can agree "within their uncertainty"
    only because one of them claims a large one."""
    from scipy import stats  # lazily: SciPy costs ~0.4 s of start-up

    ua, ub = a.uncertainty, b.uncertainty
    if ua is None or ub is None or min(ua.noise_mm, ub.noise_mm) <= 0:
        return None
    f = (ua.noise_mm / ub.noise_mm) ** 2
    p = 2 * min(float(stats.f.sf(f, ua.dof, ub.dof)), float(stats.f.cdf(f, ua.dof, ub.dof)))
    if p >= alpha:
        return None
    (hi, hi_u, hi_m), (lo, lo_u, lo_m) = sorted(
        (("A", ua, a.model_name), ("B", ub, b.model_name)), key=lambda t: -t[1].noise_mm
    )
    return (
        f"the maps agree only within {hi}'s wide uncertainty: {hi} ({hi_m}) leaves {hi_u.noise_mm:.3g} mm of "
        f"residual noise per axis where {lo} ({lo_m}) leaves {lo_u.noise_mm:.3g} mm (F test p = {p:.2g}) — "
        f"{hi}'s model lacks a term, or its pairs were noisier"
    )


def _verdict(
    layers: tuple[Layer, ...], motion: Motion, scale_ppm: float, alpha: float
) -> tuple[Verdict, str]:
    by = {x.name: x for x in layers}
    raw = by[LayerName.RAW]
    if raw.p_value >= alpha:
        return Verdict.CONSISTENT, (
            f"the two differ by what their own uncertainty allows (mean squared ratio {raw.q:.3g}, "
            f"p = {raw.p_value:.2g})"
        )
    if by[LayerName.RIGID].p_value >= alpha:
        return Verdict.MOVED, f"camera or robot base {motion.describe()}; nothing else differs"
    if by[LayerName.SCALE].p_value >= alpha:
        return Verdict.SCALE, (
            f"a scale change of {scale_ppm:+.0f} ppm (a different height or units) after {motion.describe()}"
        )
    if by[LayerName.HOMOGRAPHY].p_value >= alpha:
        return Verdict.MODEL_ERROR, (
            "a perspective difference (the camera tilted, or one model lacks perspective); "
            f"rigid part: {motion.describe()}"
        )
    return Verdict.MODEL_ERROR, (
        "a difference no homography explains (lens or focus changed, or a model lacks a lens term); "
        f"RMS left after a homography {by[LayerName.HOMOGRAPHY].rms_mm:.3g} mm"
    )
