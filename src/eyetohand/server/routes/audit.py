"""The audit trail (``GET /api/audit``): every change of the store, newest first, filtered and paged.
Runs on the thread pool (it reads the database)."""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated

from fastapi import APIRouter, Query

from eyetohand.server.errors import ApiError
from eyetohand.server.routes import StrictJsonRoute, Svc
from eyetohand.server.stores import QueryError, audit_query

router = APIRouter(tags=["audit"], route_class=StrictJsonRoute)


@router.get("/api/audit")
def audit(
    svc: Svc,
    calibration: Annotated[
        str | None, Query(max_length=256, description="name or id (id:N, name:NAME) of one calibration")
    ] = None,
    user: Annotated[
        str | None, Query(max_length=256, description="the token name of the change's author")
    ] = None,
    since: Annotated[
        str | None, Query(max_length=64, description="ISO 8601 (UTC when no zone): at or after")
    ] = None,
    until: Annotated[str | None, Query(max_length=64, description="ISO 8601: at or before")] = None,
    before: Annotated[
        int | None,
        Query(ge=1, le=2**62, description="entries older than this id (the previous page's next_before)"),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="entries per page")] = 100,
) -> dict:
    """Audit entries newest first: ``entries`` (utc, user, action, calibration, version_before and
    _after, note) and ``next_before``, the ``before`` of the next page (null on the last one)."""
    try:
        q = audit_query(
            svc.store,
            calibration=calibration,
            user=user,
            since=since,
            until=until,
            before=before,
            limit=limit,
        )
    except QueryError as exc:
        raise ApiError(422, str(exc), exc.field) from None
    entries = svc.store.audit(q)
    more = len(entries) == q.limit and bool(svc.store.audit(replace(q, before=entries[-1].id, limit=1)))
    return {"entries": [e.to_dict() for e in entries], "next_before": entries[-1].id if more else None}
