"""The calibrated region: where a calibration has seen its training pairs, and how far a point is
outside it.

A mapping is answered only inside the convex hull of the training pixels, grown by a margin, and at
heights the calibration knows: the plane (single-height models, within ``PLANE_TOLERANCE_MM`` of the
plane at the point's x, y) or the calibrated z range grown by a margin (multi-height models). The
same rule, margins and words serve the library, the CLI, HTTP, TCP and the page (they all call
:meth:`CalibratedRegion.check`).

Whether robot points are *one height* is one rule too (:func:`fit_height_plane`, used by the
single-height models, ``auto`` and the region): a robot's reported z varies from pose to pose by
0.01–0.05 mm and a table is not perfectly level, so the points' least-squares plane
z = a·x + b·y + c is fitted and they are one height when its residuals are robot noise — they do not
split into levels (no gap between sorted residuals wider than ``LEVEL_GAP_MIN_MM`` and
``LEVEL_GAP_NOISE`` × the RMS within the levels) and their RMS is at most ``MAX_HEIGHT_NOISE_MM``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from types import ModuleType

import numpy as np

from eyetohand.core import InputError

_HULL: ModuleType | None
try:  # the optional compiled loop (setup.py); see hull_kernel
    from eyetohand.geometry import _hull as _HULL
except ImportError:
    _HULL = None

MARGIN_FRACTION = 0.05
"""The image margin: 5 % of the larger side of the hull's bounding box (at least ``MIN_MARGIN_PX``)."""
MIN_MARGIN_PX = 5.0
PLANE_TOLERANCE_MM = 0.5
"""A z given to a single-height model may differ from its plane (at the point's x, y) by this much (mm)."""
MIN_HEIGHT_TOLERANCE_MM = 0.05
"""The floor of a plane's tolerance, max(0.05 mm, 3 × its RMS): a robot's z repeats to 0.01–0.05 mm."""
HEIGHT_TOLERANCE_RMS = 3.0
MAX_HEIGHT_NOISE_MM = 0.1
"""Points whose RMS about their plane exceeds this are not one height: twice the worst robot z noise."""
LEVEL_GAP_MIN_MM = PLANE_TOLERANCE_MM / 2
"""Two levels must be at least this far apart (and ``LEVEL_GAP_NOISE`` × the noise within them)."""
LEVEL_GAP_NOISE = 10.0
ONE_HEIGHT_RULE = (
    f"one height: the least-squares plane's residuals split into no levels (no gap wider than "
    f"{LEVEL_GAP_MIN_MM:g} mm and {LEVEL_GAP_NOISE:g}× the RMS within the levels) and their RMS is at "
    f"most {MAX_HEIGHT_NOISE_MM:g} mm"
)
"""The one-height rule in words (notes, the report, messages)."""
Z_MARGIN_FRACTION = 0.25
"""Multi-height models: the z range grown by 25 % of its span on each side (at least ``MIN_Z_MARGIN_MM``)."""
MIN_Z_MARGIN_MM = 5.0
_CHUNK = 1 << 16
_TEST_CHUNK = 1 << 13  # points per pass of the NumPy half-plane tests (no compiled loop): stays in cache
BANDS = 256
"""Horizontal bands of the hull whose proven-inside u intervals decide most pixels in one lookup."""
_BAND_SLACK = 1e-6
"""Each band's rectangle is proven for v this fraction of a band beyond its edges (a pixel's band is
found by one rounded multiplication)."""
MARGIN_BANDS = 256
"""Horizontal bands of a polygon proven to lie within the margin: the lookup of the margin ring."""
MARGIN_ARC_POINTS = 64
"""Vertices of the regular polygon that stands for the margin's disc in a grown hull."""
_MARGIN_SHRINK = 1e-9
"""The margin polygon is the hull grown by the margin less this × (the hull's span + the margin): room
above the rounding of a computed distance by six orders of magnitude."""
_PROOF_MARGIN = 1e-12
"""A band's corners must pass every edge's cross product by this × |e_u| + |e_v| × the hull's span:
above the rounding of any cross product there by three orders of magnitude."""


def hull_kernel() -> ModuleType | None:
    """``eyetohand.geometry._hull``, the compiled test of many pixels against the hull
    (src/eyetohand/geometry/_hull.c, built at install), or None where it could not be built: the tests
    then run in NumPy chunks — the same verdicts, slower."""
    return _HULL


