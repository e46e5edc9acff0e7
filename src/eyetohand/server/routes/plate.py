"""A calibration from a plate's image(s) and a few robot touches (``eyetohand calibrate-plate``), and the
workbench's steps to it:

* ``POST /api/plate/detect`` — one image: the plate's points found (pixels, ids ``r{row}c{col}``), the
  corners to touch labelled A–D (:meth:`PlateSpec.corner_labels`, as ``--annotate`` draws them), the
  grid's border and the snap radius; a plate not found is 422 in the library's words with the points
  it did see (``seen_px``), to draw on the image;
* ``POST /api/plate/snap`` — pixels (a click on the image) snapped to the detected corners by the rule
  the fit applies (:func:`eyetohand.calibration.snap`), refused in its words;
* ``GET /api/plate/grab.png`` — the server camera's image now (``serve --tcp … --camera URI``);
* ``POST /api/plate/calibrate`` — the fit. It takes a fraction of a second, so it is answered in the
  request (no job); with ``name`` the file is stored as that calibration's new version (or a new
  calibration), proved on the way in like any imported file. The answer carries the page's summary
  (``summary``, as a fit job's: statistics, vectors, the expected-accuracy line)."""

from __future__ import annotations

import base64
import binascii

import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from pydantic import Field

from eyetohand.calibration import (
    PlateImage,
    Touch,
    calibrate_detected,
    snap,
    snap_radius_px,
    touches_from_text,
)
from eyetohand.core import InputError, PointPairs
from eyetohand.models import get_model
from eyetohand.server.errors import ApiError
from eyetohand.server.routes import StrictJsonRoute, Svc
from eyetohand.server.schemas import Finite, PairIn, Strict, UploadedFile
from eyetohand.server.summaries import summarize
from eyetohand.vision import PlateDetection, PlateNotFound, PlateSpec, annotate_plate, detect_plate

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


def _spec(text: str) -> PlateSpec:
    try:
        return PlateSpec.parse(text)
    except InputError as exc:
        raise _fail(exc, "plate") from None


