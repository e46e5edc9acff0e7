"""The workbench and positioning service: a FastAPI app over a SQLite store of calibrations.

``create_app(data_dir, token=None)`` builds the app; ``eyetohand serve`` runs it with uvicorn. Every
error is a JSON object ``{"error": "...", "field": "..."}`` with a 4xx status (5xx only for a bug).
Limits: request bodies up to :data:`MAX_BODY_BYTES` (64 MiB), image-to-robot requests up to
:data:`MAX_POINTS` (1 000 000) points; beyond either the answer is 413.
"""

from __future__ import annotations

import hmac
import os
import re
from collections import OrderedDict
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import orjson
from fastapi import FastAPI, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from .. import __version__
from ..calibration import Calibration
from ..errors import InputError
from ..evaluate import evaluate
from ..models import MODEL_CHOICES
from ..objectives import OBJECTIVES
from ..pairs import PointPairs
from ..solvers import OPTIMIZERS
from . import core
from .core import ApiError, Jobs
from .schemas import (
    MAX_BODY_BYTES,
    MAX_ITERATIONS,
    MAX_NAME,
    MAX_PAIRS,
    MAX_PARTICLES,
    MAX_POINTS,
    MAX_PSO_WORK,
    MAX_TEXT_CHARS,
    CalibrationBrief,
    CalibrationDetail,
    CalibrationOut,
    CompareRequest,
    CreateCalibration,
    ErrorOut,
    EvaluateRequest,
    FitOptions,
    JobCreated,
    JobOut,
    MapRequest,
    MapResponse,
    Meta,
    NewVersion,
    ParseRequest,
    ParseResponse,
    Rename,
    Rollback,
    SaveJob,
    StatsOut,
    VersionList,
)
from .storage import NameTaken, NotFound, Store

STATIC_DIR = Path(str(resources.files("eyetohand.server") / "static"))
PAPER_PRESET = {"model": "paper", "optimizer": "hybrid-pso", "objective": "l2", "particles": 200,
                "iterations": 150, "seed": 0}
LOOPBACK_HOSTS = ["127.0.0.1", "localhost", "::1", "[::1]"]
FAVICON = (b'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 16 16">'
           b'<circle cx="8" cy="8" r="6" fill="none" stroke="#1f5fae" stroke-width="2"/>'
           b'<circle cx="8" cy="8" r="2" fill="#1f5fae"/></svg>')

INLINE_BYTES = 64 * 1024
INLINE_POINTS = 2000

CalId = Annotated[int, PathParam(ge=1, le=2**62, description="calibration id")]
VersionQ = Annotated[int | None, Query(ge=1, le=2**62, description="version (default: current)")]
JobId = Annotated[str, PathParam(min_length=1, max_length=64, description="job id")]

ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorOut, "description": desc}
    for code, desc in ((400, "malformed request"), (404, "no such calibration, version or job"),
                       (413, "request too large"), (422, "invalid field (named in 'field')"))
}


def _error(status: int, message: str, field: str | None = None, line: int | None = None,
           errors: list | None = None) -> JSONResponse:
    body: dict[str, Any] = {"error": message, "field": field}
    if line is not None:
        body["line"] = line
    if errors:
        body["errors"] = errors
    return JSONResponse(body, status_code=status)


_TYPE_TAG = re.compile(r"[\[\-]|^(float|int|str|bool|list|dict|tuple|none|function-.*)$")


def _field_of(loc) -> str | None:
    parts = list(loc)
    if parts and parts[0] in ("body", "query", "path", "header"):
        parts = parts[1:]
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        elif isinstance(p, str) and not _TYPE_TAG.search(p):
            out += ("." if out else "") + p
    return out or ("body" if loc and loc[0] == "body" else None)


def validation_response(errors) -> JSONResponse:
    errs = list(errors)
    if not errs:
        return _error(422, "invalid request")
    first = errs[0]
    if first.get("type") == "json_invalid":
        ctx = first.get("ctx") or {}
        return _error(400, f"body: invalid JSON ({ctx.get('error', first.get('msg'))})", "body")
    listed = []
    for e in errs[:20]:
        fld = _field_of(e.get("loc", ()))
        msg = e.get("msg", "invalid")
        if e.get("type") == "missing":
            msg = "required field missing"
        listed.append({"field": fld, "error": f"{fld}: {msg}" if fld else msg})
    return _error(422, listed[0]["error"], listed[0]["field"], errors=listed if len(listed) > 1 else None)


