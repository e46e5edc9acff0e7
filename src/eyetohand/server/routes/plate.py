"""A calibration from a plate's image(s) and a few robot touches (``eyetohand calibrate-plate``):
POST /api/plate/calibrate. The fit takes a fraction of a second, so it is answered in the request
(no job); with ``name`` the file is stored as that calibration's new version (or a new calibration),
proved on the way in like any imported file."""

from __future__ import annotations

import base64
import binascii

import numpy as np
from fastapi import APIRouter
from pydantic import Field

from eyetohand.calibration import PlateImage, calibrate_detected, touches_from_text
from eyetohand.core import InputError, PointPairs
from eyetohand.models import get_model
from eyetohand.server.core import ApiError
from eyetohand.server.routes import StrictJsonRoute, Svc
from eyetohand.server.schemas import Finite, PairIn, Strict, UploadedFile
from eyetohand.vision import PlateSpec, detect_plate

router = APIRouter(tags=["plate"], route_class=StrictJsonRoute)
MAX_PLATE_IMAGES = 50


class PlateCalibrate(Strict):
    """The plate's spec, its images (one per placement), the touches CSV ``[image,]u,v,x,y,z[,id]``."""

    plate: str = Field(max_length=100, description="KIND:COLSxROWS:PITCH_MM, e.g. chessboard:9x6:20")
    images: list[UploadedFile] = Field(
        min_length=1, max_length=MAX_PLATE_IMAGES, description="the plate's images"
    )
    touches: UploadedFile = Field(description="the touches CSV, bytes as uploaded (UTF-8)")
    check: list[PairIn] | None = Field(None, min_length=1, max_length=5000, description="check pairs")
    model: str | None = Field(
        None, max_length=40, description="default: homography-radial (one plane) or camera"
    )
    touch_noise_mm: Finite | None = Field(
        None, description="the pointer's noise per axis, mm (default: estimated)"
    )
    touch_tolerance_mm: Finite = Field(1.0, description="largest residual a touch may keep, mm")
    name: str | None = Field(None, min_length=1, max_length=200, description="store under this name")
    note: str = Field("", max_length=1000)


def _bytes(f: UploadedFile, fld: str) -> bytes:
    try:
        return base64.b64decode(f.data_base64, validate=True)
    except (binascii.Error, ValueError):
        raise ApiError(422, f"{fld}.data_base64: not base64 text", f"{fld}.data_base64") from None


def _fail(exc: InputError, fld: str) -> ApiError:
    return ApiError(422, str(exc), fld)


@router.post("/api/plate/calibrate")
def calibrate_plate_route(req: PlateCalibrate, svc: Svc):
    """Detect the plate in each image, place it by the touches, fit, and answer the calibration file
    (``calibration``) with its summary; refusals are 422 naming the field (``plate``, ``images[k]``,
    ``touches``, ``check``) in the CLI's words."""
    import cv2

    try:
        spec = PlateSpec.parse(req.plate)
    except InputError as exc:
        raise _fail(exc, "plate") from None
    if req.model is not None:
        try:
            get_model(req.model)
        except InputError as exc:
            raise _fail(exc, "model") from None
    names = [f.name for f in req.images]
    found = []
    for k, f in enumerate(req.images):
        fld = f"images[{k}]"
        if f.name in names[:k]:
            raise ApiError(422, f"{fld}.name: {f.name!r} is uploaded twice", f"{fld}.name")
        img = cv2.imdecode(np.frombuffer(_bytes(f, fld), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ApiError(422, f"{fld}: {f.name} is not an image file OpenCV can read", fld)
        try:
            det = detect_plate(img, spec, f.name)
        except InputError as exc:
            raise _fail(exc, fld) from None
        found.append(PlateImage(f.name, det.image_size, det.uv_px))
    try:
        text = _bytes(req.touches, "touches").decode("utf-8")
        touches = touches_from_text(text, req.touches.name, names)
    except UnicodeDecodeError:
        raise ApiError(422, f"touches: {req.touches.name} is not UTF-8 text", "touches") from None
    except InputError as exc:
        raise _fail(exc, "touches") from None
    check = None
    if req.check is not None:
        recs = [p.model_dump(exclude_none=True) for p in req.check]
        try:
            check = PointPairs.from_arrays(
                [[p["u"], p["v"]] for p in recs],
                [[p["x"], p["y"], p.get("z", 0.0)] for p in recs],
                [p.get("id", str(i + 1)) for i, p in enumerate(recs)],
                source="check",
            )
        except InputError as exc:
            raise _fail(exc, "check") from None
    try:
        cal = calibrate_detected(
            spec,
            found,
            touches,
            check=check,
            model=req.model,
            tolerance_mm=req.touch_tolerance_mm,
            touch_noise_mm=req.touch_noise_mm,
        )
    except InputError as exc:
        raise _fail(exc, "touches") from None
    body = cal.to_dict()
    stored = None
    if req.name is not None:
        stored, _ = svc.import_calibration(req.name, body, req.note or f"plate {spec.text}")
    return {
        "model": cal.model_name,
        "train": cal.train.to_dict(),
        "check": cal.check.to_dict() if cal.check else None,
        "notes": list(cal.notes),
        "warnings": list(cal.warnings),
        "plate": {
            "spec": spec.text,
            "placements": [
                {"image": p.image + 1, "rms_mm": p.fit.rms_mm, "noise_mm": p.noise_mm, "scale": p.fit.scale}
                for p in (cal.plate.placements if cal.plate else ())
            ],
        },
        "calibration": body,
        "stored": stored,
    }
