"""The workbench and positioning service: a FastAPI app over a SQLite store of calibrations.

``create_app(data_dir, token=None)`` builds the app: routers by resource (``routes/``) over one
:class:`~eyetohand.server.service.Service` on ``app.state.service`` (store, calibration cache, job
queue); ``eyetohand serve`` runs it with uvicorn. Every error is a JSON object
``{"error": "...", "field": "..."}`` with a 4xx status (503 / 507 when the database is busy or
full; 5xx otherwise only for a bug).
Limits, checked from ``Content-Length`` (or while the body streams in) before anything is parsed:
mapping bodies up to :data:`MAX_BODY_BYTES` (64 MiB) and :data:`MAX_POINTS` (1 000 000) points;
fit and other bodies up to :data:`MAX_FIT_BODY_BYTES`; beyond either the answer is 413.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI

from eyetohand._version import __version__
from eyetohand.core import AuthBackoff, TokenTable
from eyetohand.server.jobs import Jobs
from eyetohand.server.middleware import BodyLimit, DatabaseGuard, HostGuard, SameOrigin, TokenGuard
from eyetohand.server.plant import CellBeat, beat
from eyetohand.server.responses import install_handlers
from eyetohand.server.routes import (
    audit,
    calibrations,
    collect,
    diff,
    images,
    jobs,
    mapping,
    meta,
    page,
    pairs,
    plant,
    plate,
    signing,
)
from eyetohand.server.routes.meta import PAPER_PRESET
from eyetohand.server.schemas import (
    MAX_BODY_BYTES,
    MAX_FIT_BODY_BYTES,
    MAX_PARSE_BODY_BYTES,
    MAX_POINTS,
    MAX_PSO_WORK,
    ErrorOut,
)
from eyetohand.server.service import Limits, Service
from eyetohand.server.storage import WAIT_S
from eyetohand.server.stores import StoreRef, open_store

LOOPBACK_HOSTS = ["127.0.0.1", "localhost", "::1", "[::1]"]

ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorOut, "description": desc}
    for code, desc in (
        (400, "malformed request"),
        (404, "no such calibration, version or job"),
        (413, "request too large"),
        (403, "a cross-site request (Origin not this server, or a POST neither JSON nor X-Requested-With)"),
        (412, "If-Match is not the calibration's current state"),
        (415, "body not sent as application/json"),
        (422, "invalid field (named in 'field')"),
        (503, "database busy (another writer; see Retry-After) or unavailable"),
    )
}


def create_app(
    data_dir: str | os.PathLike | StoreRef,
    token: str | Mapping[str, str] | TokenTable | None = None,
    *,
    allowed_hosts: list[str] | None = None,
    max_body_bytes: int = MAX_BODY_BYTES,
    max_fit_body_bytes: int = MAX_FIT_BODY_BYTES,
    max_pending_jobs: int = 8,
    max_pso_work: int = MAX_PSO_WORK,
    db_wait_s: float = WAIT_S,
    create_db: bool = True,
    sign_key: bytes | None = None,
    require_signed: bool = False,
    heartbeat: Callable[[], CellBeat] | None = None,
    auth_backoff: AuthBackoff | None = None,
) -> FastAPI:
    """The app over the database in ``data_dir`` (or the store a ``sqlite:PATH`` or
    ``postgresql://…`` reference names: docs/store.md). ``token``: required on /api/ when set; a
    mapping of names to tokens accepts each, and audits a change under its token's name; a
    :class:`~eyetohand.core.TokenTable` adds each token's role (what it may do: middleware.required_role).
    ``allowed_hosts``: accepted Host header names (None: any). ``max_pso_work``: the largest
    particles × iterations a PSO fit may ask for (422 beyond). ``db_wait_s``: how long a write
    waits for another connection's lock before answering 503. ``create_db``: create the database
    when ``data_dir`` has none (``serve`` passes True only at a first start); once open, a database
    deleted or replaced under the app answers 503 and is never recreated. ``sign_key``: checks
    signed calibration files on import and signs exports; ``require_signed``: imports must be signed
    with it. ``heartbeat``: what this server is and follows, registered in the store every few
    seconds (``serve`` passes it; the plant view lists it). ``auth_backoff``: failed tokens per
    address (``serve`` shares one with TCP and OPC UA)."""
    limits = Limits(
        max_body_bytes=max_body_bytes,
        max_fit_body_bytes=min(max_fit_body_bytes, max_body_bytes),
        max_parse_body_bytes=min(MAX_PARSE_BODY_BYTES, max_body_bytes),
        max_pso_work=max_pso_work,
    )
    service = Service(
        open_store(data_dir, db_wait_s, create=create_db),
        Jobs(max_pending=max_pending_jobs, max_pso_work=max_pso_work),
        limits,
        token,
        sign_key=sign_key,
        require_signed=require_signed,
    )

    @asynccontextmanager
    async def lifespan(_app):
        # changes made by other processes reach the cache (server/follow.py); the cell beats (plant.py)
        service.start_following(None if heartbeat is None else lambda: beat(service.store, heartbeat()))
        yield
        if service.follower is not None:
            service.follower.stop()
        service.jobs.shutdown()

    app = FastAPI(
        title="eyetohand workbench",
        version=__version__,
        description=(
            "Calibrate a fixed camera to a robot from point pairs, keep calibrations with their "
            "history, and map image points (px) to robot points (mm). Errors are "
            '`{"error", "field"}` objects. Limits: mapping body ≤ 64 MiB and ≤ 1 000 000 points '
            f"per request, fit bodies ≤ {limits.max_fit_body_bytes // 2**20} MiB (413 beyond), "
            "≤ 5000 pairs per fit. A write that cannot get the database within "
            f"{db_wait_s:g} s answers 503 with Retry-After."
        ),
        lifespan=lifespan,
        responses=ERRORS,
        docs_url=None,
        redoc_url=None,
    )
    app.state.service = service
    app.state.store = service.store  # kept for callers that close the store themselves
    app.state.jobs = service.jobs
    install_handlers(app)
    # mapping first: a request is matched against the routes in order, and the robot's mapping calls
    # are the hot path (no other route matches their paths; tested)
    for r in (mapping, page, meta, pairs, calibrations, jobs, collect, images, diff, plate, audit, plant):
        app.include_router(r.router)
    app.include_router(signing.router)
    page.mount_static(app)

    def limit_for(path: str) -> int:
        if path.endswith("/image-to-robot"):
            return limits.max_body_bytes
        if path == "/api/pairs/parse":
            return limits.max_parse_body_bytes
        if path in ("/api/images/calibrate", "/api/plate/calibrate", "/api/plate/detect"):  # base64 images
            return limits.max_body_bytes
        return limits.max_fit_body_bytes

    # the last added runs first: Host, then cross-site refusal, token, database, body; innermost, after
    # every guard, the one-point mapping call's short way to the route's own functions
    app.add_middleware(mapping.FastMap, service=service)
    app.add_middleware(BodyLimit, limit_for=limit_for)
    app.add_middleware(DatabaseGuard, check=service.store.check_same_file)
    app.add_middleware(TokenGuard, token=token, backoff=auth_backoff)
    app.add_middleware(SameOrigin)
    if allowed_hosts is not None:
        app.add_middleware(HostGuard, hosts=allowed_hosts)
    return app


__all__ = ["create_app", "MAX_BODY_BYTES", "MAX_POINTS", "LOOPBACK_HOSTS", "PAPER_PRESET"]