class BodyLimit:
    """Refuse request bodies larger than ``max_bytes`` with 413 before the app sees them."""

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        too_big = (f"request body larger than the limit of {self.max_bytes} bytes "
                   f"({self.max_bytes // 2**20} MiB)")
        if length is not None:
            if not length.strip().isdigit():
                return await _send(send, _error(400, "Content-Length is not a number", "Content-Length"))
            if int(length) > self.max_bytes:
                return await _send(send, _error(413, too_big, "body"))
        body = bytearray()
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return
            body += msg.get("body", b"")
            if len(body) > self.max_bytes:
                return await _send(send, _error(413, too_big, "body"))
            if not msg.get("more_body"):
                break
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()

        return await self.app(scope, replay, send)


async def _send(send, response: JSONResponse) -> None:
    await send({"type": "http.response.start", "status": response.status_code,
                "headers": response.raw_headers})
    await send({"type": "http.response.body", "body": response.body})


class TokenGuard:
    """With a token set, every /api/ request needs ``Authorization: Bearer <token>``."""

    def __init__(self, app, token: str | None):
        self.app = app
        self.token = token.encode() if token else None

    async def __call__(self, scope, receive, send):
        if self.token and scope["type"] == "http" and scope["path"].startswith("/api/") \
                and scope["path"] != "/api/health":
            auth = dict(scope.get("headers") or []).get(b"authorization", b"")
            given = auth[7:].strip() if auth[:7].lower() == b"bearer " else b""
            if not hmac.compare_digest(given, self.token):
                return await _send(send, _error(
                    401, "missing or wrong token: send the header 'Authorization: Bearer <token>'",
                    "Authorization"))
        return await self.app(scope, receive, send)


class HostGuard:
    """Answer only requests whose Host is one of ``hosts`` (stops DNS-rebinding pages)."""

    def __init__(self, app, hosts: list[str]):
        self.app = app
        self.hosts = {h.lower() for h in hosts}

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http":
            host = dict(scope.get("headers") or []).get(b"host", b"").decode("latin-1").lower()
            name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
            if name not in self.hosts and host not in self.hosts:
                return await _send(send, _error(400, f"Host {host!r} is not served here", "Host"))
        return await self.app(scope, receive, send)


