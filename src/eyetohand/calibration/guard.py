"""The guard: a calibration's mapping of pixels to robot points, answered only where it was calibrated.

:func:`map_points` is the one path that checks everything and names every refusal (the calibrated
region and its margin, the height, the horizon, the angle options); :func:`map_one` (one pixel inside
the training points' hull, on plain floats) and :func:`map_many` (many pixels at one height, one
lookup: ``region.unproven``; docs/performance.md) answer the common cases faster with the same
numbers, and leave everything else to :func:`map_points`. :class:`~eyetohand.calibration.Calibration`'s
``image_to_robot`` and ``map`` delegate here.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from eyetohand.calibration.horizon import beyond_horizon
from eyetohand.calibration.mapped import Mapped, all_finite
from eyetohand.calibration.points import check_part_diameter, corrected_at_use, mix_refusal
from eyetohand.core import MAX_ABS_ANGLE_DEG, InputError, angle_refusal
from eyetohand.geometry import check_symmetry, image_angle_to_rz, local_jacobian, wrap_deg
from eyetohand.models import HeightRule, as_uv, one_point

if TYPE_CHECKING:
    from eyetohand.calibration.file import Calibration


def image_to_robot(
    cal: Calibration, uv_px, z=None, *, allow_outside: bool = False, part_diameter_mm=None
) -> np.ndarray:
    """(N, 2) pixels → (N, 3) robot mm, refused outside the calibrated region (see ``map``)."""
    # a part's diameter, or a calibration of circle centres: points.py's rule, through map's path
    # (0 for every point: the pixels as given, by the fast paths below)
    if part_diameter_mm is not None or cal.image_points.circle_diameter_mm is not None:
        d = check_part_diameter(part_diameter_mm)
        if d is None or np.any(d):
            m = map_points(cal, uv_px, z, allow_outside=allow_outside, with_sigma=False, part_diameter_mm=d)
            return m.xyz_mm
    one = map_one(cal, uv_px, z)
    if one is not None:
        return one[1]
    if not allow_outside:
        many = map_many(cal, uv_px, z)
        if many is not None:
            return many
    return _guarded(cal, uv_px, z, allow_outside=allow_outside, with_sigma=False).xyz_mm  # as given


def map_many(cal: Calibration, uv_px, z) -> np.ndarray | None:
    """(N, 3) robot mm of many pixels (a float64 (N, 2) array) at one allowed height (or none), when
    the guard passes them all; None for anything else, for :func:`map_points` to answer in its one
    path and words. One lookup proves most pixels within the margin (``region.unproven``); where the
    horizon is proven clear over the margin (``Calibration.horizon_proven_clear``) that is all they
    need, and :func:`map_points` checks the few others; without that proof the hull's own scan
    (``region.scan``) leaves :func:`map_points` the pixels outside the hull, for the margin and the
    horizon."""
    region = cal.region
    if region is None or not many_uv(uv_px):
        return None
    n = len(uv_px)
    zq = None
    if z is not None:
        zf = one_height(z)
        if zf is None or not region.z_allowed_one(zf):
            return None
        zq = np.broadcast_to(np.asarray(zf, float), (n,))  # as map passes it to the model
    uv = np.ascontiguousarray(uv_px)
    if cal.horizon_proven_clear:
        few = region.unproven(uv)
    else:  # the pixels outside the hull (margin, beyond, not finite) take map's region and horizon tests
        sc = region.scan(uv)
        few = np.empty(0, np.intp) if sc.mask is None else np.flatnonzero(sc.mask)
    if len(few):
        try:
            _guarded(cal, uv[few], None if zq is None else zq[few], with_sigma=False)
        except InputError:
            return None  # map refuses one of them: let it name the first one among all
    try:
        xyz = np.ascontiguousarray(cal.model.image_to_robot(uv, zq))
    except InputError:
        return None
    # proven within the margin where the horizon is clear: finite (Model.jacobian_det_range)
    return xyz if cal.horizon_proven_clear or all_finite(xyz) else None


def map_one(cal: Calibration, uv_px, z) -> tuple[tuple[float, float], np.ndarray] | None:
    """``((u, v), (1, 3) robot mm)`` of one pixel inside the training points' hull at an allowed height,
    on plain floats; None for anything else (many points, in the margin or beyond, a height to refuse,
    a tilted plane's z, a non-finite result): :func:`map_points` answers those, in its one path and
    words."""
    region = cal.region
    if region is None:
        return None
    pt = one_point(uv_px)
    if pt is None or region.outside_one(pt[0], pt[1]) != 0.0:
        return None
    if z is not None:
        z = one_height(z)
        if z is None or not region.z_allowed_one(z):  # not one number, not finite, a height to
            return None  # refuse, a tilted plane's
    xyz = cal.model.image_to_robot(pt, z)
    x, y, zz = xyz[0].tolist()
    if x - x != 0.0 or y - y != 0.0 or zz - zz != 0.0:  # NaN or ±inf
        return None
    return pt, xyz


def map_points(
    cal: Calibration,
    uv_px,
    z=None,
    *,
    angle_deg=None,
    allow_outside: bool = False,
    symmetry: int = 1,
    tool_rz_offset_deg: float | None = None,
    with_sigma: bool = True,
    part_diameter_mm=None,
) -> Mapped:
    """``cal.map``: pixels (and image angles) to robot points (and rz), guarded — the one path that
    checks everything and names every refusal (:meth:`Calibration.map
    <eyetohand.calibration.Calibration.map>` says what each option does)."""
    if part_diameter_mm is not None or cal.image_points.circle_diameter_mm is not None:
        guarded = functools.partial(
            _guarded,
            cal,
            angle_deg=angle_deg,
            allow_outside=allow_outside,
            symmetry=symmetry,
            tool_rz_offset_deg=tool_rz_offset_deg,
        )
        return _map_detections(cal, uv_px, z, part_diameter_mm, with_sigma, guarded)
    return _guarded(
        cal,
        uv_px,
        z,
        angle_deg=angle_deg,
        allow_outside=allow_outside,
        symmetry=symmetry,
        tool_rz_offset_deg=tool_rz_offset_deg,
        with_sigma=with_sigma,
    )


def _guarded(
    cal: Calibration,
    uv_px,
    z=None,
    *,
    angle_deg=None,
    allow_outside: bool = False,
    symmetry: int = 1,
    tool_rz_offset_deg: float | None = None,
    with_sigma: bool = True,
) -> Mapped:
    """:func:`map_points` of the pixels as given (the calibration's own kind of point)."""
    s = check_symmetry(symmetry)  # checked with or without an angle: one rule on every interface
    if tool_rz_offset_deg is not None:  # likewise
        why = angle_refusal(float(tool_rz_offset_deg))
        if why:
            raise InputError(why, field="tool_rz_offset_deg")
    if angle_deg is None:
        one = map_one(cal, uv_px, z)
        if one is not None:
            uv1, xyz1 = np.array([one[0]]), one[1]
            return Mapped(uv1, xyz1, None, _sigma(cal, uv1, xyz1, with_sigma), np.ones(1, bool), np.zeros(1))
    uv = as_uv(uv_px, check_finite=False)
    n = len(uv)
    # many points: the hull's half-plane tests and the pixels' finiteness in one pass
    scanned = cal.region.scan(uv) if cal.region is not None and n > 1 else None
    if scanned is None or not scanned.finite:
        uv = as_uv(uv)  # refuses a non-finite pixel in its words
    if z is not None:
        z = np.broadcast_to(np.asarray(z, float), (n,))
        if not np.isfinite(z).all():
            i = int(np.flatnonzero(~np.isfinite(z))[0])
            raise InputError("must be a finite number (mm)", index=i, field="z", label="points")
    if cal.region is None:
        if not allow_outside:
            raise InputError(
                "this calibration file records no calibrated region (written by eyetohand 0.1): "
                "recalibrate it with this version, or allow_outside to map without the guard"
            )
        inside, outside = np.zeros(n, bool), np.full(n, np.nan)
    else:
        xy = None  # a tilted plane's height at the points: x, y of a single-height map do not depend on z
        if z is not None and cal.region.plane_slope is not None:
            xy = cal.model.image_to_robot(uv, z)[:, :2]
        inside, outside = cal.region.check(uv, z, allow_outside=allow_outside, xy_mm=xy, scanned=scanned)
    xyz = np.ascontiguousarray(cal.model.image_to_robot(uv, z))
    bad = np.zeros(n, bool) if all_finite(xyz) else ~np.isfinite(xyz).all(axis=1)
    some_outside = cal.region is not None and (scanned is None or scanned.mask is not None)
    if not bad.any() and some_outside and (outside > 0).any():  # scanned: none is outside the hull
        bad[outside > 0] = _beyond_horizon(cal, uv[outside > 0], None if z is None else z[outside > 0])
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"(u, v) = ({uv[i, 0]:g}, {uv[i, 1]:g}) px maps to no finite robot point "
            "(on or beyond the model's horizon)",
            index=i,
            label="points",
        )
    rz = None
    if angle_deg is not None:
        ang = np.broadcast_to(np.asarray(angle_deg, float), (n,))
        bad_angle = ~(np.abs(ang) <= MAX_ABS_ANGLE_DEG)  # NaN too
        if bad_angle.any():
            i = int(np.flatnonzero(bad_angle)[0])
            raise InputError(str(angle_refusal(float(ang[i]))), index=i, field="angle", label="points")
        J = local_jacobian(cal.xy_map(z), uv)
        rz = image_angle_to_rz(J, ang)
        if tool_rz_offset_deg is not None:
            rz = rz + float(tool_rz_offset_deg) - cal.local_frame().u_axis_rz_deg
        rz = wrap_deg(rz, s)
    return Mapped(uv, xyz, rz, _sigma(cal, uv, xyz, with_sigma), inside, outside)


def _map_detections(
    cal: Calibration, uv_px, z, part_diameter_mm, with_sigma: bool, guarded: Callable[..., Mapped]
) -> Mapped:
    """:func:`map_points` with a part's diameter, or of a circle-centre calibration: the pixels
    made the points the calibration maps first (:mod:`~eyetohand.calibration.points`), or refused.
    ``guarded(uv, z, with_sigma=…)``: :func:`_guarded` with the request's other options."""
    d = check_part_diameter(part_diameter_mm)
    if d is not None and not np.any(d):  # the pixels are the points' own images: as given, no rule
        return guarded(uv_px, z, with_sigma=with_sigma)
    uv = as_uv(uv_px)
    if isinstance(d, np.ndarray) and len(d) != len(uv):
        raise InputError(
            f"{len(d)} diameters for {len(uv)} points; give one, or one per point", field="part_diameter_mm"
        )
    zz = None if z is None else np.broadcast_to(np.asarray(z, float), (len(uv),))
    if zz is not None and not np.isfinite(zz).all():  # refused by the guard, in its words
        return guarded(uv, z, with_sigma=with_sigma)
    if d is None:  # a circle-centre calibration fed detections as given: mapped only where that is harmless
        m = guarded(uv, z, with_sigma=True)
        mix_refusal(cal, uv, zz, m.xyz_mm, m.sigma_mm)
        return m if with_sigma else dataclasses.replace(m, sigma_mm=None)
    rows = np.flatnonzero(np.broadcast_to(d, (len(uv),)) > 0)  # 0: that point as given
    centres = uv.copy()
    dd = d[rows] if isinstance(d, np.ndarray) else d
    centres[rows] = corrected_at_use(cal, uv[rows], None if zz is None else zz[rows], dd, rows)
    m = guarded(centres, z, with_sigma=with_sigma)
    return dataclasses.replace(m, uv_px=uv)  # answered for the detections as given


def _sigma(cal: Calibration, uv: np.ndarray, xyz: np.ndarray, wanted: bool) -> np.ndarray | None:
    """(N,) predicted error (mm) of the mapped points, when ``wanted`` and the file has an uncertainty."""
    if not wanted or cal.uncertainty is None:
        return None
    zs = xyz[:, 2] if cal.model.height_rule is not HeightRule.COMPUTED else np.zeros(len(uv))
    sigma = cal.uncertainty.sigma_mm(cal.model, uv, zs)
    if cal.plate is not None:  # the touches' error, common to every point (plate_record.py)
        sigma = np.sqrt(sigma**2 + cal.plate.placement_variance_mm2(xyz, cal.uncertainty.n_coords))
    return sigma


def _beyond_horizon(cal: Calibration, uv: np.ndarray, z) -> np.ndarray:
    """(N,) True for points on or beyond the model's horizon (:func:`~.horizon.beyond_horizon`)."""
    return beyond_horizon(cal.xy_map(z), cal.centre_jacobian, uv)


def many_uv(uv_px) -> bool:
    """Whether ``uv_px`` is a float64 (N, 2) array of two or more pixels."""
    return (
        isinstance(uv_px, np.ndarray)
        and uv_px.dtype == np.float64
        and uv_px.ndim == 2
        and uv_px.shape[1] == 2
        and len(uv_px) > 1
    )


def one_height(z) -> float | None:
    """One height as a float: a number or a one-element numeric array; None for anything else."""
    if isinstance(z, np.ndarray) and z.size == 1 and z.dtype.kind in "fiu":
        return float(z.reshape(-1)[0])
    if isinstance(z, bool) or not isinstance(z, (float, int, np.floating, np.integer)):
        return None
    return float(z)
