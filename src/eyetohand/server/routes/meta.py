"""Service endpoints: liveness, and the choices, presets and limits the page builds its forms from."""

from __future__ import annotations

from fastapi import APIRouter

from eyetohand._version import __version__
from eyetohand.calibration import key_id
from eyetohand.models import MODEL_CHOICES
from eyetohand.server.routes import StrictJsonRoute, Svc
from eyetohand.server.schemas import (
    MAX_ITERATIONS,
    MAX_NAME,
    MAX_PAIRS,
    MAX_PARTICLES,
    MAX_POINTS,
    MAX_TEXT_CHARS,
    Meta,
)
from eyetohand.solve import OBJECTIVES, OPTIMIZERS

PAPER_PRESET = {
    "model": "paper",
    "optimizer": "hybrid-pso",
    "objective": "l2",
    "particles": 200,
    "iterations": 150,
    "seed": 1,
}  # eyetohand demo's default seed: the same figure

router = APIRouter(tags=["service"], route_class=StrictJsonRoute)


@router.get("/api/health")
async def health(svc: Svc) -> dict:
    """Alive (always 200, no token needed); ``status`` is ``degraded`` while the store cannot be read
    (``store`` says since when and why: the cell maps with the versions in force, changes get 503)."""
    store = svc.store_state()
    return {
        "status": "degraded" if store["reachable"] is False else "ok",
        "version": __version__,
        "store": store,
    }


@router.get("/api/meta", response_model=Meta)
async def meta(svc: Svc):
    lim = svc.limits
    return {
        "version": __version__,
        "models": list(MODEL_CHOICES),
        "optimizers": list(OPTIMIZERS),
        "objectives": list(OBJECTIVES),
        "presets": {"paper": PAPER_PRESET},
        "limits": {
            "max_body_bytes": lim.max_body_bytes,
            "max_fit_body_bytes": lim.max_fit_body_bytes,
            "max_points": MAX_POINTS,
            "max_pairs": MAX_PAIRS,
            "max_text_chars": MAX_TEXT_CHARS,
            "max_name": MAX_NAME,
            "max_particles": MAX_PARTICLES,
            "max_iterations": MAX_ITERATIONS,
            "max_pso_work": lim.max_pso_work,
        },
        "auth": svc.auth,
        "signing": {
            "key_id": None if svc.sign_key is None else key_id(svc.sign_key),
            "required": svc.require_signed,
        },
    }
