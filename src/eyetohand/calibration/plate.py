"""Commission a cell from images of a calibration plate and a few robot touches of its corners.

1. Each image: the plate's points (:func:`eyetohand.vision.detect_plate`) — hundreds of
   correspondences that measure the lens and the plate's plane from the image alone.
2. The camera from the plate (OpenCV's ``calibrateCamera``): one image, the principal point held at
   the image centre, square pixels, k1 and k2; several, the full camera (principal point free).
   Reported in the notes; it also tells which side of the plate the camera is on, so a mirrored
   plate (touches that are the mirror image of the plate: left-handed robot axes, x and y swapped, a
   mirrored print) is refused.
3. The touches place each image's plate in the robot frame (:mod:`.touches`: snapped, rigid fit,
   refusals in their own words).
4. The plate's points, placed, are the training pairs of an ordinary calibration: one placement
   (one height) ``homography-radial`` (homography + lens k1, k2 about the image centre), placements at
   several heights ``camera`` (pinhole + lens + pose); any other ``model`` may be asked for. The file
   keeps the plate record (:mod:`.plate_record`), which proves itself on load and adds the touches'
   error to ``sigma_mm``.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from eyetohand.calibration.file import Calibration
from eyetohand.calibration.fit import calibrate
from eyetohand.calibration.plate_record import PlateImage, PlateRecord
from eyetohand.calibration.touches import TOLERANCE_MM, Touch, load_touches
from eyetohand.core import ROBOT_UNITS, InputError, PointPairs
from eyetohand.geometry import fit_height_plane
from eyetohand.vision import PlateSpec, detect_plate

STRAIGHT_ON_DEG = 5.0
"""Below this tilt between the optical axis and the plate's normal the focal length is not measured."""


