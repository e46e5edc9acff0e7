"""Every error of the API as one JSON object ``{"error", "field"[, "line"][, "errors"]}``, and the
exception handlers that make them (4xx for the caller's mistakes, 503/507 for the storage's state)."""

from __future__ import annotations

import re
from typing import Any

from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from eyetohand.core import InputError
from eyetohand.server.errors import ApiError, input_error
from eyetohand.server.storage import Ambiguous, Conflict, NameTaken, NotFound, StorageError


def error_response(
    status: int,
    message: str,
    field: str | None = None,
    line: int | None = None,
    errors: list | None = None,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    body: dict[str, Any] = {"error": message, "field": field}
    if line is not None:
        body["line"] = line
    if errors:
        body["errors"] = errors
    return JSONResponse(body, status_code=status, headers=headers)


async def send_response(send, response: JSONResponse) -> None:
    """Send ``response`` straight from ASGI middleware."""
    await send(
        {"type": "http.response.start", "status": response.status_code, "headers": response.raw_headers}
    )
    await send({"type": "http.response.body", "body": response.body})


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


_TYPE_NAMES = {bool: "a boolean", str: "a string", type(None): "null", list: "a list", dict: "an object"}


def _message(e: dict) -> str:
    if e.get("type") == "missing":
        return "required field missing"
    msg = e.get("msg", "invalid")
    if e.get("type") == "value_error" and (e.get("ctx") or {}).get("error") is not None:
        msg = str(e["ctx"]["error"])  # our validators' own words, without pydantic's "Value error, "
    if e.get("type") in ("float_type", "int_type") and "input" in e:
        got = _TYPE_NAMES.get(type(e["input"]))
        if got:
            msg = f"{msg}, not {got}"
    return msg


def validation_response(errors) -> JSONResponse:
    errs = list(errors)
    if not errs:
        return error_response(422, "invalid request")
    first = errs[0]
    if first.get("type") == "json_invalid":
        ctx = first.get("ctx") or {}
        return error_response(400, f"body: invalid JSON ({ctx.get('error', first.get('msg'))})", "body")
    listed: list[dict[str, Any]] = []
    for e in errs[:20]:
        fld = _field_of(e.get("loc", ()))
        msg = _message(e)
        listed.append({"field": fld, "error": f"{fld}: {msg}" if fld else msg})
    return error_response(
        422, listed[0]["error"], listed[0]["field"], errors=listed if len(listed) > 1 else None
    )


def api_error_of_validation(errors) -> ApiError:
    """A pydantic ValidationError's errors (of a body validated by hand) as an ApiError."""
    resp = validation_response([{**e, "loc": ("body", *e["loc"])} for e in errors])
    import orjson

    body = orjson.loads(resp.body)
    return ApiError(resp.status_code, body["error"], body.get("field"))


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(_req, exc: ApiError):
        return error_response(exc.status, exc.message, exc.field, exc.line)

    @app.exception_handler(RequestValidationError)
    async def _validation(_req, exc: RequestValidationError):
        return validation_response(exc.errors())

    @app.exception_handler(InputError)
    async def _input(_req, exc: InputError):
        e = input_error(exc)
        return error_response(e.status, e.message, e.field, e.line)

    @app.exception_handler(NotFound)
    async def _not_found(_req, exc: NotFound):
        return error_response(404, str(exc).strip("'\""), "version" if "version" in str(exc) else "id")

    @app.exception_handler(NameTaken)
    async def _taken(_req, exc: NameTaken):
        return error_response(409, str(exc), "name")

    @app.exception_handler(Ambiguous)
    async def _ambiguous(_req, exc: Ambiguous):
        return error_response(409, str(exc).strip("'\""), "name")

    @app.exception_handler(Conflict)
    async def _conflict(_req, exc: Conflict):
        body = {
            "error": str(exc),
            "field": "If-Match",
            "current_version": exc.current_version,
            "etag": exc.etag,
        }
        return JSONResponse(body, status_code=412, headers={"ETag": exc.etag})

    @app.exception_handler(StorageError)
    async def _storage(_req, exc: StorageError):
        headers = {"Retry-After": str(exc.retry_after_s)} if exc.retry_after_s else None
        return error_response(exc.status, str(exc), None, headers=headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_req, exc: StarletteHTTPException):
        return error_response(
            exc.status_code,
            str(exc.detail),
            getattr(exc, "field", None),  # e.g. a duplicate key's path
            headers=dict(exc.headers) if exc.headers else None,
        )
