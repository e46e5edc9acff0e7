"""The API's routers, one per resource; each reaches the service through :func:`service`."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import Depends, Header, Query, Request
from fastapi import Path as PathParam
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException

from eyetohand.server.errors import ApiError
from eyetohand.server.service import Service
from eyetohand.server.storage import weak_tag_refusal


def get_service(request: Request) -> Service:
    return request.app.state.service


Svc = Annotated[Service, Depends(get_service)]
CalId = Annotated[int, PathParam(ge=1, le=2**62, description="calibration id")]
VersionQ = Annotated[int | None, Query(ge=1, le=2**62, description="version (default: current)")]
JobId = Annotated[str, PathParam(min_length=1, max_length=64, description="job id")]
MAX_IF_MATCH = 1024  # characters of an If-Match value (a few ETags; one is ~70)


def if_match_header(
    value: Annotated[
        str | None,
        Header(
            alias="If-Match",
            description="the ETag of the state this change was decided on (from a GET or a write's "
            "answer); 412 with the current version when it is not current any more; a weak ETag "
            "(W/...) or a value over 1024 characters: 400",
        ),
    ] = None,
) -> str | None:
    """The ``If-Match`` header, refused (400 naming it) when longer than :data:`MAX_IF_MATCH` or when it
    holds a weak ETag: If-Match compares strongly (RFC 9110, 13.1.1), so ``W/"…"`` never matches and
    taking it as the strong tag would pass a condition the client did not set."""
    if value is None:
        return None
    if len(value) > MAX_IF_MATCH:
        raise ApiError(
            400,
            f"If-Match: {len(value)} characters, more than {MAX_IF_MATCH}; send the ETag of a GET or "
            "of a write's answer",
            "If-Match",
        )
    weak = weak_tag_refusal(value)  # the store's require_match refuses it with the same words
    if weak is not None:
        raise ApiError(400, weak, "If-Match")
    return value


IfMatch = Annotated[str | None, Depends(if_match_header)]


class DuplicateKey(HTTPException):
    """A JSON body with one key twice in an object (400 naming it): JSON leaves which one counts to
    the parser, so two readers of one body could act on different values."""

    def __init__(self, field: str, key: str):
        super().__init__(400, f"{field}: key {key!r} appears twice in one object of the JSON body")
        self.field = field


def strict_json(body: bytes | bytearray | str) -> Any:
    """``json.loads`` of a request body, refusing a key given twice in one object
    (:class:`DuplicateKey` naming it as ``pairs[3].u``); syntax errors raise ``JSONDecodeError``."""
    dups: list[tuple[int, str]] = []

    def hook(pairs: list[tuple[str, Any]]) -> dict:
        d: dict = {}
        for k, v in pairs:
            if k in d and not dups:
                dups.append((0, k))
            d[k] = v
        if dups and dups[-1][0] == 0:
            dups[-1] = (id(d), dups[-1][1])
        return d

    try:
        doc = json.loads(body, object_pairs_hook=hook)
    except RecursionError:  # nested deeper than the parser's stack allows (~1000 levels): a syntax refusal
        text = body.decode("utf-8", "replace") if isinstance(body, (bytes, bytearray)) else body
        raise json.JSONDecodeError("nested too deeply", text, 0) from None
    if dups:
        target, key = dups[0]
        try:
            path = _path_of(doc, target, "")
        except RecursionError:  # the object is too deep to name its path: its key alone
            path = None
        raise DuplicateKey(f"{path}.{key}" if path else key, key)
    return doc


def _path_of(obj: Any, target: int, path: str) -> str | None:
    """The field path (``pairs[3].u`` style) of the object with ``id`` target, joined with its key."""
    if isinstance(obj, dict):
        if id(obj) == target:
            return path
        for k, v in obj.items():
            found = _path_of(v, target, f"{path}.{k}" if path else str(k))
            if found is not None:
                return found
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            found = _path_of(v, target, f"{path}[{i}]")
            if found is not None:
                return found
    return None


class StrictJsonRequest(Request):
    """A request whose JSON body is read by :func:`strict_json`."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = strict_json(await self.body())
        return self._json


class StrictJsonRoute(APIRoute):
    """A route whose body is parsed by :func:`strict_json` (every router of the API uses it)."""

    def get_route_handler(self):
        handler = super().get_route_handler()

        async def strict_handler(request: Request):
            return await handler(StrictJsonRequest(request.scope, request.receive))

        return strict_handler