def _camera_from_plate(spec: PlateSpec, images: list[PlateImage]) -> tuple[dict, list[np.ndarray]]:
    """OpenCV's camera from the plate's images: (intrinsics and lens, camera centre (3,) in each
    image's plate frame)."""
    import cv2

    size = images[0].image_size
    obj = [spec.points_mm()[i.seen].astype(np.float32) for i in images]  # the points seen in each
    img = [i.uv_px[i.seen].astype(np.float32) for i in images]
    w, h = size
    f0 = float(max(w, h)) * 2.0
    K0 = np.array([[f0, 0, (w - 1) / 2], [0, f0, (h - 1) / 2], [0, 0, 1]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    if len(images) == 1:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, K0, np.zeros(5), flags=flags)
    centres, tilts = [], []
    for rv, tv in zip(rvecs, tvecs, strict=True):
        R, _ = cv2.Rodrigues(rv)
        centres.append(-R.T @ tv.reshape(3))
        tilts.append(float(np.degrees(np.arccos(min(1.0, abs(R[2, 2]))))))
    cam = {
        "fx_px": float(K[0, 0]),
        "fy_px": float(K[1, 1]),
        "cx_px": float(K[0, 2]),
        "cy_px": float(K[1, 2]),
        "k1": float(dist.ravel()[0]),
        "k2": float(dist.ravel()[1]),
        "reprojection_rms_px": float(rms),
        "max_tilt_deg": max(tilts),
    }
    return cam, centres


def _check_not_mirrored(record: PlateRecord, centres: list[np.ndarray]) -> None:
    """Refuse a placement that puts the camera below its plate (module docstring, step 2)."""
    for pl, c in zip(record.placements, centres, strict=True):
        cam_mm = pl.fit.apply(c.reshape(1, 3))[0]
        plate_mid = pl.fit.apply(record.spec.points_mm().mean(axis=0, keepdims=True))[0]
        below = float(plate_mid[2] - cam_mm[2])
        if below > 0:
            raise InputError(
                f"image {pl.image + 1}: the touches are the mirror image of the plate as the camera sees it "
                f"(they would put the camera {below:.0f} mm below the plate): robot axes left-handed, "
                "x and y swapped, or a mirrored print? (a camera looking up at the plate is not supported)"
            )


def touches_again(old: Calibration, spec: PlateSpec, found: list[PlateImage]) -> tuple[list[Touch], str]:
    """The touches of ``old`` (a calibration from this plate) on new images of the plate where it lay:
    each touch moved to its corner's pixel in the new image (the camera was bumped, the plate and the
    robot's readings stand), and a note of how far the corners moved. A chessboard or dot grid may be
    numbered from its other end in the new image: the numbering nearer the old pixels is taken, and
    refused when the two are not clearly apart."""
    rec = old.plate
    if rec is None:
        raise InputError("the earlier calibration was not made from a plate: it has no touches to reuse")
    if rec.spec != spec:
        raise InputError(f"the earlier calibration's plate is {rec.spec.text}, not {spec.text}")
    if len(found) != len(rec.images):
        raise InputError(
            f"the earlier calibration has {len(rec.images)} plate image(s), {len(found)} given: one new "
            "image per placement, in the same order"
        )
    out: list[Touch] = []
    moved = []
    ids = spec.ids()
    for k, (img, before, pl) in enumerate(zip(found, rec.images, rec.placements, strict=True)):
        uv = img.uv_px  # a ChArUco board seen in part: NaN where not seen, compared on the points in both
        both = img.seen & before.seen
        d = float(np.median(np.linalg.norm(uv[both] - before.uv_px[both], axis=1))) if both.any() else np.nan
        if spec.kind != "charuco":  # a board numbered from its other end
            d_rev = float(np.median(np.linalg.norm(uv[::-1] - before.uv_px, axis=1)))
            if d_rev < d:
                uv, d, d_rev = uv[::-1], d_rev, d
            if d > 0.25 * d_rev:
                raise InputError(
                    f"image {k + 1}: the plate's {spec.what} moved {d:.0f} px since the earlier calibration: "
                    "too far to tell which is which; touch the corners again"
                )
        moved.append(d)
        mine = [t for t in rec.touches if t.image == k]
        for t, c in zip(mine, pl.corners, strict=True):
            if not np.isfinite(uv[c]).all():
                raise InputError(
                    f"image {k + 1}: {t.where}'s {spec.what[:-1]} {ids[c]} is not seen in the new image: "
                    "bring that part of the plate into view, or touch the corners again"
                )
            out.append(Touch((float(uv[c, 0]), float(uv[c, 1])), t.xyz_mm, k, t.id, t.line))
    note = (
        f"touches reused from the earlier calibration by corner; the plate's {spec.what} moved "
        + ", ".join(f"{m:.2f}" for m in moved)
        + " px (median) in the image since"
    )
    return out, note


def calibrate_plate(
    images: list,
    spec: PlateSpec | str,
    touches: list[Touch] | str | os.PathLike | Calibration,
    *,
    check: PointPairs | None = None,
    model: str | None = None,
    tolerance_mm: float = TOLERANCE_MM,
    touch_noise_mm: float | None = None,
    names: list[str] | None = None,
    loo: bool = False,
    robot_units: str = "mm",
) -> Calibration:
    """A calibration from plate images (paths or arrays) and touches (a CSV path or :class:`Touch`
    list). ``model``: None chooses (module docstring). ``touch_noise_mm``: the robot's pointer noise
    σ per axis, when known; otherwise estimated from the touches' residuals (never below 0.01 mm).
    ``loo``: also the leave-one-out errors of the corners (slower; they measure the pixel fit, not
    the touches). ``touches`` may be an earlier :class:`Calibration` from this plate: after a bump of the
    camera, new images of the plate where it lay re-commission the cell with its touches
    (:func:`touches_again`). ``robot_units``: the touches' x, y, z in mm, m or in (converted to mm).
    """
    spec = PlateSpec.parse(spec) if isinstance(spec, str) else spec
    if robot_units not in ROBOT_UNITS:
        raise InputError(f"robot units {robot_units!r} not known; expected one of {', '.join(ROBOT_UNITS)}")
    if not images:
        raise InputError("no plate images given")
    if not (np.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise InputError(f"touch tolerance: expected a number of mm > 0, got {tolerance_mm!r}")
    if touch_noise_mm is not None and not (np.isfinite(touch_noise_mm) and touch_noise_mm >= 0):
        raise InputError(f"touch noise: expected a number of mm >= 0, got {touch_noise_mm!r}")
    names = names or [
        str(i) if isinstance(i, (str, os.PathLike)) else f"image {k + 1}" for k, i in enumerate(images)
    ]
    base = [Path(n).name for n in names]
    twice = sorted({b for b in base if base.count(b) > 1})
    if twice:
        raise InputError(
            f"plate images: two named {twice[0]!r} "
            f"({', '.join(n for n in names if Path(n).name == twice[0])}): the touches' image column could "
            "not tell them apart; rename one"
        )
    found = [
        PlateImage(Path(name).name, det.image_size, det.uv_px)
        for det, name in (
            (detect_plate(img, spec, name), name) for img, name in zip(images, names, strict=True)
        )
    ]
    extra_note = None
    if isinstance(touches, Calibration):
        touches, extra_note = touches_again(touches, spec, found)
    else:
        if not isinstance(touches, list):
            touches = load_touches(touches, names)
        if robot_units != "mm":
            f = ROBOT_UNITS[robot_units]
            touches = [
                replace(t, xyz_mm=(t.xyz_mm[0] * f, t.xyz_mm[1] * f, t.xyz_mm[2] * f)) for t in touches
            ]
            extra_note = f"touches: robot x, y, z read in {robot_units} and converted to mm (x {f:g})"
    cal = calibrate_detected(
        spec,
        found,
        touches,
        check=check,
        model=model,
        tolerance_mm=tolerance_mm,
        touch_noise_mm=touch_noise_mm,
        loo=loo,
    )
    return cal if extra_note is None else replace(cal, notes=(*cal.notes, extra_note))


def calibrate_detected(
    spec: PlateSpec,
    found: list[PlateImage],
    touches: list[Touch],
    *,
    check: PointPairs | None = None,
    model: str | None = None,
    tolerance_mm: float = TOLERANCE_MM,
    touch_noise_mm: float | None = None,
    loo: bool = False,
) -> Calibration:
    """:func:`calibrate_plate` from the plate's points as detected in each image (``found``)."""
    sizes = {i.image_size for i in found}
    if len(sizes) > 1:
        raise InputError(
            f"the plate images differ in size ({', '.join(f'{w}x{h}' for w, h in sorted(sizes))})"
        )
    record = PlateRecord.build(spec, found, touches, tolerance_mm=tolerance_mm, touch_noise_mm=touch_noise_mm)
    cam, centres = _camera_from_plate(spec, found)
    _check_not_mirrored(record, centres)
    pairs = record.pairs()
    if model is None:
        model = "homography-radial" if fit_height_plane(pairs.xyz_mm).one_height else "camera"
    cal = calibrate(pairs, model, check=check, image_size=found[0].image_size, loo=loo)
    notes = [
        f"plate {spec.text}: {len(found)} image(s), "
        + (
            f"{spec.n_points} {spec.what} each"
            if all(i.seen.all() for i in found)
            else f"{', '.join(str(int(i.seen.sum())) for i in found)} of its {spec.n_points} {spec.what} seen"
        ),
        "camera from the plate (OpenCV): f {:.1f} px, principal point ({:.1f}, {:.1f}) px, "
        "k1 {:.4g}, k2 {:.4g}, reprojection RMS {:.3f} px".format(
            cam["fx_px"], cam["cx_px"], cam["cy_px"], cam["k1"], cam["k2"], cam["reprojection_rms_px"]
        ),
    ]
    if cam["max_tilt_deg"] < STRAIGHT_ON_DEG:
        notes.append(
            f"the plate is seen nearly straight on (tilt {cam['max_tilt_deg']:.1f} deg): its image cannot "
            "tell the focal length from the distance, so f and k1 above are not measured (the map is); tilt "
            "the plate ~20 deg in a second image to measure the lens"
        )
    ids = spec.ids()
    for pl in record.placements:
        touched = ", ".join(ids[i] for i in pl.corners)
        notes.append(
            f"placement {pl.image + 1}: {len(pl.corners)} touches ({touched}), "
            f"rigid-fit RMS {pl.fit.rms_mm:.3f} mm, touch noise {pl.noise_mm:.3f} mm "
            + ("given" if touch_noise_mm is not None else "from the residuals")
        )
    return replace(cal, plate=record.fitted(cal.model), notes=cal.notes + tuple(notes))


__all__ = ["calibrate_detected", "calibrate_plate", "touches_again"]