@dataclass(frozen=True)
class HullScan:
    """Many pixels tested against the hull (:meth:`CalibratedRegion.scan`): ``outside`` how many fail a
    half-plane test, ``mask`` (N,) True for those (None when none does), ``finite`` whether every pixel
    was finite."""

    outside: int
    mask: np.ndarray | None
    finite: bool


@dataclass(frozen=True)
class HeightPlane:
    """The least-squares plane z = a·x + b·y + c of robot points and the verdict of the one-height rule
    (module docstring). ``levels``: the (z_mm, count) of each level when the points split into two or
    more (empty when they do not)."""

    z0_mm: float  # c: the plane's z at x = y = 0
    slope: tuple[float, float]  # (a, b), mm of z per mm of x and of y
    rms_mm: float  # RMS of the points' z about the plane (N − 3 degrees of freedom)
    centre_xy_mm: tuple[float, float]
    n: int
    levels: tuple[tuple[float, int], ...] = ()

    @property
    def tolerance_mm(self) -> float:
        """How far the points lie from their plane, from the robot's noise: max(0.05 mm, 3 × RMS)."""
        return max(MIN_HEIGHT_TOLERANCE_MM, HEIGHT_TOLERANCE_RMS * self.rms_mm)

    @property
    def tilt_deg(self) -> float:
        return math.degrees(math.atan(math.hypot(*self.slope)))

    @property
    def tilted(self) -> bool:
        return self.slope != (0.0, 0.0)

    @property
    def one_height(self) -> bool:
        return not self.levels and self.rms_mm <= MAX_HEIGHT_NOISE_MM

    @property
    def centre_z_mm(self) -> float:
        return float(self.z_at(np.array([self.centre_xy_mm]))[0])

    def z_at(self, xy_mm) -> np.ndarray:
        """(N,) the plane's z at (N, 2) robot x, y (mm)."""
        xy = np.asarray(xy_mm, float).reshape(-1, 2)
        return plane_z(self.z0_mm, self.slope, xy)

    def describe(self) -> str:
        """The plane in words: its height, tilt, RMS and tolerance (for notes and the report)."""
        where = f"z = {self.z0_mm:g} mm" if not self.tilted else self.formula()
        return (
            f"{where} (tilt {self.tilt_deg:.3f} deg, RMS {self.rms_mm:.3f} mm about it, "
            f"tolerance {self.tolerance_mm:.3f} mm)"
        )

    def formula(self) -> str:
        a, b = self.slope
        return (
            f"z = {self.z0_mm:.6g} {'+-'[a < 0]} {abs(a):.6g}·x {'+-'[b < 0]} {abs(b):.6g}·y mm "
            f"({self.centre_z_mm:g} mm at the points' centre)"
        )

    def why_not_one(self) -> str:
        """Why the points are not one height (empty when they are)."""
        if self.levels:
            parts = [f"z ≈ {z:.3f} mm ({k} pair{'s' * (k != 1)})" for z, k in self.levels]
            what = " and ".join(parts) if len(parts) == 2 else ", ".join(parts)
            return f"{len(self.levels)} levels: {what}"
        if self.rms_mm > MAX_HEIGHT_NOISE_MM:
            return (
                f"heights spread by RMS {self.rms_mm:.3f} mm about their best plane, beyond a robot's "
                f"z noise ({MAX_HEIGHT_NOISE_MM:g} mm)"
            )
        return ""


def plane_z(z0_mm: float, slope, xy_mm: np.ndarray) -> np.ndarray:
    """(N,) z = a·x + b·y + c at (N, 2) x, y; exactly ``c`` where the slope is (0, 0)."""
    a, b = float(slope[0]), float(slope[1])
    if a == 0.0 and b == 0.0:
        return np.full(len(xy_mm), float(z0_mm))
    return a * xy_mm[:, 0] + b * xy_mm[:, 1] + float(z0_mm)


