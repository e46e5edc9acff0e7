"""The circle target's perspective bias, corrected: a detected ellipse centre moved to where the
circle's centre projects.

On a view tilted against the target's plane the centre of a circle's image (an ellipse) is not the
image of the circle's centre; the detector finds the former. The robot's plane is metric, so a fitted
map's own ``robot_to_image`` knows how a circle of known diameter at a plane point projects (lens
included, for the lens models): the bias it predicts there — the centre of the ellipse through the
circle's projected outline minus the projected centre — is subtracted (a fixed point: the bias varies
slowly over the view). No camera model is needed. Measured in docs/limit.md ("The circle's perspective
bias", ``benchmarks/bias.py``).

:func:`corrected_centres_px` corrects pixels with a calibration's maps; :func:`fit_corrected` is the
fit loop (fit, correct the training pixels with the fit's own maps, refit; twice) that
:func:`~eyetohand.calibration.calibrate_request` runs when ``FitRequest.target_diameter_mm`` is set.
"""

from __future__ import annotations

import dataclasses
import math
from typing import overload

import numpy as np

from eyetohand.core import InputError, PointPairs

OUTLINE_POINTS = 64
"""Projected outline points per circle. The conic's centre through them is the closed form's (the
centre of H⁻ᵀ C H⁻¹) to 7e-13 px on bias.py's cell (20°/30° tilt, 6/20 mm, 9×9 over the view)."""
ITERATIONS = 2
"""Fixed-point steps of :func:`projected_centres_px`: the bias varies slowly, so one leaves 4e-5 px,
two 5e-9 px (bias.py's cell at 30°, 20 mm, the true camera's maps)."""
FIT_PASSES = 2
"""Correct-and-refit passes of :func:`fit_corrected` after the first fit ("fitted" in bias.py)."""


def check_target_diameter(value) -> float | None:
    """The circle target's diameter (mm) as a float: a finite number above 0, or None."""
    if value is None:
        return None
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok or not math.isfinite(float(value)) or float(value) <= 0:
        got = f"{float(value):g}" if ok else repr(value)
        raise InputError(f"target_diameter_mm must be a finite number of mm above 0, got {got}")
    return float(value)


def ellipse_centres_px(robot_to_image, centre_mm, diameter_mm, n: int = OUTLINE_POINTS) -> np.ndarray:
    """(N, 2) centres of the image ellipses of circles of ``diameter_mm`` centred at ``centre_mm``
    (N, 3) parallel to the robot's x-y plane, through ``robot_to_image`` ((M, 3) mm → (M, 2) px; any
    map, lens included): the least-squares conic through ``n`` projected outline points of each
    circle, all circles' outlines mapped in one call and fitted in one batched eigen-decomposition
    of their 6×6 scatter matrices (the design's least singular vector: the same centres as a batched
    SVD to 2e-13 px on bias.py's cell, in a third of the time). ``diameter_mm``: one for all, or (N,)
    one per circle."""
    c = np.asarray(centre_mm, float).reshape(-1, 3)
    th = 2 * np.pi * np.arange(n) / n
    r = (
        np.asarray(diameter_mm, float).reshape(-1, 1) / 2 if np.ndim(diameter_mm) else diameter_mm / 2
    )  # or one each
    ring = np.empty((len(c), n, 3))
    ring[..., 0] = c[:, None, 0] + r * np.cos(th)
    ring[..., 1] = c[:, None, 1] + r * np.sin(th)
    ring[..., 2] = c[:, None, 2]
    b = np.asarray(robot_to_image(ring.reshape(-1, 3)), float).reshape(len(c), n, 2)
    m = b.mean(axis=1, keepdims=True)
    s = np.sqrt(((b - m) ** 2).sum(axis=-1).mean(axis=1))[:, None]  # Hartley-style scale per circle
    x, y = ((b - m) / s[..., None]).transpose(2, 0, 1)
    design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)  # (N, n, 6)
    scatter = np.matmul(design.transpose(0, 2, 1), design)  # (N, 6, 6): its least eigenvector is the conic
    a, bb, cc, d, e, _ = np.linalg.eigh(scatter)[1][:, :, 0].T
    hess = np.stack([np.stack([2 * a, bb], -1), np.stack([bb, 2 * cc], -1)], -2)
    centre_n = np.linalg.solve(hess, np.stack([-d, -e], -1)[..., None])[..., 0]
    return m[:, 0] + s * centre_n


def projected_centres_px(
    uv_px, diameter_mm, z_mm, image_to_robot, robot_to_image, iterations: int = ITERATIONS
) -> np.ndarray:
    """Detected ellipse centres ``uv_px`` (N, 2) moved to where the circles' centres project: the
    bias (ellipse centre − projected centre) that ``robot_to_image`` predicts for a circle of
    ``diameter_mm`` at the plane point ``image_to_robot(uv, z_mm)`` finds under the pixel, subtracted.
    ``image_to_robot(uv (N, 2), z) → (N, 3)``, ``robot_to_image(xyz (M, 3)) → (M, 2)``: a fitted
    model's or a camera's. For a lens-free map with plane→image homography H this is the closed form:
    the ellipse's centre is that of the conic H⁻ᵀ C H⁻¹, the circle's centre's image H·(x, y, 1)."""
    uv0 = np.asarray(uv_px, float).reshape(-1, 2)
    uv = uv0.copy()
    for _ in range(iterations):
        xyz = np.asarray(image_to_robot(uv, z_mm), float)
        bias = ellipse_centres_px(robot_to_image, xyz, diameter_mm) - np.asarray(robot_to_image(xyz), float)
        uv = uv0 - bias
    return uv


