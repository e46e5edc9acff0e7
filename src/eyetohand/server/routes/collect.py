"""The workbench's collection view: the live camera with the detected target drawn, the collection's
plan, points and fit, and drop / keep for each point (issue 14 part 4).

Only there when ``eyetohand serve --tcp … --camera URI`` runs a collection (``app.state.collect``, a
:class:`CameraView`); otherwise every route here answers 404 naming the option.

The live image: when the collection is idle (no POINT/CHECK grabbing: its lock is free) a live source
is grabbed afresh; while it grabs, and for a ``folder:`` source always (a grab there would take the
robot's next image away from the collection), the view shows the collection's last grab. A grab never
changes what the collection records: the ``sim:`` camera renders each POINT from its pose again.
"""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response

from eyetohand.server.errors import ApiError
from eyetohand.server.routes import StrictJsonRoute
from eyetohand.server.routes.page import STATIC_DIR

router = APIRouter(tags=["collection"], route_class=StrictJsonRoute)
PointN = Annotated[int, PathParam(ge=1, le=10**6, description="point number (n of CAL POINT's reply)")]


class CameraView:
    """The live camera and the collection behind the routes (thread-safe)."""

    def __init__(self, collector, source):
        from eyetohand.vision import FolderSource

        self.collector = collector
        self.source = source
        self.live = not isinstance(source, FolderSource)
        self.frames = 0
        self._lock = threading.Lock()

    def _grab(self):
        """(image or None, detection or None, where it came from or what the operator should do)."""
        from eyetohand.vision import detect_target

        col = self.collector
        with col.camera_if_idle() if self.live else contextlib.nullcontext(False) as idle:
            img, err = None, None
            if idle:
                try:
                    img, _ = self.source.grab()
                except Exception as exc:  # no pose yet (sim:), a camera that fails: say so on the image
                    err = self._grab_failed(exc)
        if idle:
            if img is not None:
                return img, detect_target(img, name="live", refine="edge"), "live"
            if col.last_grab is None:
                return None, None, err
        if col.last_grab is not None:
            img, det, utc = col.last_grab
            return img, det, f"last grab of the collection ({utc})"
        return None, None, "no image yet"

    def _grab_failed(self, exc: Exception) -> str:
        """What the view says when the camera gave no image: for a camera the robot's pose drives (the
        ``sim:`` camera renders the target where the robot holds it) before the robot has moved, what
        to do; else the camera's own error. (Called holding the collection's lock: reads no status.)"""
        if hasattr(self.source, "set_robot_pose") and self.collector.last_grab is None:
            return (
                "no image yet: the simulated camera shows the target once the robot has moved "
                "(CAL NEXT, then the first POINT)"
            )
        return f"camera error: {type(exc).__name__}: {exc}"

    def still(self) -> tuple[np.ndarray | None, str]:
        """The camera's image now, as the view would show it but undrawn (the trust map's background):
        ``(image or None, where it came from or why there is none)``. Not counted as a view frame."""
        with self._lock:
            img, _, where = self._grab()
        return img, where or "no image"

    def frame(self, width: int | None = None, fmt: str = "png") -> tuple[bytes, dict]:
        """The annotated image now: full resolution and lossless (``fmt`` "png", ``width`` None), or
        as a JPEG ``width`` px wide (never enlarged) with the overlay drawn at that size."""
        import cv2

        with self._lock:
            img, det, where = self._grab()
            self.frames += 1
            n = self.frames
        info: dict = {"frame": n, "source": where, "ok": None, "size": None}
        if img is None:
            out = _message_image(where or "no image", width or 640)
        else:
            info["size"] = f"{img.shape[1]}x{img.shape[0]}"
            info["ok"] = bool(det.ok)
            if det.ok:
                info.update(u=det.u, v=det.v, score=det.score, rms_px=det.rms_px, contrast=det.contrast)
            out = _annotated(img, det, width)
        k = out.shape[1] / 640
        _text(out, f"#{n} {time.strftime('%H:%M:%S')}", (8, int(18 * max(k, 1))), (255, 255, 0), max(k, 1))
        if fmt == "jpg":
            return cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1].tobytes(), info
        return cv2.imencode(".png", out)[1].tobytes(), info


JPEG_QUALITY = 80


def _text(out: np.ndarray, text: str, org: tuple[int, int], colour, scale: float = 1.0) -> None:
    import cv2

    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45 * scale, colour, 1, cv2.LINE_AA)


def _message_image(message: str, width: int) -> np.ndarray:
    """A dark image with ``message`` word-wrapped on it (never cut off)."""
    import textwrap

    width = max(320, min(width, 1280))
    per_line = max(20, int(width / 8.5))
    lines = textwrap.wrap(message, per_line) or [""]
    out = np.full((max(240, 60 + 22 * len(lines)), width, 3), 40, np.uint8)
    for i, line in enumerate(lines):
        _text(out, line, (10, 60 + 22 * i), (0, 200, 255), 1.1)
    return out


def _annotated(img: np.ndarray, det, width: int | None) -> np.ndarray:
    """The image with the detection drawn: at full resolution (``annotate``, as the CLI draws it), or
    scaled to ``width`` px first and drawn at that size (lines stay visible on a small view)."""
    import cv2

    from eyetohand.vision import annotate

    h, w = img.shape[:2]
    if width is None or width >= w:
        out = annotate(img, det)
        k = 1.0
    else:
        k = width / w
        small = cv2.resize(img, (width, max(1, round(h * k))), interpolation=cv2.INTER_AREA)
        out = _draw_small(small, det, k)
    if det.ok:
        text = (
            f"u {det.u:.2f} v {det.v:.2f}  d {det.diameter_px:.1f} px  score {det.score:.2f}  "
            f"rms {det.rms_px:.3f} px  contrast {det.contrast:.0f}"
        )
        _text(out, text, (8, out.shape[0] - 10), (0, 255, 0), max(1.0, out.shape[1] / 1400))
    return out