def fit_height_plane(xyz_mm) -> HeightPlane:
    """The one-height rule (module docstring) on (N, 3) robot points. Points whose z is exactly
    constant give the plane z = mean(z) with slope (0, 0) — exactly what a calibration of one height
    stored before the plane (``plane_z_mm`` alone)."""
    xyz = np.asarray(xyz_mm, float).reshape(-1, 3)
    z = xyz[:, 2]
    n = len(z)
    if n == 0 or not np.isfinite(xyz).all():
        raise InputError("the height plane needs one or more finite robot points")
    centre = xyz[:, :2].mean(axis=0)
    cxy = (float(centre[0]), float(centre[1]))
    if np.ptp(z) == 0.0:
        return HeightPlane(float(z.mean()), (0.0, 0.0), 0.0, cxy, n)
    d = xyz[:, :2] - centre
    zm = float(z.mean())
    a = b = 0.0
    if n >= 3 and np.linalg.matrix_rank(d) == 2:
        (a, b), *_ = np.linalg.lstsq(d, z - zm, rcond=None)
        a, b = float(a), float(b)
    c = zm - a * cxy[0] - b * cxy[1]
    r = z - plane_z(c, (a, b), xyz[:, :2])
    rms = float(np.sqrt((r @ r) / max(n - 3, 1)))
    groups = _levels(r)
    if groups is None and rms > MAX_HEIGHT_NOISE_MM:
        groups = _levels(z)  # e.g. two layers side by side, which a tilted plane half follows
    levels = () if groups is None else tuple((float(z[g].mean()), int(g.size)) for g in groups)
    return HeightPlane(c, (a, b), rms, cxy, n, levels)


def _levels(v: np.ndarray) -> list[np.ndarray] | None:
    """Index groups of ``v`` split at every gap wider than ``LEVEL_GAP_MIN_MM`` between its sorted
    values, when each of those gaps is also wider than ``LEVEL_GAP_NOISE`` × the pooled RMS of the
    values about their group's mean; None when ``v`` is one level."""
    order = np.argsort(v, kind="stable")
    s = v[order]
    gaps = np.diff(s)
    cuts = np.flatnonzero(gaps > LEVEL_GAP_MIN_MM) + 1
    if cuts.size == 0:
        return None
    groups = np.split(order, cuts)
    ss = sum(float(((v[g] - v[g].mean()) ** 2).sum()) for g in groups)
    within = math.sqrt(ss / max(len(v) - len(groups), 1))
    if gaps[cuts - 1].min() <= LEVEL_GAP_NOISE * within:
        return None
    return groups


class OutsideError(InputError):
    """A point outside the calibrated region (image or height), refused unless allowed."""