def corrected_centres_px(cal, uv_px, diameter_mm: float, z_mm=None) -> np.ndarray:
    """:func:`projected_centres_px` with a fitted calibration's own maps (its model's, unguarded: a
    training pixel may lie on the region's edge): the pixels ``uv_px`` (N, 2) where circles of
    ``diameter_mm`` at height ``z_mm`` (None: the calibration's plane; a number, or one per point)
    were detected, moved to where their centres project. Refused with the point named where the map
    gives no finite answer (a circle across the camera's horizon)."""
    diameter = check_target_diameter(diameter_mm)
    if diameter is None:
        raise InputError("target_diameter_mm must be given to correct circle centres")
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    model = cal.model
    with np.errstate(all="ignore"):
        out = projected_centres_px(uv, diameter, z_mm, model.image_to_robot, model.robot_to_image)
    bad = np.flatnonzero(~np.isfinite(out).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"point {i} ({uv[i, 0]:g}, {uv[i, 1]:g}) px: the map gives no finite image of a "
            f"{diameter:g} mm circle there, so its centre cannot be corrected"
        )
    return out


def with_centres(pairs: PointPairs, uv_px: np.ndarray) -> PointPairs:
    """``pairs`` with their pixels replaced (ids, robot positions, angles and notes kept)."""
    return dataclasses.replace(pairs, uv_px=uv_px)


def fit_corrected(
    fit, pairs: PointPairs, check: PointPairs | None, diameter_mm: float, passes: int = FIT_PASSES
):
    """Fit, then ``passes`` times: correct the detected centres of ``pairs`` (and ``check``, the same
    target) with the last fit's maps and refit. ``fit(pairs, check, last: bool) → Calibration``
    (``last``: the fit that is returned, the others may skip what only the result needs). Returns
    the last calibration, its fit record extended by the correction: ``target_diameter_mm``,
    ``centre_correction_passes``, the RMS and largest shift of the training pixels (px) and
    ``detected_sha256``, the SHA-256 of the pairs as detected (the stored pairs are the corrected)."""
    diameter = check_target_diameter(diameter_mm)
    if diameter is None:
        raise InputError("target_diameter_mm must be given to correct circle centres")
    cal = fit(pairs, check, passes == 0)
    train_uv = pairs.uv_px
    for k in range(passes):
        train_uv = corrected_centres_px(cal, pairs.uv_px, diameter, pairs.xyz_mm[:, 2])
        moved = None
        if check is not None:
            moved = with_centres(check, corrected_centres_px(cal, check.uv_px, diameter, check.xyz_mm[:, 2]))
        cal = fit(with_centres(pairs, train_uv), moved, k == passes - 1)
    shift = np.sqrt(((train_uv - pairs.uv_px) ** 2).sum(axis=1))
    record = {
        "target_diameter_mm": diameter,
        "centre_correction_passes": passes,
        "centre_shift_px_rms": float(np.sqrt(np.mean(shift**2))),
        "centre_shift_px_max": float(shift.max()),
        "detected_sha256": pairs.sha256(),
    }
    note = (
        f"centres corrected for a {diameter:g} mm circle's perspective bias (RMS shift "
        f"{record['centre_shift_px_rms']:.3g} px): this calibration maps where a circle's centre "
        "projects; correct a detection of the same target before mapping it: give the part's diameter "
        "at use (part_diameter_mm; apply --part-diameter-mm, TCP d=)"
    )
    fit_info = dataclasses.replace(cal.fit, extra={**cal.fit.extra, **record})
    return dataclasses.replace(cal, fit=fit_info, notes=(*cal.notes, note))


def recorded_diameter_mm(cal) -> float | None:
    """The target diameter (mm) a calibration's centres were corrected for (its fit record's
    ``target_diameter_mm``), or None: fitted on the centres as detected."""
    value = cal.fit.extra.get("target_diameter_mm")
    return None if value is None else check_target_diameter(value)


@overload
def as_fitted(cal, pairs: PointPairs) -> PointPairs: ...
@overload
def as_fitted(cal, pairs: None) -> None: ...
def as_fitted(cal, pairs: PointPairs | None) -> PointPairs | None:
    """``pairs`` as detected, in the form ``cal`` was fitted on: their centres corrected with its
    maps when it records a target diameter (:func:`recorded_diameter_mm`), else unchanged — so that
    their residuals are comparable with its statistics. The very pairs it was fitted on (their
    SHA-256 its ``detected_sha256``) become its stored training pairs, bit for bit; its stored
    training and check pairs are returned as they are."""
    diameter = recorded_diameter_mm(cal)
    if pairs is None or diameter is None:
        return pairs
    stored = [p.sha256() for p in (cal.pairs, cal.check_pairs) if p is not None]
    if pairs.sha256() in (cal.data_sha256, *stored):  # the calibration's own: already as fitted
        return pairs
    if cal.pairs is not None and pairs.sha256() == cal.fit.extra.get("detected_sha256"):
        return cal.pairs
    return with_centres(pairs, corrected_centres_px(cal, pairs.uv_px, diameter, pairs.xyz_mm[:, 2]))