def _draw_small(small: np.ndarray, det, k: float) -> np.ndarray:
    """The detection (ellipse green, centre cross red) on an image scaled by ``k``, 2 px lines."""
    import cv2

    out = small if small.ndim == 3 else cv2.cvtColor(small, cv2.COLOR_GRAY2BGR)
    if out.dtype != np.uint8:
        out = cv2.normalize(out, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if not det.ok:
        _text(out, (det.reason or "not found")[:80], (10, 40), (0, 0, 255), 1.2)
        return out
    S = 16
    (cx, cy), (A, B), ang = det.ellipse
    c = (int(round(cx * k * S)), int(round(cy * k * S)))
    axes = (int(round(A / 2 * k * S)), int(round(B / 2 * k * S)))
    cv2.ellipse(out, c, axes, ang, 0, 360, (0, 255, 0), 2, cv2.LINE_AA, 4)
    arm = int(max(6, 0.15 * A * k) * S)
    cv2.line(out, (c[0] - arm, c[1]), (c[0] + arm, c[1]), (0, 0, 255), 2, cv2.LINE_AA, 4)
    cv2.line(out, (c[0], c[1] - arm), (c[0], c[1] + arm), (0, 0, 255), 2, cv2.LINE_AA, 4)
    return out


def _view(request: Request) -> CameraView:
    view = getattr(request.app.state, "collect", None)
    if view is None:
        raise ApiError(
            404, "no collection on this server: start it with eyetohand serve --tcp HOST:PORT --camera URI"
        )
    return view


@router.get("/collect", include_in_schema=False)
def collect_page():
    return FileResponse(STATIC_DIR / "collect.html", headers={"Cache-Control": "no-store"})


def _frame_headers(info: dict) -> dict:
    headers = {
        "Cache-Control": "no-store",
        "X-Frame": str(info["frame"]),
        "X-Frame-Source": str(info["source"])[:200].encode("ascii", "replace").decode(),
    }
    if info["size"]:
        headers["X-Frame-Size"] = info["size"]
    return headers


@router.get("/api/camera/frame.png", responses={200: {"content": {"image/png": {}}}})
def camera_frame(request: Request):
    """The camera's image now at full resolution, lossless, with the detected target (ellipse, centre)
    and its quality drawn (several MB for a 5 MP camera: the page asks for ``frame.jpg``)."""
    png, info = _view(request).frame(None, "png")
    return Response(png, media_type="image/png", headers=_frame_headers(info))


Width = Annotated[
    int, Query(ge=64, le=8192, description="width of the view in px (the image is never enlarged)")
]


@router.get("/api/camera/frame.jpg", responses={200: {"content": {"image/jpeg": {}}}})
def camera_frame_jpeg(request: Request, width: Width = 960):
    """The camera's image now as a JPEG sized to the view (``width`` px), the detection drawn at
    that size: what the collection page shows once a second."""
    jpg, info = _view(request).frame(width, "jpg")
    return Response(jpg, media_type="image/jpeg", headers=_frame_headers(info))


@router.get("/api/collect/status")
def collect_status(request: Request) -> dict:
    """The collection: plan poses (done / failed), points with their detections, the last END's fit,
    and the verification history of the calibration."""
    view = _view(request)
    st = view.collector.status()
    name = st.get("name") or st.get("calibration")
    st["checks"] = view.collector.history(name)[-20:] if name else []
    st["camera"] = getattr(view.source, "uri", "")
    st["live"] = view.live
    st["frames"] = view.frames
    return st


@router.get("/api/collect/plate.jpg", responses={200: {"content": {"image/jpeg": {}}}})
def plate_image(request: Request, width: Width = 960):
    """The open plate session's image (``CAL PLATE``, its latest placement) as the collection kept it,
    as a JPEG ``width`` px wide (never enlarged); the status's ``corners`` are in its pixels. 404 when
    no plate session is open."""
    import cv2

    view = _view(request)
    st = view.collector.status()
    if st.get("kind") != "plate":
        raise ApiError(404, "no plate session: the robot opens one with CAL PLATE <spec>")
    root = Path(view.collector.dir).resolve()
    path = (root / st["image_file"]).resolve()
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_relative_to(root) else None
    if img is None:
        raise ApiError(404, f"the plate session's image {st['image_file']} cannot be read")
    if width < img.shape[1]:
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1].tobytes()
    return Response(jpg, media_type="image/jpeg", headers={"Cache-Control": "no-store"})


def _drop(request: Request, n: int, keep: bool) -> dict:
    from eyetohand.cell import CommandError

    try:
        p = _view(request).collector.drop(n, keep=keep)
    except CommandError as exc:
        status = 404 if str(exc).startswith("no point") else 409
        raise ApiError(status, str(exc), "n") from None
    return {"n": n, "dropped": not keep, "xyz_mm": p["xyz_mm"]}


@router.post("/api/collect/points/{n}/drop")
def drop_point(request: Request, n: PointN) -> dict:
    """Leave point n out of the fit (its planned pose is offered again by CAL NEXT)."""
    return _drop(request, n, keep=False)


@router.post("/api/collect/points/{n}/keep")
def keep_point(request: Request, n: PointN) -> dict:
    """Take a dropped point back into the fit."""
    return _drop(request, n, keep=True)