def _image(f: UploadedFile, fld: str) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(_bytes(f, fld), np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ApiError(422, f"{fld}: {f.name} is not an image file OpenCV can read", fld)
    return img


def _png_base64(img: np.ndarray) -> str:
    import cv2

    return base64.b64encode(cv2.imencode(".png", img)[1].tobytes()).decode()


def _pts(uv: np.ndarray) -> list[list[float] | None]:
    """Points as JSON: a point not seen (NaN: a ChArUco board seen in part) is null."""
    return [
        [float(u), float(v)] if np.isfinite(u) and np.isfinite(v) else None
        for u, v in np.asarray(uv, float).reshape(-1, 2)
    ]


class PlateDetect(Strict):
    """One image of the plate, its spec; ``annotated``: also the image as ``--annotate`` draws it."""

    plate: str = Field(max_length=100, description="KIND:COLSxROWS:PITCH_MM, e.g. chessboard:9x6:20")
    image: UploadedFile = Field(description="the plate's image (PNG, JPEG, BMP, TIFF)")
    annotated: bool = Field(False, description="answer the annotated image too (PNG, base64)")


def _border(spec: PlateSpec, n: int) -> list[int]:
    """The indices of the grid's border, A → B → C → D (row by row numbering)."""
    c, r = spec.cols, spec.rows
    top = list(range(c))
    right = [k * c + c - 1 for k in range(1, r)]
    bottom = [(r - 1) * c + k for k in range(c - 2, -1, -1)]
    left = [k * c for k in range(r - 2, 0, -1)]
    return [i for i in top + right + bottom + left if i < n]


@router.post("/api/plate/detect")
def detect_plate_route(req: PlateDetect):
    """The plate's points in one image, the corners to touch (A–D, as ``calibrate-plate --annotate``
    labels them), the grid's border (``outline_px``, A → B → C → D) and the snap radius a touch's pixel
    must keep. Not found, or found with another count: 422 naming ``image`` in the library's words,
    with the points it saw (``seen_px``) and, with ``annotated``, the image of them."""
    spec = _spec(req.plate)
    img = _image(req.image, "image")
    try:
        det = detect_plate(img, spec, req.image.name)
    except PlateNotFound as exc:
        body: dict = {"error": str(exc), "field": "image", "seen_px": _pts(exc.seen_px)}
        if req.annotated:
            body["annotated_png_base64"] = _png_base64(annotate_plate(img, spec, exc.seen_px, found=False))
        return JSONResponse(body, status_code=422)
    except InputError as exc:
        raise _fail(exc, "image") from None
    ids = spec.ids()
    spacing = det.spacing_px()
    out = {
        "plate": spec.text,
        "what": spec.what,
        "image": req.image.name,
        "image_size": list(det.image_size),
        "ids": ids,
        "uv_px": _pts(det.uv_px),
        "labels": [
            {"label": k, "index": i, "id": ids[i], "u": float(det.uv_px[i, 0]), "v": float(det.uv_px[i, 1])}
            for k, i in spec.corner_labels(det.seen).items()
        ],
        "seen": int(det.seen.sum()),
        "outline_px": [p for p in _pts(det.uv_px[_border(spec, len(ids))]) if p is not None],
        "spacing_px": spacing,
        "snap_radius_px": snap_radius_px(spacing),
    }
    if req.annotated:
        out["annotated_png_base64"] = _png_base64(annotate_plate(img, spec, det.uv_px))
    return out


class TouchPixel(Strict):
    u: Finite = Field(description="px")
    v: Finite = Field(description="px")
    id: str = Field("", max_length=40, description="the touch's name (A, B, …)")
    line: int = Field(0, ge=0, le=10**6, description="the touches CSV line it becomes")


class PlateSnap(Strict):
    """Pixels (clicks) snapped to the corners ``detect`` found, by the fit's own rule."""

    plate: str = Field(max_length=100)
    uv_px: list[tuple[Finite, Finite] | None] = Field(
        min_length=6,
        max_length=40_000,
        description="the detected points, as detect answered them (null: not seen on a board seen in part)",
    )
    image_size: tuple[int, int] = Field(description="(width, height) px, as detect answered it")
    touches: list[TouchPixel] = Field(min_length=1, max_length=1000)


@router.post("/api/plate/snap")
def snap_route(req: PlateSnap):
    """Each touch's pixel on its detected corner (index, id, pixel, distance), or 422 naming
    ``touches`` in the fit's words: no corner within the snap radius, or two touches on one corner."""
    spec = _spec(req.plate)
    uv = np.array([(np.nan, np.nan) if p is None else p for p in req.uv_px], float).reshape(-1, 2)
    if len(uv) != spec.n_points:
        raise ApiError(
            422, f"uv_px: {len(uv)} points, but plate {spec.text} has {spec.n_points} {spec.what}", "uv_px"
        )
    det = PlateDetection(spec, uv, (int(req.image_size[0]), int(req.image_size[1])), "image")
    touches = [
        Touch((t.u, t.v), (0.0, 0.0, 0.0), 0, t.id or str(k + 1), t.line) for k, t in enumerate(req.touches)
    ]
    try:
        idx = snap(touches, uv, det.spacing_px(), spec)
    except InputError as exc:
        raise _fail(exc, "touches") from None
    ids = spec.ids()
    return {
        "snap_radius_px": snap_radius_px(det.spacing_px()),
        "corners": [
            {
                "index": i,
                "id": ids[i],
                "u": float(uv[i, 0]),
                "v": float(uv[i, 1]),
                "distance_px": float(np.hypot(*(uv[i] - np.array(t.uv_px)))),
            }
            for i, t in zip(idx, touches, strict=True)
        ],
    }


@router.get("/api/plate/grab.png")
def grab_route(request: Request):
    """The server camera's image now (lossless PNG) to detect the plate in; 404 without a camera."""
    import cv2

    view = getattr(request.app.state, "collect", None)
    if view is None:
        raise ApiError(
            404,
            "no camera on this server: start it with eyetohand serve --tcp HOST:PORT --camera URI, "
            "or upload the plate's image",
        )
    img, where = view.still()
    if img is None:
        raise ApiError(409, f"the camera gave no image: {where}")
    png = cv2.imencode(".png", img)[1].tobytes()
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.post("/api/plate/calibrate")
def calibrate_plate_route(req: PlateCalibrate, svc: Svc):
    """Detect the plate in each image, place it by the touches, fit, and answer the calibration file
    (``calibration``) with its summary; refusals are 422 naming the field (``plate``, ``images[k]``,
    ``touches``, ``check``) in the CLI's words."""
    spec = _spec(req.plate)
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
        img = _image(f, fld)
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
        "summary": summarize(cal, cal.pairs, cal.check_pairs) if cal.pairs is not None else None,
        "stored": stored,
    }
