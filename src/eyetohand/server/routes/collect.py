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

import threading
import time
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response

from eyetohand.server.core import ApiError
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
        """(image or None, detection or None, where it came from)."""
        from eyetohand.vision import detect_target

        col = self.collector
        if self.live and col._lock.acquire(blocking=False):
            err: str | None = None
            try:
                img, _ = self.source.grab()
            except Exception as exc:  # no pose yet (sim:), a camera that fails: say so on the image
                img, err = None, f"{type(exc).__name__}: {exc}"
            finally:
                col._lock.release()
            if img is not None:
                return img, detect_target(img, name="live", refine="edge"), "live"
            if col.last_grab is None:
                return None, None, err
        if col.last_grab is not None:
            img, det, utc = col.last_grab
            return img, det, f"last grab of the collection ({utc})"
        return None, None, "no image yet"

    def frame_png(self) -> tuple[bytes, dict]:
        import cv2

        from eyetohand.vision import annotate

        with self._lock:
            img, det, where = self._grab()
            self.frames += 1
            n = self.frames
        info = {"frame": n, "source": where, "ok": None}
        if img is None:
            out = np.full((240, 640, 3), 40, np.uint8)
            cv2.putText(
                out,
                (where or "no image")[:70],
                (10, 120),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.5,
                (0, 200, 255),
                1,
                cv2.LINE_AA,
            )
        else:
            out = annotate(img, det)
            info["ok"] = bool(det.ok)
            if det.ok:
                info.update(u=det.u, v=det.v, score=det.score, rms_px=det.rms_px, contrast=det.contrast)
                text = (
                    f"u {det.u:.2f} v {det.v:.2f}  d {det.diameter_px:.1f} px  score {det.score:.2f}  "
                    f"rms {det.rms_px:.3f} px  contrast {det.contrast:.0f}"
                )
                cv2.putText(
                    out,
                    text,
                    (8, out.shape[0] - 10),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    0.45,
                    (0, 255, 0),
                    1,
                    cv2.LINE_AA,
                )
        cv2.putText(
            out,
            f"#{n} {time.strftime('%H:%M:%S')}",
            (8, 18),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (255, 255, 0),
            1,
            cv2.LINE_AA,
        )
        return cv2.imencode(".png", out)[1].tobytes(), info


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


@router.get("/api/camera/frame.png", responses={200: {"content": {"image/png": {}}}})
def camera_frame(request: Request):
    """The camera's image now, with the detected target (ellipse, centre) and its quality drawn."""
    png, info = _view(request).frame_png()
    headers = {
        "Cache-Control": "no-store",
        "X-Frame": str(info["frame"]),
        "X-Frame-Source": str(info["source"])[:120].encode("ascii", "replace").decode(),
    }
    return Response(png, media_type="image/png", headers=headers)


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
