"""The plant view: ``GET /api/plant`` (every calibration of the store, its version in force, last
check, and the cells that follow it) and its page ``/plant``. Runs on the thread pool."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse

from eyetohand.server.plant import plant_view
from eyetohand.server.routes import StrictJsonRoute, Svc
from eyetohand.server.routes.page import STATIC_DIR

router = APIRouter(tags=["plant"], route_class=StrictJsonRoute)


@router.get("/api/plant")
def plant(svc: Svc) -> dict:
    """``calibrations``: id, name, current_version, etag, updated_utc, last_check (the last
    verification: version, utc, passed, rms_mm, drift_significant, …; null before any), cells (the
    serve processes that follow it: cell, url, version they answer with, seen_utc, alive);
    ``other_cells``: cells that follow none of them (a calibration file, or nothing yet)."""
    return plant_view(svc.store)


@router.get("/plant", include_in_schema=False)
def plant_page():
    return FileResponse(STATIC_DIR / "plant.html", headers={"Cache-Control": "no-store"})