@dataclass(frozen=True)
class CalibratedRegion:
    """``hull_px`` (K, 2) counter-clockwise in image coordinates; ``margin_px``; the heights:
    the plane z = ``plane_slope`` · (x, y) + ``plane_z_mm`` (single height; a slope of None is (0, 0),
    as every file before the plane stored it) or ``z_range_mm`` (lo, hi) with ``z_margin_mm``."""

    hull_px: np.ndarray
    margin_px: float
    plane_z_mm: float | None = None
    z_range_mm: tuple[float, float] | None = None
    z_margin_mm: float = 0.0
    plane_slope: tuple[float, float] | None = None

    @classmethod
    def from_pairs(
        cls, uv_px, xyz_mm, *, plane_z_mm: float | None, plane_slope: tuple[float, float] | None = None
    ) -> CalibratedRegion:
        uv = np.asarray(uv_px, float)
        hull = convex_hull(uv)
        span = float(np.max(uv.max(axis=0) - uv.min(axis=0)))
        margin = max(MIN_MARGIN_PX, MARGIN_FRACTION * span)
        if plane_z_mm is not None:
            slope = None if plane_slope is None or tuple(plane_slope) == (0.0, 0.0) else plane_slope
            return cls(
                hull,
                margin,
                plane_z_mm=float(plane_z_mm),
                plane_slope=None if slope is None else (float(slope[0]), float(slope[1])),
            )
        z = np.asarray(xyz_mm, float)[:, 2]
        lo, hi = float(z.min()), float(z.max())
        return cls(
            hull, margin, z_range_mm=(lo, hi), z_margin_mm=max(MIN_Z_MARGIN_MM, Z_MARGIN_FRACTION * (hi - lo))
        )

    # ------------------------------------------------------------ geometry
    @cached_property
    def _edges(self) -> tuple[np.ndarray, ...]:
        """The hull's edges as columns: start (a_u, a_v), direction (e_u, e_v), squared length."""
        a = self.hull_px
        e = np.roll(a, -1, axis=0) - a
        return (
            a[:, 0].copy(),
            a[:, 1].copy(),
            e[:, 0].copy(),
            e[:, 1].copy(),
            np.maximum((e * e).sum(-1), 1e-300),
        )

    @cached_property
    def _edge_floats(self) -> tuple[tuple[float, float, float, float, float], ...]:
        """The same per edge as Python floats (a_u, a_v, e_u, e_v, squared length): one point's test."""
        return tuple(zip(*(c.tolist() for c in self._edges), strict=True))

    @cached_property
    def _scan_tables(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        """``(edges (K, 4), bands (B, 2), v0, 1/h)`` of the compiled scan (see ``_bands``)."""
        au, av, eu, ev, _ = self._edges
        edges = np.ascontiguousarray(np.column_stack([au, av, eu, ev]))
        bands, v0, inv_h = _bands(edges)
        return edges, bands, v0, inv_h

    @cached_property
    def _margin_polygon(self) -> np.ndarray:
        """The hull grown by the margin less ``_MARGIN_SHRINK`` (inscribed: every point of it is nearer
        the hull than the margin, with room for a computed distance's rounding)."""
        span = float(np.ptp(self.hull_px, axis=0).max()) if len(self.hull_px) else 0.0
        return grown_polygon(self.hull_px, self.margin_px - _MARGIN_SHRINK * (span + self.margin_px))

    @cached_property
    def _margin_chords(self) -> tuple[np.ndarray, float, float]:
        """The trapezoid lookup (:func:`_chord_bands`) of ``_margin_polygon``."""
        return _chord_bands(_polygon_edges(self._margin_polygon), MARGIN_BANDS)

    def unproven(self, uv_px) -> np.ndarray:
        """The indices of the (N, 2) pixels that one lookup does not prove within the margin (the
        trapezoids of ``_margin_chords``): every other pixel is finite and passes :meth:`check`'s image
        test. Many pixels in one compiled pass, else the same arithmetic in NumPy."""
        uv = np.ascontiguousarray(np.asarray(uv_px, float).reshape(-1, 2))
        rows, v0, inv_h = self._margin_chords
        kernel = hull_kernel()
        if kernel is not None:
            idx = np.empty(len(uv), np.int64)
            return idx[: kernel.unproven(uv, rows, v0, inv_h, idx)]
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            t = (v - v0) * inv_h
            in_t = (t >= 0.0) & (t < len(rows))
            r = rows[np.where(in_t, t, 0.0).astype(np.intp)]
            dv = v - r[:, 0]
            ok = in_t & (u >= r[:, 1] + r[:, 2] * dv) & (u <= r[:, 3] + r[:, 4] * dv)
        return np.flatnonzero(~ok)

    def _outside_one(self, u: float, v: float) -> float:
        """``outside_px`` of one point on Python floats: the same arithmetic as the many-point paths
        (IEEE doubles, in their order), no arrays."""
        edges = self._edge_floats
        for au, av, eu, ev, _ in edges:
            if not (eu * (v - av) - ev * (u - au) >= 0):
                break
        else:
            return 0.0
        best = math.inf
        for au, av, eu, ev, ee in edges:
            ru, rv = u - au, v - av
            t = (ru * eu + rv * ev) / ee
            t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t  # np.clip's order: a NaN stays NaN
            du, dv = u - (au + t * eu), v - (av + t * ev)
            dd = du * du + dv * dv
            if not dd >= best:  # np.min: the first NaN wins
                best = dd
                if dd != dd:
                    break
        return math.sqrt(best)

    def outside_one(self, u: float, v: float) -> float:
        """``outside_px`` of one point (floats): the library's one-point path, no arrays."""
        return self._outside_one(u, v)

    def scan(self, uv_px) -> HullScan:
        """Which of (N, 2) pixels fail one of the hull's half-plane tests (the outside ones, and NaN), in
        one compiled pass (``hull_kernel``) or NumPy chunks; and whether every pixel was finite."""
        uv = np.ascontiguousarray(np.asarray(uv_px, float).reshape(-1, 2))
        kernel = hull_kernel()
        if kernel is not None:
            edges, bands, v0, inv_h = self._scan_tables
            mask = np.empty(len(uv), np.uint8)
            count, finite = kernel.scan(uv, edges, bands, v0, inv_h, mask)
            return HullScan(count, mask.view(bool) if count else None, finite)
        au, av, eu, ev, _ = self._edges
        fail = np.zeros(len(uv), bool)
        for s in range(0, len(uv), _TEST_CHUNK):
            u, v = uv[s : s + _TEST_CHUNK, 0], uv[s : s + _TEST_CHUNK, 1]
            f = fail[s : s + _TEST_CHUNK]
            for k in range(len(au)):
                f |= ~(eu[k] * (v - av[k]) - ev[k] * (u - au[k]) >= 0)
        count = int(np.count_nonzero(fail))
        return HullScan(count, fail if count else None, bool(np.isfinite(uv).all()))

    def outside_px(self, uv_px, scanned: HullScan | None = None) -> np.ndarray:
        """(N,) distance (px) of each point outside the hull; 0 inside or on it. The distance is
        computed only for the points that fail a half-plane test (``scan``, or ``scanned`` of these
        points)."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        if len(uv) == 1 and scanned is None:
            return np.array([self._outside_one(float(uv[0, 0]), float(uv[0, 1]))])
        sc = self.scan(uv) if scanned is None else scanned
        out = np.zeros(len(uv))
        if sc.mask is not None:
            idx = np.flatnonzero(sc.mask)
            for s in range(0, len(idx), _CHUNK):
                i = idx[s : s + _CHUNK]
                out[i] = _outside_distance(self.hull_px, uv[i])
        return out

    def plane_z_at(self, xy_mm=None) -> np.ndarray | float:
        """The plane's z (single height): a number for a level plane, else (N,) at the (N, 2) robot
        x, y ``xy_mm`` (required then: a tilted plane's height depends on where)."""
        if self.plane_z_mm is None:
            raise InputError("the calibrated region records no plane (a calibration of several heights)")
        if self.plane_slope is None:
            return self.plane_z_mm
        if xy_mm is None:
            raise InputError("the calibration plane is tilted: its height needs the point's x, y (mm)")
        return plane_z(self.plane_z_mm, self.plane_slope, np.asarray(xy_mm, float).reshape(-1, 2))

    def z_outside_mm(self, z_mm, xy_mm=None) -> np.ndarray:
        """(N,) how far each height is beyond what the calibration allows (mm; 0 when fine): off the
        plane at the point's x, y (``xy_mm``, (N, 2): needed for a tilted plane) by more than
        ``PLANE_TOLERANCE_MM``, or beyond the calibrated z range and its margin."""
        z = np.asarray(z_mm, float)
        if self.plane_z_mm is not None:
            return np.maximum(np.abs(z - self.plane_z_at(xy_mm)) - PLANE_TOLERANCE_MM, 0.0)
        lo, hi = self._z_range()
        return np.maximum(np.maximum(lo - self.z_margin_mm - z, z - hi - self.z_margin_mm), 0.0)

    def z_allowed_one(self, z: float) -> bool:
        """Whether one height ``z`` (a float) passes ``z_outside_mm`` without needing x, y: finite, and on
        a level plane within ``PLANE_TOLERANCE_MM`` or in the calibrated range and its margin — the same
        arithmetic on floats. False for a tilted plane (its height depends on where)."""
        if not math.isfinite(z):
            return False
        if self.plane_z_mm is not None:
            return self.plane_slope is None and not abs(z - self.plane_z_mm) - PLANE_TOLERANCE_MM > 0.0
        lo, hi = self._z_range()
        m = self.z_margin_mm
        return not (lo - m - z > 0.0 or z - hi - m > 0.0)

    def _z_range(self) -> tuple[float, float]:
        if self.z_range_mm is None:
            raise InputError("the calibrated region records neither a plane nor a z range")
        return self.z_range_mm

    # ------------------------------------------------------------ the rule
    def check(
        self, uv_px, z_mm=None, *, allow_outside: bool = False, xy_mm=None, scanned: HullScan | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(inside (N,) bool, outside_px (N,))``; refuses (``OutsideError``, naming the first point
        and how far outside) a point beyond the margin or a height beyond its tolerance, unless
        ``allow_outside``. A height off a single-height model's plane (at the point's mapped x, y,
        ``xy_mm`` (N, 2): needed when the plane is tilted) is refused even when allowed: the model
        cannot map it. ``scanned``: :meth:`scan` of these points, when the caller has it."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        if scanned is not None and scanned.mask is None:  # every point passes every half-plane test
            d, inside = np.zeros(len(uv)), np.ones(len(uv), bool)
        else:
            d = self.outside_px(uv, scanned)
            inside = d <= self.margin_px
        xy = None if xy_mm is None else np.asarray(xy_mm, float).reshape(-1, 2)
        if z_mm is not None and (len(uv) == 1 or (len(uv) > 1 and _one_value(z_mm) and xy is None)):
            # one point, or one height for all (no tilted plane): one test of it
            if float(self.z_outside_mm(np.asarray(z_mm, float).reshape(-1)[0], xy).reshape(-1)[0]) <= 0:
                z_mm = None  # at an allowed height: nothing more to check
        if z_mm is not None:
            z = np.broadcast_to(np.asarray(z_mm, float), (len(uv),))
            dz = self.z_outside_mm(z, xy)
            if self.plane_z_mm is not None and (dz > 0).any():
                i = int(np.flatnonzero(dz > 0)[0])
                zp = np.broadcast_to(self.plane_z_at(xy), (len(uv),))
                at = "" if self.plane_slope is None else f" at (x, y) = ({xy[i, 0]:g}, {xy[i, 1]:g}) mm"  # type: ignore[index]
                raise OutsideError(
                    f"z = {z[i]:g} mm is {abs(z[i] - zp[i]):.3g} mm off the calibration plane "
                    f"z = {zp[i]:g} mm{at} (tolerance {PLANE_TOLERANCE_MM:g} mm): this single-height "
                    "calibration maps only that plane; calibrate at two or more heights to map others",
                    index=i,
                    field="z",
                    label="points",
                )
            inside &= dz <= 0
            if not allow_outside and (dz > 0).any():
                i = int(np.flatnonzero(dz > 0)[0])
                lo, hi = self._z_range()
                raise OutsideError(
                    f"outside the calibrated heights: z = {z[i]:g} mm, calibrated {lo:g}..{hi:g} mm "
                    f"(margin {self.z_margin_mm:g} mm); allow_outside maps it anyway",
                    index=i,
                    field="z",
                    label="points",
                )
        if not allow_outside and not inside.all():
            i = int(np.flatnonzero(~inside)[0])
            raise OutsideError(
                f"outside the calibrated region: (u, v) = ({uv[i, 0]:g}, {uv[i, 1]:g}) px is "
                f"{d[i]:.1f} px outside the training points' hull (margin {self.margin_px:.1f} px); "
                "allow_outside maps it anyway",
                index=i,
                label="points",
            )
        return inside, d

    # ------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        out = {
            "hull_px": self.hull_px.tolist(),
            "margin_px": self.margin_px,
            "plane_z_mm": self.plane_z_mm,
            "z_range_mm": None if self.z_range_mm is None else list(self.z_range_mm),
            "z_margin_mm": self.z_margin_mm,
            "plane_tolerance_mm": PLANE_TOLERANCE_MM,
        }
        if self.plane_slope is not None:  # a level plane is written as before the plane had a slope
            out["plane_slope"] = list(self.plane_slope)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> CalibratedRegion:
        hull = np.asarray(d["hull_px"], float)
        if hull.ndim != 2 or hull.shape[1] != 2 or len(hull) < 3 or not np.isfinite(hull).all():
            raise InputError("region 'hull_px' must be three or more finite (u, v) points")
        zr = d.get("z_range_mm")
        slope = d.get("plane_slope")
        if slope is not None and (
            not isinstance(slope, list)
            or len(slope) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in slope)
        ):
            raise InputError("region 'plane_slope' must be two numbers (mm of z per mm of x, y)")
        return cls(
            hull,
            float(d["margin_px"]),
            None if d.get("plane_z_mm") is None else float(d["plane_z_mm"]),
            None if zr is None else (float(zr[0]), float(zr[1])),
            float(d.get("z_margin_mm", 0.0)),
            None if slope is None else (float(slope[0]), float(slope[1])),
        )


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise (in the u-right, v-down image, as drawn: the usual orientation of the
    cross product) convex hull of (N, 2) points, Andrew's monotone chain."""
    # the distinct points in (u, v) order, as np.unique(axis=0) gives them, on Python floats: the
    # same double arithmetic as NumPy's scalars at a tenth of the cost
    seq = sorted(set(map(tuple, np.asarray(points, float).reshape(-1, 2).tolist())))
    if len(seq) < 3:
        return np.array(seq, dtype=float).reshape(-1, 2)

    def half(seq):
        out: list[tuple[float, float]] = []
        for p in seq:
            while len(out) >= 2 and _cross(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(seq), half(seq[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=float)


def _cross(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _one_value(z) -> bool:
    """Whether ``z`` is one number: a scalar, or an array broadcast from one (every stride 0)."""
    return np.ndim(z) == 0 or (isinstance(z, np.ndarray) and not any(z.strides))


def grown_polygon(hull_px: np.ndarray, radius_px: float, *, circumscribed: bool = False) -> np.ndarray:
    """The convex polygon ``hull_px`` ⊕ a regular ``MARGIN_ARC_POINTS``-gon of radius ``radius_px``
    (counter-clockwise, as :func:`convex_hull`): inside the hull grown by the radius (every point nearer
    the hull than that) or, ``circumscribed``, around it (the polygon's edges touch the circle)."""
    a = 2 * math.pi * np.arange(MARGIN_ARC_POINTS) / MARGIN_ARC_POINTS
    r = radius_px / math.cos(math.pi / MARGIN_ARC_POINTS) if circumscribed else radius_px
    disc = r * np.column_stack([np.cos(a), np.sin(a)])
    return convex_hull((np.asarray(hull_px, float)[:, None, :] + disc[None]).reshape(-1, 2))


def _bands(edges: np.ndarray, count: int = BANDS) -> tuple[np.ndarray, float, float]:
    """The lookup of the compiled scan for the convex polygon of (K, 4) ``edges`` rows (a_u, a_v, e_u, e_v):
    ``(bands (count, 2), v0, 1/h)``, the polygon's v extent cut into ``count`` bands of height h, each with
    a u interval [lo, hi] whose rectangle — widened by ``_BAND_SLACK`` of a band in v — passes every
    edge's cross product e_u (v - a_v) - e_v (u - a_u) at its four corners by ``_PROOF_MARGIN`` × (|e_u|
    + |e_v|) × the hull's span. The cross product is affine in (u, v), so its least value on the
    rectangle is at a corner, and that margin is far above its rounding anywhere there: every pixel in a
    band's interval passes every test, as computed. A band that cannot be proven is empty (lo > hi)."""
    empty = np.tile([math.inf, -math.inf], (count, 1))
    g = _BandGeometry.of(edges, count)
    if g is None:
        return empty, 0.0, 0.0
    with np.errstate(invalid="ignore"):
        lo, hi = np.maximum(g.l0, g.l1) + g.pad, np.minimum(g.r0, g.r1) - g.pad
        ok = g.corners_inside(edges, [lo, hi, lo, hi]) & (lo <= hi) & np.isfinite(lo) & np.isfinite(hi)
    bands = np.where(ok[:, None], np.column_stack([lo, hi]), empty)
    return np.ascontiguousarray(bands), g.v0, 1.0 / g.h


@dataclass(frozen=True)
class _BandGeometry:
    """A convex polygon's v extent cut into bands of height ``h`` from ``v0``, each band's v limits
    widened by ``_BAND_SLACK`` of a band (``lo_v``, ``hi_v``), the polygon's [left, right] u there
    (``l0``, ``r0`` at ``lo_v``; ``l1``, ``r1`` at ``hi_v``), its ``span`` and the inward ``pad``."""

    v0: float
    h: float
    span: float
    lo_v: np.ndarray
    hi_v: np.ndarray
    l0: np.ndarray
    r0: np.ndarray
    l1: np.ndarray
    r1: np.ndarray

    @property
    def pad(self) -> float:
        return 1e-9 * self.span

    @classmethod
    def of(cls, edges: np.ndarray, count: int) -> _BandGeometry | None:
        av = edges[:, 1]
        v0, v1 = float(av.min()), float(av.max())
        span = float(np.ptp(edges[:, :2], axis=0).max())
        if not v1 > v0 or not span > 0:
            return None
        h = (v1 - v0) / count
        b = np.arange(count, dtype=float)
        lo_v = v0 + (b - _BAND_SLACK) * h
        hi_v = v0 + (b + 1 + _BAND_SLACK) * h
        with np.errstate(invalid="ignore"):
            (l0, r0), (l1, r1) = _cross_section(edges, lo_v), _cross_section(edges, hi_v)
        return cls(v0, h, span, lo_v, hi_v, l0, r0, l1, r1)

    def corners_inside(self, edges: np.ndarray, corner_u) -> np.ndarray:
        """(B,) whether each band's four corners — u ``corner_u`` (four (B,) arrays: at ``lo_v``,
        ``lo_v``, ``hi_v``, ``hi_v``) — pass every edge's cross product e_u (v - a_v) - e_v (u - a_u), as
        the compiled loops compute it, by ``_PROOF_MARGIN`` × (|e_u| + |e_v|) × the span: the cross
        product is affine in (u, v), so a shape that is the convex hull of its corners is inside,
        with that margin far above the products' rounding anywhere there."""
        au, av, eu, ev = edges.T
        cu = np.stack(corner_u, axis=1)[..., None]  # (B, 4, 1)
        cv = np.stack([self.lo_v, self.lo_v, self.hi_v, self.hi_v], axis=1)[..., None]
        with np.errstate(invalid="ignore"):
            c = eu * (cv - av) - ev * (cu - au)  # (B, 4, K)
            need = _PROOF_MARGIN * (np.abs(eu) + np.abs(ev)) * self.span
            return (c >= need).all(axis=(1, 2))


def _polygon_edges(polygon: np.ndarray) -> np.ndarray:
    """(K, 4) rows (a_u, a_v, e_u, e_v) of a polygon's edges, as ``CalibratedRegion._edges`` has them."""
    e = np.roll(polygon, -1, axis=0) - polygon
    return np.ascontiguousarray(np.column_stack([polygon, e]))


def _cross_section(edges: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[left, right] u of the convex polygon of (K, 4) ``edges`` rows at each v (inf, -inf outside its
    v extent)."""
    au, av, eu, ev = edges.T
    bv = av + ev
    vv = v[:, None]
    spans = (np.minimum(av, bv)[None] <= vv) & (vv <= np.maximum(av, bv)[None]) & (ev != 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(spans, au[None] + (v[:, None] - av[None]) * (eu / ev)[None], np.nan)
        return np.nanmin(u, axis=1, initial=math.inf), np.nanmax(u, axis=1, initial=-math.inf)


def _chord_bands(edges: np.ndarray, count: int) -> tuple[np.ndarray, float, float]:
    """A finer lookup than :func:`_bands` for the convex polygon of (K, 4) ``edges`` rows: ``(rows
    (count, 5), v0, 1/h)``, each band b a trapezoid, row (v_b, L, l, R, r): a pixel with
    L + l·(v - v_b) <= u <= R + r·(v - v_b) is inside. Its sides are the chords between the polygon's
    boundary points at the band's v limits (widened by ``_BAND_SLACK``), which lie inside a convex
    polygon, moved 1e-9 × its span inwards; the four corners are then proven against every edge as
    in :func:`_bands`, so the trapezoid (their convex hull) is inside with room for rounding. Only
    the thin triangles between a chord and a polygon vertex within the band are left out. A band that
    cannot be proven gets the row (0, inf, 0, -inf, 0): no pixel passes it."""
    empty = np.tile([0.0, math.inf, 0.0, -math.inf, 0.0], (count, 1))
    g = _BandGeometry.of(edges, count)
    if g is None:
        return empty, 0.0, 0.0
    with np.errstate(invalid="ignore"):
        dv = g.hi_v - g.lo_v
        L, R = g.l0 + g.pad, g.r0 - g.pad
        sl, sr = ((g.l1 + g.pad) - L) / dv, ((g.r1 - g.pad) - R) / dv
        # the corners as the lookup computes them: L + l·(v - v_b) at both v limits
        ok = g.corners_inside(edges, [L, R, L + sl * dv, R + sr * dv])
        ok &= np.isfinite(np.column_stack([L, R, sl, sr])).all(axis=1)
    rows = np.where(ok[:, None], np.column_stack([g.lo_v, L, sl, R, sr]), empty)
    return np.ascontiguousarray(rows), g.v0, 1.0 / g.h


def _outside_distance(hull: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Distance outside a convex polygon (0 inside), vectorised over the points, one edge at a time
    (no (N, K, 2) temporaries: 10x faster on the margin ring's points). Per element the arithmetic of
    the (N, K, 2) form it replaced, bit for bit: the cross product, the clipped projection, the
    squared distance, the least of them, then the root (monotone and correctly rounded, so the root of
    the least is the least of the roots)."""
    a = hull
    e = np.roll(hull, -1, axis=0) - a  # (K, 2)
    ee = np.maximum((e * e).sum(-1), 1e-300)
    u, v = uv[:, 0], uv[:, 1]
    inside = np.ones(len(uv), bool)
    least = np.full(len(uv), np.inf)
    # a pixel far out (1e200) overflows the products to ±inf (inf − inf: NaN, never inside): fmin skips
    # a NaN edge, so its distance is inf or a huge number, refused as outside, and the caller sees no
    # RuntimeWarning; for finite products fmin is minimum, bit for bit
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(len(a)):  # K edges, each vectorised over the N points
            ru, rv = u - a[k, 0], v - a[k, 1]
            inside &= e[k, 0] * rv - e[k, 1] * ru >= 0  # > 0: left of the edge (inside)
            t = np.clip((ru * e[k, 0] + rv * e[k, 1]) / ee[k], 0.0, 1.0)
            du, dv = u - (a[k, 0] + t * e[k, 0]), v - (a[k, 1] + t * e[k, 1])
            least = np.fmin(least, du**2 + dv**2)
    return np.where(inside, 0.0, np.sqrt(least))
