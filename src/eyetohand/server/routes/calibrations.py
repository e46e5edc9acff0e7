"""Stored calibrations and their versions (every route here runs on the thread pool: it reads or
writes the database)."""

from __future__ import annotations

import re
from typing import Any

from fastapi import APIRouter, Response

from eyetohand.calibration import evaluate_pairs
from eyetohand.core import InputError
from eyetohand.server import core
from eyetohand.server.routes import CalId, IfMatch, StrictJsonRoute, Svc, VersionQ
from eyetohand.server.schemas import (
    CalibrationBrief,
    CalibrationDetail,
    CalibrationOut,
    CreateCalibration,
    EvaluateOut,
    EvaluateRequest,
    ImportCalibration,
    NewVersion,
    Rename,
    Rollback,
    VerifyRequest,
    VersionList,
)

router = APIRouter(tags=["calibrations"], route_class=StrictJsonRoute)
CONFLICT: dict[int | str, dict[str, Any]] = {
    412: {"description": "If-Match is not the calibration's current state (the JSON names it)"}
}


def _tagged(response: Response, out: dict) -> dict:
    response.headers["ETag"] = out["etag"]
    return out


@router.post("/api/calibrations", response_model=CalibrationOut, status_code=201)
def create_calibration(req: CreateCalibration, svc: Svc, response: Response):
    """Fit a calibration and store it as version 1 of a new named calibration."""
    return _tagged(response, svc.create(req, req.name))


@router.post(
    "/api/calibrations/import",
    response_model=CalibrationOut,
    status_code=201,
    responses={
        200: {"description": "stored as a new version of the calibration with that name"},
        422: {"description": "the file is not a valid, intact calibration (names why)"},
        **CONFLICT,
    },
)
def import_calibration(req: ImportCalibration, svc: Svc, response: Response, if_match: IfMatch = None):
    """Store a calibration file (``eyetohand calibrate -o``) as a new calibration, or as a new version
    of the calibration with that name; it must prove itself intact (hash, statistics, region, and
    its signature when the server has a key). A refused file changes nothing."""
    out, created = svc.import_calibration(req.name, req.calibration, req.note, if_match)
    response.status_code = 201 if created else 200
    return _tagged(response, out)


@router.get("/api/calibrations", response_model=list[CalibrationBrief])
def list_calibrations(svc: Svc):
    return svc.brief_list()


@router.get("/api/calibrations/{cal_id}", response_model=CalibrationDetail)
def get_calibration(cal_id: CalId, svc: Svc, response: Response, version: VersionQ = None):
    """A version (default: the current one); ``ETag`` names the calibration's current state."""
    return _tagged(response, svc.out(cal_id, version, detail=True))


@router.patch("/api/calibrations/{cal_id}", response_model=CalibrationOut, responses=CONFLICT)
def rename_calibration(cal_id: CalId, req: Rename, svc: Svc, response: Response, if_match: IfMatch = None):
    return _tagged(response, svc.rename(cal_id, req.name, if_match))


@router.delete("/api/calibrations/{cal_id}", status_code=204, responses=CONFLICT)
def delete_calibration(cal_id: CalId, svc: Svc, if_match: IfMatch = None):
    svc.delete(cal_id, if_match)
    return Response(status_code=204)


@router.get("/api/calibrations/{cal_id}/versions", response_model=VersionList)
def list_versions(cal_id: CalId, svc: Svc, response: Response):
    rec = svc.store.get(cal_id)
    versions = [v.brief() for v in svc.store.versions(cal_id)]
    current = versions[-1]["version"] if versions else rec.current_version
    if current != rec.current_version:  # a version was added between the two reads: name that one
        rec = svc.store.get(cal_id)
    response.headers["ETag"] = rec.etag
    return {
        "id": rec.id,
        "name": rec.name,
        "current_version": rec.current_version,
        "etag": rec.etag,
        "versions": versions,
    }


@router.post(
    "/api/calibrations/{cal_id}/versions", response_model=CalibrationOut, status_code=201, responses=CONFLICT
)
def new_version(cal_id: CalId, req: NewVersion, svc: Svc, response: Response, if_match: IfMatch = None):
    """Refit (e.g. with pairs excluded) and store the result as the new current version. The answer
    names the version this request created (``version``)."""
    svc.check_if_match(cal_id, if_match)  # before spending a fit; the write checks again
    return _tagged(response, svc.save_version(cal_id, svc.wait_fit(req), req.note, if_match))


@router.post("/api/calibrations/{cal_id}/rollback", response_model=CalibrationOut, responses=CONFLICT)
def rollback(cal_id: CalId, req: Rollback, svc: Svc, response: Response, if_match: IfMatch = None):
    """Make an earlier version current again (as a new version that copies it)."""
    return _tagged(response, svc.rollback(cal_id, req.version, if_match))


@router.get(
    "/api/calibrations/{cal_id}/export",
    responses={
        200: {
            "description": "the calibration file (JSON), as `eyetohand apply` reads it",
            "content": {"application/json": {}},
        }
    },
)
def export(cal_id: CalId, svc: Svc, version: VersionQ = None):
    rec = svc.store.get(cal_id)
    ver, cal = svc.calibration(cal_id, version)
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", rec.name).strip("._")[:60] or "calibration"
    return Response(
        cal.to_json(svc.sign_key),  # signed with the server's --sign-key
        media_type="application/json",
        headers={"Content-Disposition": f'attachment; filename="{safe}-v{ver.version}.json"'},
    )


@router.post("/api/calibrations/{cal_id}/evaluate", response_model=EvaluateOut)
def evaluate_calibration(cal_id: CalId, req: EvaluateRequest, svc: Svc, version: VersionQ = None):
    """Errors (mm) of a stored calibration on other pairs (e.g. new check points), as ``eyetohand
    evaluate``: pairs outside the calibrated region or heights refused (422, counted and named by id)
    unless ``allow_outside``; a mixed-up convention named in ``warnings``."""
    _, cal = svc.calibration(cal_id, version)
    try:
        return evaluate_pairs(
            cal, core.to_pairs(req.pairs, "pairs"), allow_outside=req.allow_outside
        ).to_dict()
    except InputError as exc:
        raise core.input_error(exc, "pairs") from None


@router.post("/api/calibrations/{cal_id}/verify")
def verify_calibration(cal_id: CalId, req: VerifyRequest, svc: Svc, version: VersionQ = None):
    """Freshly measured pairs against the stored calibration: per-point errors, the camera's estimated
    motion since calibration and whether it is significant, pass/fail against ``tolerance_mm``; the
    result joins the calibration's history."""
    return svc.verify(cal_id, core.to_pairs(req.pairs, "pairs"), req.tolerance_mm, version)


@router.get("/api/calibrations/{cal_id}/history")
def verification_history(cal_id: CalId, svc: Svc):
    """The calibration's verifications, oldest first (rms, max, shift, rotation, scale change)."""
    rec = svc.store.get(cal_id)
    return {"id": rec.id, "name": rec.name, "entries": svc.store.verifications(cal_id)}