def create_app(
    data_dir: str | os.PathLike,
    token: str | None = None,
    *,
    allowed_hosts: list[str] | None = None,
    max_body_bytes: int = MAX_BODY_BYTES,
    max_pending_jobs: int = 8,
    max_pso_work: int = MAX_PSO_WORK,
) -> FastAPI:
    """The app over the database in ``data_dir``. ``token``: required on /api/ when set.
    ``allowed_hosts``: accepted Host header names (None: any). ``max_pso_work``: the largest
    particles × iterations a PSO fit may ask for (422 beyond)."""
    store = Store(data_dir)
    jobs = Jobs(max_pending=max_pending_jobs, max_pso_work=max_pso_work)
    cache: OrderedDict[tuple[int, int], Calibration] = OrderedDict()

    @asynccontextmanager
    async def lifespan(_app):
        yield
        jobs.shutdown()

    app = FastAPI(
        title="eyetohand workbench",
        version=__version__,
        description=(
            "Calibrate a fixed camera to a robot from point pairs, keep calibrations with their "
            "history, and map image points (px) to robot points (mm). Errors are "
            "`{\"error\", \"field\"}` objects. Limits: body ≤ 64 MiB, ≤ 1 000 000 points per "
            "image-to-robot request (413 beyond), ≤ 5000 pairs per fit."
        ),
        lifespan=lifespan,
        responses=ERRORS,
    )
    app.state.store = store
    app.state.jobs = jobs

    # ------------------------------------------------------------ errors
    @app.exception_handler(ApiError)
    async def _api_error(_req, exc: ApiError):
        return _error(exc.status, exc.message, exc.field, exc.line)

    @app.exception_handler(RequestValidationError)
    async def _validation(_req, exc: RequestValidationError):
        return validation_response(exc.errors())

    @app.exception_handler(InputError)
    async def _input(_req, exc: InputError):
        e = core.input_error(exc)
        return _error(e.status, e.message, e.field, e.line)

    @app.exception_handler(NotFound)
    async def _not_found(_req, exc: NotFound):
        return _error(404, str(exc).strip("'\""), "version" if "version" in str(exc) else "id")

    @app.exception_handler(NameTaken)
    async def _taken(_req, exc: NameTaken):
        return _error(409, str(exc), "name")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_req, exc: StarletteHTTPException):
        return _error(exc.status_code, str(exc.detail))

    # ------------------------------------------------------------ helpers
    def load(cal_id: int, version: int | None = None):
        ver = store.version(cal_id, version)
        key = (cal_id, ver.version)
        cal = cache.get(key)
        if cal is None:
            cal = Calibration.from_dict(ver.calibration, f"calibration {cal_id} version {ver.version}")
            cache[key] = cal
            while len(cache) > 64:
                cache.popitem(last=False)
        return ver, cal

    def pairs_of(records: list[dict] | None, label: str) -> PointPairs | None:
        if records is None:
            return None
        return core.pairs_from_records(records, source=label)

    def out(cal_id: int, version: int | None = None, detail: bool = False) -> dict:
        rec = store.get(cal_id)
        ver, cal = load(cal_id, version)
        pairs = pairs_of(ver.pairs, "pairs")
        check = pairs_of(ver.check, "check")
        excluded = ver.request.get("exclude") or []
        d = {
            "id": rec.id, "name": rec.name, "version": ver.version, "current_version": rec.current_version,
            "created_utc": rec.created_utc, "updated_utc": rec.updated_utc, "note": ver.note,
            "request": ver.request, "summary": core.summarize(cal, pairs, check, excluded),
        }
        if detail:
            d.update(pairs=ver.pairs, check=ver.check, calibration=ver.calibration)
        return d

    def records(p: PointPairs | None) -> list[dict] | None:
        return None if p is None else p.to_records()

    def save_new(fitted: core.Fitted, name: str, note: str) -> dict:
        rec = store.create(name, fitted.request, fitted.calibration.to_dict(), records(fitted.pairs),
                           records(fitted.check), note=note or "created")
        return out(rec.id)

    def save_version(cal_id: int, fitted: core.Fitted, note: str) -> dict:
        rec = store.add_version(cal_id, fitted.request, fitted.calibration.to_dict(),
                                records(fitted.pairs), records(fitted.check), note=note or "refit")
        return out(rec.id)

    def wait_fit(opts: FitOptions) -> core.Fitted:
        job = jobs.fit_job(opts)
        job.done.wait()
        if job.error:
            e = job.error
            raise ApiError(e["status"], e["error"], e.get("field"), e.get("line"))
        if job.fitted is None:
            raise ApiError(409, "the fit was cancelled")
        return job.fitted

    async def map_body(request: Request) -> MapRequest:
        ctype = request.headers.get("content-type", "")
        if ctype.split(";")[0].strip().lower() != "application/json":
            raise ApiError(415, "Content-Type must be application/json", "Content-Type")
        body = await request.body()
        try:  # small bodies inline (a thread hop costs more than the parse), large ones off the loop
            if len(body) <= INLINE_BYTES:
                req = MapRequest.model_validate_json(body)
            else:
                req = await run_in_threadpool(MapRequest.model_validate_json, body)
        except ValidationError as exc:
            errs = exc.errors(include_url=False, include_input=False)
            resp = validation_response([{**e, "loc": ("body", *e["loc"])} for e in errs])
            body_d = orjson.loads(resp.body)
            raise ApiError(resp.status_code, body_d["error"], body_d.get("field")) from None
        if len(req.points) > MAX_POINTS:
            raise ApiError(413, f"points: {len(req.points)} points, more than the {MAX_POINTS} per request "
                           "limit; split the request", "points")
        return req

    async def mapped(cal: Calibration, req: MapRequest, cal_id=None, version=None) -> Response:
        def work() -> bytes:
            pts = np.asarray(req.points, float).reshape(-1, 2)
            xyz = core.map_points(cal, pts, req.z)
            return orjson.dumps({"id": cal_id, "version": version, "units": "mm", "points": xyz},
                                option=orjson.OPT_SERIALIZE_NUMPY)

        content = work() if len(req.points) <= INLINE_POINTS else await run_in_threadpool(work)
        return Response(content, media_type="application/json")

    map_openapi = {"requestBody": {"required": True, "content": {
        "application/json": {"schema": MapRequest.model_json_schema()}}}}

    # ------------------------------------------------------------ page
    @app.get("/", include_in_schema=False)
    def index():
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-store"})

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon():
        return Response(FAVICON, media_type="image/svg+xml")

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    # ------------------------------------------------------------ API
    @app.get("/api/health", tags=["service"])
    def health() -> dict[str, str]:
        return {"status": "ok", "version": __version__}

    @app.get("/api/meta", response_model=Meta, tags=["service"])
    def meta():
        return {
            "version": __version__, "models": list(MODEL_CHOICES), "optimizers": list(OPTIMIZERS),
            "objectives": list(OBJECTIVES), "presets": {"paper": PAPER_PRESET},
            "limits": {"max_body_bytes": max_body_bytes, "max_points": MAX_POINTS, "max_pairs": MAX_PAIRS,
                       "max_text_chars": MAX_TEXT_CHARS, "max_name": MAX_NAME,
                       "max_particles": MAX_PARTICLES, "max_iterations": MAX_ITERATIONS,
                       "max_pso_work": max_pso_work},
            "auth": token is not None,
        }

    @app.post("/api/pairs/parse", response_model=ParseResponse, tags=["pairs"])
    def parse_pairs(req: ParseRequest):
        """Read CSV or JSON text of point pairs with the rules of `eyetohand calibrate`."""
        p = core.parse_text(req.text, req.source)
        return {"source": p.source, "n": len(p), "pairs": p.to_records(), "notes": list(p.notes),
                "z_levels_mm": [float(z) for z in p.z_levels_mm]}

    @app.post("/api/calibrations", response_model=CalibrationOut, status_code=201, tags=["calibrations"])
    def create_calibration(req: CreateCalibration):
        """Fit a calibration and store it as version 1 of a new named calibration."""
        if store.by_name(req.name) is not None:  # before spending a fit on it
            raise ApiError(409, f"a calibration named {req.name!r} exists already", "name")
        return save_new(wait_fit(req), req.name, "created")

    @app.get("/api/calibrations", response_model=list[CalibrationBrief], tags=["calibrations"])
    def list_calibrations():
        rows = []
        for rec, ver in store.list():
            b = ver.brief()
            rows.append({"id": rec.id, "name": rec.name, "current_version": rec.current_version,
                         "updated_utc": rec.updated_utc, **{k: b[k] for k in (
                             "model", "optimizer", "fitness_mm", "train_rms_mm", "check_rms_mm")}})
        return rows

    @app.get("/api/calibrations/{cal_id}", response_model=CalibrationDetail, tags=["calibrations"])
    def get_calibration(cal_id: CalId, version: VersionQ = None):
        return out(cal_id, version, detail=True)

    @app.patch("/api/calibrations/{cal_id}", response_model=CalibrationOut, tags=["calibrations"])
    def rename_calibration(cal_id: CalId, req: Rename):
        store.rename(cal_id, req.name)
        return out(cal_id)

    @app.delete("/api/calibrations/{cal_id}", status_code=204, tags=["calibrations"])
    def delete_calibration(cal_id: CalId):
        store.delete(cal_id)
        for key in [k for k in cache if k[0] == cal_id]:
            cache.pop(key, None)
        return Response(status_code=204)

    @app.get("/api/calibrations/{cal_id}/versions", response_model=VersionList, tags=["calibrations"])
    def list_versions(cal_id: CalId):
        rec = store.get(cal_id)
        return {"id": rec.id, "name": rec.name, "current_version": rec.current_version,
                "versions": [v.brief() for v in store.versions(cal_id)]}

    @app.post("/api/calibrations/{cal_id}/versions", response_model=CalibrationOut, status_code=201,
              tags=["calibrations"])
    def new_version(cal_id: CalId, req: NewVersion):
        """Refit (e.g. with pairs excluded) and store the result as the new current version."""
        store.get(cal_id)
        return save_version(cal_id, wait_fit(req), req.note)

    @app.post("/api/calibrations/{cal_id}/rollback", response_model=CalibrationOut, tags=["calibrations"])
    def rollback(cal_id: CalId, req: Rollback):
        """Make an earlier version current again (as a new version that copies it)."""
        store.rollback(cal_id, req.version)
        return out(cal_id)

    @app.get("/api/calibrations/{cal_id}/export", tags=["calibrations"],
             responses={200: {"description": "the calibration file (JSON), as `eyetohand apply` reads it",
                              "content": {"application/json": {}}}})
    def export(cal_id: CalId, version: VersionQ = None):
        rec = store.get(cal_id)
        ver, cal = load(cal_id, version)
        safe = re.sub(r"[^A-Za-z0-9._-]+", "_", rec.name).strip("._")[:60] or "calibration"
        return Response(cal.to_json(), media_type="application/json", headers={
            "Content-Disposition": f'attachment; filename="{safe}-v{ver.version}.json"'})

    @app.post("/api/calibrations/{cal_id}/image-to-robot", response_model=MapResponse, tags=["mapping"],
              openapi_extra=map_openapi)
    async def image_to_robot(cal_id: CalId, request: Request, version: VersionQ = None):
        """Map image points (px) to robot points (mm) with a stored calibration."""
        ver, cal = load(cal_id, version)  # an indexed SQLite read, then the in-memory cache
        req = await map_body(request)
        return await mapped(cal, req, cal_id, ver.version)

    @app.post("/api/calibrations/{cal_id}/evaluate", response_model=StatsOut, tags=["calibrations"])
    def evaluate_calibration(cal_id: CalId, req: EvaluateRequest, version: VersionQ = None):
        """Errors (mm) of a stored calibration on other pairs (e.g. new check points)."""
        _, cal = load(cal_id, version)
        return evaluate(cal, core.to_pairs(req.pairs, "pairs")).to_dict()

    # ------------------------------------------------------------ jobs
    @app.post("/api/jobs/fit", response_model=JobCreated, status_code=202, tags=["jobs"])
    def start_fit(req: FitOptions):
        """Start a fit in the background; follow it with GET /api/jobs/{id} (convergence history)."""
        job = jobs.fit_job(req)
        return {"id": job.id, "kind": job.kind, "status": job.status}

    @app.post("/api/jobs/compare", response_model=JobCreated, status_code=202, tags=["jobs"])
    def start_compare(req: CompareRequest):
        """Fit every model with every solver on the pairs and score each on the check pairs."""
        pairs = core.to_pairs(req.pairs, "pairs")
        check = core.to_pairs(req.check, "check")
        job = jobs.compare_job(pairs, check, req.seed)
        return {"id": job.id, "kind": job.kind, "status": job.status}

    @app.get("/api/jobs/{job_id}", response_model=JobOut, tags=["jobs"])
    def get_job(job_id: JobId, since: Annotated[int, Query(ge=0, le=10**6)] = 0):
        """A job's state; ``since``: send the convergence history from that index on."""
        return jobs.get(job_id).view(since)

    @app.delete("/api/jobs/{job_id}", response_model=JobOut, tags=["jobs"])
    def cancel_job(job_id: JobId):
        """Ask a queued or running job to stop (a PSO run stops after its current iteration)."""
        job = jobs.get(job_id)
        job.cancel.set()
        return job.view()

    def finished_fit(job_id: str) -> core.Fitted:
        job = jobs.get(job_id)
        if job.kind != "fit":
            raise ApiError(409, f"job {job_id} is a {job.kind} job, not a fit", "id")
        if job.status != "done" or job.fitted is None:
            raise ApiError(409, f"job {job_id} is {job.status}, it has no calibration to use", "id")
        return job.fitted

    @app.post("/api/jobs/{job_id}/save", response_model=CalibrationOut, status_code=201, tags=["jobs"])
    def save_job(job_id: JobId, req: SaveJob):
        """Store a finished fit: as a new calibration (``name``) or a new version (``calibration_id``)."""
        fitted = finished_fit(job_id)
        if (req.name is None) == (req.calibration_id is None):
            raise ApiError(422, "give either name (a new calibration) or calibration_id (a new version)",
                           "name")
        if req.name is not None:
            d = save_new(fitted, req.name, req.note)
        else:
            d = save_version(req.calibration_id, fitted, req.note)
        jobs.get(job_id).saved = {"id": d["id"], "version": d["version"], "name": d["name"]}
        return d

    @app.post("/api/jobs/{job_id}/image-to-robot", response_model=MapResponse, tags=["mapping"],
              openapi_extra=map_openapi)
    async def job_image_to_robot(job_id: JobId, request: Request):
        """Map image points (px) to robot points (mm) with a finished, unsaved fit."""
        fitted = finished_fit(job_id)
        req = await map_body(request)
        return await mapped(fitted.calibration, req)

    app.add_middleware(BodyLimit, max_bytes=max_body_bytes)
    app.add_middleware(TokenGuard, token=token)
    if allowed_hosts is not None:
        app.add_middleware(HostGuard, hosts=allowed_hosts)
    return app


__all__ = ["create_app", "MAX_BODY_BYTES", "MAX_POINTS", "LOOPBACK_HOSTS", "PAPER_PRESET"]
