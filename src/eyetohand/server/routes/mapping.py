"""Image → robot mapping (HTTP). These routes run on the event loop and never touch the database
once a calibration is cached: a cache miss is read on the thread pool; small bodies are parsed and
mapped inline (a thread hop costs more than the work), large ones off the loop."""

from __future__ import annotations

import numpy as np
import orjson
from fastapi import APIRouter, Request, Response
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from ...calibration import Calibration
from .. import core
from ..core import ApiError
from ..responses import api_error_of_validation
from ..schemas import MAX_POINTS, MapRequest, MapResponse
from . import CalId, JobId, VersionQ

INLINE_BYTES = 64 * 1024
INLINE_POINTS = 2000

router = APIRouter(tags=["mapping"])
MAP_OPENAPI = {
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": MapRequest.model_json_schema()}},
    }
}


async def map_body(request: Request) -> MapRequest:
    body = await request.body()  # the size guard has checked the length; read once, not copied
    try:
        if len(body) <= INLINE_BYTES:
            req = MapRequest.model_validate_json(body)
        else:
            req = await run_in_threadpool(MapRequest.model_validate_json, body)
    except ValidationError as exc:
        raise api_error_of_validation(exc.errors(include_url=False)) from None
    if len(req.points) > MAX_POINTS:
        raise ApiError(
            413,
            f"points: {len(req.points)} points, more than the {MAX_POINTS} per request "
            "limit; split the request",
            "points",
        )
    return req


def _work(cal: Calibration, req: MapRequest, cal_id, version) -> bytes:
    pts = np.asarray(req.points, float).reshape(-1, 2)
    m = core.map_points(
        cal,
        pts,
        req.z,
        angles=req.angles,
        symmetry=req.symmetry,
        tool_rz_offset_deg=req.tool_rz_offset_deg,
        allow_outside=req.allow_outside,
        sigma=req.sigma,
    )
    return orjson.dumps(
        {
            "id": cal_id,
            "version": version,
            "units": "mm",
            "points": m.xyz_mm,
            "rz_deg": m.rz_deg,
            "sigma_mm": m.sigma_mm,
            "inside": m.inside,
        },
        option=orjson.OPT_SERIALIZE_NUMPY,
    )


async def mapped(cal: Calibration, req: MapRequest, cal_id=None, version=None) -> Response:
    if len(req.points) <= INLINE_POINTS:
        content = _work(cal, req, cal_id, version)
    else:
        content = await run_in_threadpool(_work, cal, req, cal_id, version)
    return Response(content, media_type="application/json")


@router.post(
    "/api/calibrations/{cal_id}/image-to-robot", response_model=MapResponse, openapi_extra=MAP_OPENAPI
)
async def image_to_robot(cal_id: CalId, request: Request, version: VersionQ = None):
    """Map image points (px) to robot points (mm) with a stored calibration."""
    svc = request.app.state.service
    hit = svc.cached(cal_id, version)
    if hit is None:
        ver, cal = await run_in_threadpool(svc.calibration, cal_id, version)
        hit = (ver.version, cal)
    req = await map_body(request)
    return await mapped(hit[1], req, cal_id, hit[0])


@router.post("/api/jobs/{job_id}/image-to-robot", response_model=MapResponse, openapi_extra=MAP_OPENAPI)
async def job_image_to_robot(job_id: JobId, request: Request):
    """Map image points (px) to robot points (mm) with a finished, unsaved fit."""
    fitted = request.app.state.service.finished_fit(job_id)
    req = await map_body(request)
    return await mapped(fitted.calibration, req)
