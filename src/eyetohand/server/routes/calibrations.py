"""Stored calibrations and their versions (every route here runs on the thread pool: it reads or
writes the database)."""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, Response

from eyetohand.calibration import evaluate_pairs
from eyetohand.core import InputError
from eyetohand.reports import load_history
from eyetohand.server import figures
from eyetohand.server.errors import ApiError, input_error
from eyetohand.server.fitting import to_pairs
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
    signed = {n: sig.to_dict() for n, sig in svc.store.signatures(cal_id).items()}
    versions = [
        {
            **v.brief(),
            "signature": signed.get(v.version),
            "waiting": svc.signing.refusal(svc.store, rec.name, v),
        }
        for v in svc.store.versions(cal_id)
    ]
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
            "description": "the calibration file (JSON), as `eyetohand apply` reads it; `X-Signature` "
            "says whether it is signed, by whom and when",
            "content": {"application/json": {}},
        }
    },
)
def export(cal_id: CalId, svc: Svc, version: VersionQ = None):
    """A version as a calibration file: with its signature when a signer signed it (or it came
    signed), else unsigned — an export never signs (``X-Signature`` says which)."""
    from eyetohand.server.signatures import export_text

    rec = svc.store.get(cal_id)
    ver, cal = svc.calibration(cal_id, version)
    sig = svc.store.signature(cal_id, ver.version)
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", rec.name).strip("._")[:60] or "calibration"
    said = (
        f"unsigned: version {ver.version} is not signed (a signer signs it: POST "
        f"/api/calibrations/{cal_id}/versions/{ver.version}/sign)"
        if sig is None
        else f"signed by {sig.signer} at {sig.utc} ({sig.origin}; key {sig.key_id})"
    )
    return Response(
        export_text(ver, cal, sig),
        media_type="application/json",
        headers={
            "Content-Disposition": f'attachment; filename="{safe}-v{ver.version}.json"',
            "X-Signature": said.encode("ascii", "replace").decode(),
        },
    )


@router.post("/api/calibrations/{cal_id}/evaluate", response_model=EvaluateOut)
def evaluate_calibration(cal_id: CalId, req: EvaluateRequest, svc: Svc, version: VersionQ = None):
    """Errors (mm) of a stored calibration on other pairs (e.g. new check points), as ``eyetohand
    evaluate``: pairs outside the calibrated region or heights refused (422, counted and named by id)
    unless ``allow_outside``; a mixed-up convention named in ``warnings``."""
    _, cal = svc.calibration(cal_id, version)
    try:
        return evaluate_pairs(cal, to_pairs(req.pairs, "pairs"), allow_outside=req.allow_outside).to_dict()
    except InputError as exc:
        raise input_error(exc, "pairs") from None


@router.post("/api/calibrations/{cal_id}/verify")
def verify_calibration(cal_id: CalId, req: VerifyRequest, svc: Svc, version: VersionQ = None):
    """Freshly measured pairs against the stored calibration: per-point errors, the camera's estimated
    motion since calibration and whether it is significant, pass/fail against ``tolerance_mm``; the
    result joins the calibration's history."""
    return svc.verify(cal_id, to_pairs(req.pairs, "pairs"), req.tolerance_mm, version)


@router.get("/api/calibrations/{cal_id}/history")
def verification_history(cal_id: CalId, svc: Svc, request: Request):
    """The calibration's verifications, oldest first (rms, max, shift, rotation, scale change);
    ``collection_checks``: how many CAL CHECKs this server's collection made of it (``drift.png``
    draws both)."""
    rec = svc.store.get(cal_id)
    try:
        collected = len(_collection_checks(request, rec.name))
    except InputError:  # a damaged checks file: drift.png names its line; the verifications stand
        collected = 0
    return {
        "id": rec.id,
        "name": rec.name,
        "entries": svc.store.verifications(cal_id),
        "collection_checks": collected,
    }


# ------------------------------------------------------------------ pictures (server/figures.py)

PNG: dict[int | str, dict[str, Any]] = {200: {"content": {"image/png": {}}}}
FigWidth = Annotated[int, Query(ge=320, le=2400, description="width of the PNG in px")]
LimitQ = Annotated[
    float | None, Query(gt=0, le=1000, description="the limit line, mm (default: the recorded tolerance)")
]


def _png_response(png: bytes, headers: dict) -> Response:
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store", **headers})


@router.get(
    "/api/calibrations/{cal_id}/trust-map.png",
    responses={**PNG, 409: {"description": "the version records no region or uncertainty"}},
)
def trust_map(cal_id: CalId, svc: Svc, request: Request, version: VersionQ = None, width: FigWidth = 800):
    """Where a version can be trusted (the report's trust map): sigma_mm over the image, the calibrated
    region and its refused-beyond line, and a star where one more pair would lower the mean sigma_mm
    most — over the camera's image when the server has a camera (``serve --camera``) of the
    calibration's image size. About 2 s to draw, then kept per (calibration, version, width):
    ``X-Cache`` says ``hit`` or ``miss``; ``X-Caption`` is the report's caption (percent-encoded),
    ``X-Trust-Background`` what is under the map."""
    ver, cal = svc.calibration(cal_id, version)
    label = f"calibration {cal_id} version {ver.version}"
    camera = getattr(request.app.state, "collect", None)
    key = ("trust-map", cal_id, ver.version, width, ver.calibration.get("content_sha256"))
    png, headers, hit = figures.figure_cache(request.app.state).get(
        key, lambda: figures.trust_map_png(cal, label, width, camera)
    )
    return _png_response(png, {**headers, "X-Cache": "hit" if hit else "miss", "X-Version": str(ver.version)})


def _collection_checks(request: Request, name: str) -> list[dict]:
    """The CAL CHECK records of calibration ``name`` when this server runs a collection."""
    view = getattr(request.app.state, "collect", None)
    if view is None:
        return []
    path = view.collector.history_path(name)
    return load_history(path) if path.exists() else []


@router.get("/api/calibrations/{cal_id}/drift.png", responses={**PNG, 404: {"description": "no checks yet"}})
def drift(cal_id: CalId, svc: Svc, request: Request, width: FigWidth = 800, limit_mm: LimitQ = None):
    """The calibration's checks over time (the verifications of ``/history`` and, when this server
    runs a collection, its CAL CHECKs): each check's largest point error against the limit
    (``limit_mm``, default the tolerance the verifications record), a vertical line where a new
    version was made. ``X-Checks``: how many checks are drawn."""
    rec = svc.store.get(cal_id)
    # a verification at the store's clock (ms, as the versions' times) rather than its own (whole s):
    # a check and a version of one second stay in the order they were made
    stored = [{**e, "utc": e.get("stored_utc") or e["utc"]} for e in svc.store.verifications(cal_id)]
    entries = stored + _collection_checks(request, rec.name)
    if not entries:
        raise ApiError(
            404,
            f"calibration {rec.name!r} has no checks yet (POST /api/calibrations/{cal_id}/verify, "
            "eyetohand verify, or CAL CHECK)",
        )
    versions = [(v.created_utc, v.version) for v in svc.store.versions(cal_id)]
    try:
        png = figures.drift_png(entries, versions, width, limit_mm)
    except InputError as exc:
        raise input_error(exc, "history") from None
    return _png_response(png, {"X-Checks": str(len(entries))})
