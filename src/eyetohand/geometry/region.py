"""The calibrated region: where a calibration has seen its training pairs, and how far a point is
outside it.

A mapping is answered only inside the convex hull of the training pixels, grown by a margin, and at
heights the calibration knows: the plane (single-height models, within ``PLANE_TOLERANCE_MM``) or
the calibrated z range grown by a margin (multi-height models). The same rule, margins and words
serve the library, the CLI, HTTP, TCP and the page (they all call :meth:`CalibratedRegion.check`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from eyetohand.core import InputError

MARGIN_FRACTION = 0.05
"""The image margin: 5 % of the larger side of the hull's bounding box (at least ``MIN_MARGIN_PX``)."""
MIN_MARGIN_PX = 5.0
PLANE_TOLERANCE_MM = 0.5
"""A z given to a single-height model may differ from its plane by this much (mm)."""
Z_MARGIN_FRACTION = 0.25
"""Multi-height models: the z range grown by 25 % of its span on each side (at least ``MIN_Z_MARGIN_MM``)."""
MIN_Z_MARGIN_MM = 5.0
_CHUNK = 1 << 16


class OutsideError(InputError):
    """A point outside the calibrated region (image or height), refused unless allowed."""


@dataclass(frozen=True)
class CalibratedRegion:
    """``hull_px`` (K, 2) counter-clockwise in image coordinates; ``margin_px``; the heights:
    ``plane_z_mm`` (single height) or ``z_range_mm`` (lo, hi) with ``z_margin_mm``."""

    hull_px: np.ndarray
    margin_px: float
    plane_z_mm: float | None = None
    z_range_mm: tuple[float, float] | None = None
    z_margin_mm: float = 0.0

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, plane_z_mm: float | None) -> CalibratedRegion:
        uv = np.asarray(uv_px, float)
        hull = convex_hull(uv)
        span = float(np.max(uv.max(axis=0) - uv.min(axis=0)))
        margin = max(MIN_MARGIN_PX, MARGIN_FRACTION * span)
        if plane_z_mm is not None:
            return cls(hull, margin, plane_z_mm=float(plane_z_mm))
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

    def _outside_one(self, u: float, v: float) -> float:
        """``outside_px`` of one point on (K,) edge columns: no (N, K, 2) temporaries."""
        au, av, eu, ev, ee = self._edges
        ru, rv = u - au, v - av
        if ((eu * rv - ev * ru) >= 0).all():
            return 0.0
        t = np.clip((ru * eu + rv * ev) / ee, 0.0, 1.0)
        du, dv = u - (au + t * eu), v - (av + t * ev)
        return float(np.sqrt((du * du + dv * dv).min()))

    def outside_px(self, uv_px) -> np.ndarray:
        """(N,) distance (px) of each point outside the hull; 0 inside or on it."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        if len(uv) == 1:
            return np.array([self._outside_one(float(uv[0, 0]), float(uv[0, 1]))])
        out = np.empty(len(uv))
        for s in range(0, len(uv), _CHUNK):
            out[s : s + _CHUNK] = _outside_distance(self.hull_px, uv[s : s + _CHUNK])
        return out

    def z_outside_mm(self, z_mm) -> np.ndarray:
        """(N,) how far each height is beyond what the calibration allows (mm; 0 when fine)."""
        z = np.asarray(z_mm, float)
        if self.plane_z_mm is not None:
            return np.maximum(np.abs(z - self.plane_z_mm) - PLANE_TOLERANCE_MM, 0.0)
        lo, hi = self._z_range()
        return np.maximum(np.maximum(lo - self.z_margin_mm - z, z - hi - self.z_margin_mm), 0.0)

    def _z_range(self) -> tuple[float, float]:
        if self.z_range_mm is None:
            raise InputError("the calibrated region records neither a plane nor a z range")
        return self.z_range_mm

    # ------------------------------------------------------------ the rule
    def check(self, uv_px, z_mm=None, *, allow_outside: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(inside (N,) bool, outside_px (N,))``; refuses (``OutsideError``, naming the first point
        and how far outside) a point beyond the margin or a height beyond its tolerance, unless
        ``allow_outside``. A height off a single-height model's plane is refused even when allowed:
        the model cannot map it."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        d = self.outside_px(uv)
        inside = d <= self.margin_px
        if z_mm is not None and len(uv) == 1:
            if float(self.z_outside_mm(np.asarray(z_mm, float).reshape(-1)[0])) <= 0:
                z_mm = None  # one point at an allowed height: nothing more to check
        if z_mm is not None:
            z = np.broadcast_to(np.asarray(z_mm, float), (len(uv),))
            dz = self.z_outside_mm(z)
            if self.plane_z_mm is not None and (dz > 0).any():
                i = int(np.flatnonzero(dz > 0)[0])
                raise OutsideError(
                    f"z = {z[i]:g} mm is {abs(z[i] - self.plane_z_mm):.3g} mm off the calibration plane "
                    f"z = {self.plane_z_mm:g} mm (tolerance {PLANE_TOLERANCE_MM:g} mm): this single-height "
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
        return {
            "hull_px": self.hull_px.tolist(),
            "margin_px": self.margin_px,
            "plane_z_mm": self.plane_z_mm,
            "z_range_mm": None if self.z_range_mm is None else list(self.z_range_mm),
            "z_margin_mm": self.z_margin_mm,
            "plane_tolerance_mm": PLANE_TOLERANCE_MM,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CalibratedRegion:
        hull = np.asarray(d["hull_px"], float)
        if hull.ndim != 2 or hull.shape[1] != 2 or len(hull) < 3 or not np.isfinite(hull).all():
            raise InputError("region 'hull_px' must be three or more finite (u, v) points")
        zr = d.get("z_range_mm")
        return cls(
            hull,
            float(d["margin_px"]),
            None if d.get("plane_z_mm") is None else float(d["plane_z_mm"]),
            None if zr is None else (float(zr[0]), float(zr[1])),
            float(d.get("z_margin_mm", 0.0)),
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


def _outside_distance(hull: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Distance outside a convex polygon (0 inside), vectorised over points × edges."""
    a = hull
    b = np.roll(hull, -1, axis=0)
    e = b - a  # (K, 2)
    rel = uv[:, None, :] - a[None]  # (N, K, 2)
    cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]  # > 0: left of the edge (inside)
    inside = (cross >= 0).all(axis=1)
    t = np.clip((rel * e[None]).sum(-1) / np.maximum((e * e).sum(-1), 1e-300)[None], 0.0, 1.0)
    closest = a[None] + t[..., None] * e[None]
    dist = np.sqrt(((uv[:, None, :] - closest) ** 2).sum(-1)).min(axis=1)
    return np.where(inside, 0.0, dist)
