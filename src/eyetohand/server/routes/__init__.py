"""The API's routers, one per resource; each reaches the service through :func:`service`."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Query, Request
from fastapi import Path as PathParam

from eyetohand.server.service import Service


def get_service(request: Request) -> Service:
    return request.app.state.service


Svc = Annotated[Service, Depends(get_service)]
CalId = Annotated[int, PathParam(ge=1, le=2**62, description="calibration id")]
VersionQ = Annotated[int | None, Query(ge=1, le=2**62, description="version (default: current)")]
JobId = Annotated[str, PathParam(min_length=1, max_length=64, description="job id")]
