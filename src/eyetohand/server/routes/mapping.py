"""Image → robot mapping (HTTP). These routes run on the event loop and never touch the database
once a calibration is cached: a cache miss is read on the thread pool; small bodies are parsed and
mapped inline (a thread hop costs more than the work), large ones off the loop.

The points array is not built by pydantic (10⁶ tuples of Python floats cost ~10× the array): the
body's ``"points"`` value is located, checked to be only numbers, brackets and commas nested as
``[[u, v], ...]`` (NumPy over its bytes), and parsed by orjson in flat chunks straight into one
(N, 2) float array; the rest of the body (with one placeholder point) is validated by
:class:`~eyetohand.server.schemas.MapRequest` as before. Anything else — other spellings, wrong
types or shapes, non-finite values — goes through ``MapRequest`` whole, so every 422 names the
field with the same words. Large answers are mapped in chunks into the output arrays and streamed
out in pieces, so a 10⁶-point request holds little more than its arrays.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import numpy as np
import orjson
from fastapi import APIRouter, Request, Response
from fastapi.responses import StreamingResponse
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from eyetohand.calibration import Calibration, Mapped
from eyetohand.core import InputError, OutputUnits, output_units
from eyetohand.server.errors import ApiError
from eyetohand.server.responses import api_error_of_validation
from eyetohand.server.routes import CalId, DuplicateKey, JobId, StrictJsonRoute, VersionQ, strict_json
from eyetohand.server.schemas import MAX_POINTS, MapRequest, MapResponse
from eyetohand.server.signatures import job_waits_for_signature
from eyetohand.server.summaries import map_points

INLINE_BYTES = 64 * 1024
INLINE_POINTS = 2000
CHUNK_POINTS = 65536  # mapped, parsed and written this many points at a time
CHUNK_BYTES = 1 << 20

router = APIRouter(tags=["mapping"], route_class=StrictJsonRoute)
MAP_OPENAPI = {
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": MapRequest.model_json_schema()}},
    }
}

_KEY = b'"points"'
_NUMBER_BYTES = b"0123456789.eE+-"
_POINTS_BYTES = _NUMBER_BYTES + b",[] \t\r\n"
_AFTER_KEY = re.compile(rb"\s*:\s*\[")
_END = re.compile(rb"\]\s*\]")
_NUMBER_WS = _NUMBER_BYTES + b" \t\r\n"
_ROW = b"[,],"
_PLAIN = {"points": [[0, 0]]}
_DEFAULT = MapRequest(points=[(0.0, 0.0)])


def _pairs(chunk: bytes) -> np.ndarray | None:
    """``[u,v],[u,v],...,[u,v]`` (numbers, brackets, commas, white space only) → (k, 2) floats, or
    None if it is not exactly that: its brackets and commas must read ``[,],`` k times (less the
    last comma), and what the brackets held one flat JSON array of 2k numbers."""
    s = chunk.translate(None, _NUMBER_WS) + b","
    k = len(s) // 4
    if s != _ROW * k:
        return None
    try:
        flat = orjson.loads(b"[" + chunk.translate(None, b"[]") + b"]")
    except orjson.JSONDecodeError:
        return None
    if len(flat) != 2 * k:
        return None
    return np.array(flat, dtype=float).reshape(k, 2)


def fast_points(body: bytes | bytearray) -> tuple[np.ndarray, bytes] | None:
    """(points (N, 2), the body with ``[[0, 0]]`` for its points) when the body's top-level
    ``"points"`` is a plain array of number pairs, else None (then the caller validates it whole)."""
    body = bytes(body) if isinstance(body, bytearray) else body
    i = body.find(_KEY)
    if i < 1 or b"\\" in body or body.find(_KEY, i + 1) != -1:
        return None
    m = _AFTER_KEY.match(body, i + len(_KEY))
    if m is None:
        return None
    start = m.end() - 1  # the outer '['
    k = body.find(b"]]", start)
    end = k + 2 if k != -1 else -1
    if k == -1 or body[start:end].translate(None, _POINTS_BYTES):
        e = _END.search(body, start)
        if e is None:
            return None
        end = e.end()
    seg = body[start:end]
    if seg.translate(None, _POINTS_BYTES):
        return None
    n = seg.count(b"[") - 1
    if n < 1:
        return None
    out = np.empty((n, 2))
    inner = seg[1 : seg.rindex(b"]")].strip()  # '[u,v],...,[u,v]'
    pos, row = 0, 0
    while pos < len(inner):
        cut = inner.find(b"]", min(pos + CHUNK_BYTES, len(inner) - 1))
        if cut == -1:
            return None
        part = inner[pos : cut + 1]
        pairs = _pairs(part.strip())
        if pairs is None or row + len(pairs) > n:
            return None
        out[row : row + len(pairs)] = pairs
        row += len(pairs)
        nxt = inner.find(b",", cut + 1)
        if nxt == -1:
            if inner[cut + 1 :].strip():
                return None
            break
        if inner[cut + 1 : nxt].strip():
            return None
        pos = nxt + 1
    if row != n or not np.isfinite(out).all():
        return None
    return out, body[:start] + b"[[0,0]]" + body[end:]


def _plain(rest: bytes) -> bool:
    """Whether the body has nothing but its points (then every option is its default)."""
    try:
        return orjson.loads(rest) == _PLAIN
    except orjson.JSONDecodeError:
        return False


def _no_duplicate_keys(body: bytes | bytearray) -> None:
    """400 naming a key given twice in one object (pydantic would keep the last one silently)."""
    try:
        strict_json(body)
    except DuplicateKey as exc:
        raise ApiError(400, str(exc.detail), exc.field) from None
    except ValueError:  # not JSON: the validation below names it with its own words
        pass


def parse_map_body(body: bytes | bytearray) -> tuple[MapRequest, np.ndarray]:
    """The request's options and its (N, 2) points; a 422 / 400 / 413 :class:`ApiError` as before."""
    fast = fast_points(body)
    try:
        if fast is not None:
            pts, rest = fast
            _no_duplicate_keys(rest)  # the points are plain number pairs: no object to repeat a key in
            req = _DEFAULT if _plain(rest) else MapRequest.model_validate_json(rest)
        else:
            _no_duplicate_keys(body)
            req = MapRequest.model_validate_json(body)
            pts = np.asarray(req.points, float).reshape(-1, 2)
    except ValidationError as exc:
        raise api_error_of_validation(exc.errors(include_url=False)) from None
    if len(pts) > MAX_POINTS:
        raise ApiError(
            413,
            f"points: {len(pts)} points, more than the {MAX_POINTS} per request limit; split the request",
            "points",
        )
    return req, pts


async def read_body(request: Request) -> bytes | bytearray:
    """The body, read once (the size guard has checked its length); a large one into one buffer
    as it streams in, not as a list of chunks joined."""
    length = request.headers.get("content-length", "")
    if length.isdigit() and int(length) <= INLINE_BYTES:
        return await request.body()
    buf = bytearray()
    async for chunk in request.stream():
        buf += chunk
    return buf


async def parsed(body: bytes | bytearray) -> tuple[MapRequest, np.ndarray]:
    """:func:`parse_map_body`, inline for a small body, off the loop for a large one."""
    if len(body) <= INLINE_BYTES:
        return parse_map_body(body)
    return await run_in_threadpool(parse_map_body, body)


async def map_body(request: Request) -> tuple[MapRequest, np.ndarray]:
    return await parsed(await read_body(request))


def request_units(req: MapRequest) -> OutputUnits:
    """The request's ``units`` and ``angle_units``, refused (422) with every interface's words."""
    if req.units is None and req.angle_units is None:
        return _MM_DEG
    try:
        return output_units(req.units, req.angle_units)
    except InputError as exc:
        raise ApiError(422, str(exc), str(exc).split(":", 1)[0]) from None


def _map(cal: Calibration, req: MapRequest, pts: np.ndarray) -> Mapped:
    """``map_points`` over the request; a large one in chunks written into the output arrays
    (each point's answer is its own: the same numbers). A refusal is re-done on the whole array, so
    it names the same point, with the same words, as one call would. Heights are given in the request's
    units (mm for the library: :meth:`OutputUnits.in_length`); the answer is in mm."""
    units = request_units(req)
    z = req.z
    if not units.is_default and z is not None:
        z = [units.in_length(v) for v in z] if isinstance(z, list) else units.in_length(z)

    def one(sl: slice) -> Mapped:
        return map_points(
            cal,
            pts[sl],
            z[sl] if isinstance(z, list) else z,
            angles=None if req.angles is None else req.angles[sl],
            symmetry=req.symmetry,
            tool_rz_offset_deg=req.tool_rz_offset_deg,
            allow_outside=req.allow_outside,
            sigma=req.sigma,
            part_diameter_mm=req.part_diameter_mm[sl]
            if isinstance(req.part_diameter_mm, list)
            else req.part_diameter_mm,
        )

    n = len(pts)
    if (
        n <= CHUNK_POINTS
        or (isinstance(req.z, list) and len(req.z) != n)
        or (isinstance(req.part_diameter_mm, list) and len(req.part_diameter_mm) != n)
        or (req.angles is not None and len(req.angles) != n)
    ):
        return one(slice(None))
    out: Mapped | None = None
    try:
        for a in range(0, n, CHUNK_POINTS):
            sl = slice(a, a + CHUNK_POINTS)
            m = one(sl)
            if out is None:
                out = Mapped(
                    pts,
                    np.empty((n, 3)),
                    None if m.rz_deg is None else np.empty(n),
                    None if m.sigma_mm is None else np.empty(n),
                    np.empty(n, bool),
                    np.empty(n),
                )
            for name in ("xyz_mm", "rz_deg", "sigma_mm", "inside", "outside_px"):
                dst = getattr(out, name)
                if dst is not None:
                    dst[sl] = getattr(m, name)
    except ApiError:
        out = None
        return one(slice(None))
    assert out is not None
    return out


_MM_DEG = output_units()


def in_units(m: Mapped, units: OutputUnits) -> Mapped:
    """The mapped points with x, y, z and sigma in ``units.length``, rz in ``units.angle``
    (:mod:`eyetohand.core.units`: m = mm / 1000.0, rad = deg · π/180)."""
    if units.is_default:
        return m
    return Mapped(
        m.uv_px,
        units.out_length(m.xyz_mm),
        None if m.rz_deg is None else units.out_angle(m.rz_deg),
        None if m.sigma_mm is None else units.out_length(m.sigma_mm),
        m.inside,
        m.outside_px,
    )


def _head(cal_id, version, units: OutputUnits) -> bytes:
    head = {"id": cal_id, "version": version, "units": units.length, "angle_units": units.angle}
    return orjson.dumps(head)[:-1]


def _work(cal: Calibration, req: MapRequest, pts: np.ndarray, cal_id, version) -> bytes:
    units = request_units(req)
    m = in_units(_map(cal, req, pts), units)
    return orjson.dumps(
        {
            "id": cal_id,
            "version": version,
            "units": units.length,
            "angle_units": units.angle,
            "points": m.xyz_mm,
            units.rz_key: m.rz_deg,
            units.sigma_key: m.sigma_mm,
            "inside": m.inside,
        },
        option=orjson.OPT_SERIALIZE_NUMPY,
    )


def _pieces(m: Mapped, cal_id, version, units: OutputUnits = _MM_DEG) -> Iterator[bytes]:
    """The same JSON as :func:`_work`, in pieces of :data:`CHUNK_POINTS` points (``m`` already in
    ``units``)."""
    n = len(m.xyz_mm)

    def array(a: np.ndarray) -> Iterator[bytes]:
        yield b"["
        for s in range(0, n, CHUNK_POINTS):
            piece = orjson.dumps(a[s : s + CHUNK_POINTS], option=orjson.OPT_SERIALIZE_NUMPY)[1:-1]
            yield piece if s == 0 else b"," + piece

        yield b"]"

    yield _head(cal_id, version, units) + b',"points":'
    yield from array(m.xyz_mm)
    yield f',"{units.rz_key}":'.encode()
    yield from (array(m.rz_deg) if m.rz_deg is not None else [b"null"])
    yield f',"{units.sigma_key}":'.encode()
    yield from (array(m.sigma_mm) if m.sigma_mm is not None else [b"null"])
    yield b',"inside":'
    yield from array(m.inside)
    yield b"}"


async def mapped(cal: Calibration, req: MapRequest, pts: np.ndarray, cal_id=None, version=None) -> Response:
    if len(pts) <= INLINE_POINTS:
        return Response(_work(cal, req, pts, cal_id, version), media_type="application/json")
    units = request_units(req)
    m = in_units(await run_in_threadpool(_map, cal, req, pts), units)
    del pts
    return StreamingResponse(_pieces(m, cal_id, version, units), media_type="application/json")


_CAL_MAP_PATH = re.compile(r"/api/calibrations/([1-9][0-9]{0,18})/image-to-robot")
_MAX_ID = 2**62  # CalId's bound


class FastMap:
    """The robot's hot call — one small ``POST /api/calibrations/{id}/image-to-robot`` (no query) to a
    calibration in the service's cache — answered without FastAPI's routing, request object and
    parameter validation (a third of the route's time for one point): the route's own parse, map and
    bytes (:func:`parse_map_body`, :func:`_work`, the same ``Response``). Anything else goes to the app
    unchanged, the body read here handed on: a query (``version``), another id spelling, a body over
    :data:`INLINE_BYTES` or in pieces, more than :data:`INLINE_POINTS` points, a calibration not cached,
    and every refusal or failure (re-done by the route, so each keeps its one path, status and words).
    Installed innermost: every guard (Host, Origin, token, database, body size) runs before it.

    The calibration is taken from the cache once the body has arrived, never before: a body that
    comes seconds after its headers is answered with the version in force then (a DELETE or a
    rollback meanwhile is not undone by a request that was already on its way)."""

    def __init__(self, app, service):
        self.app = app
        self.service = service

    async def __call__(self, scope, receive, send):
        if (
            scope["type"] != "http"
            or scope["method"] != "POST"
            or scope["query_string"]
            or scope.get("root_path")
        ):
            return await self.app(scope, receive, send)
        m = _CAL_MAP_PATH.fullmatch(scope["path"])
        cal_id = int(m.group(1)) if m is not None else 0
        if not 0 < cal_id <= _MAX_ID or self.service.cached(cal_id) is None:  # a miss: the route reads it
            return await self.app(scope, receive, send)
        msg = await receive()
        body = msg.get("body", b"")
        complete = msg["type"] == "http.request" and not msg.get("more_body", False)
        # taken now that the body is here: what is in force when the request is complete
        hit = self.service.cached(cal_id) if complete and len(body) <= INLINE_BYTES else None
        if hit is not None:
            try:
                req, pts = parse_map_body(body)
                content = _work(hit[1], req, pts, cal_id, hit[0]) if len(pts) <= INLINE_POINTS else None
            except Exception:  # noqa: BLE001 - the route answers it, with its words
                content = None
            if content is not None:
                return await Response(content, media_type="application/json")(scope, receive, send)
        given = False

        async def replay():
            nonlocal given
            if not given:
                given = True
                return msg
            return await receive()

        return await self.app(scope, replay, send)


@router.post(
    "/api/calibrations/{cal_id}/image-to-robot", response_model=MapResponse, openapi_extra=MAP_OPENAPI
)
async def image_to_robot(cal_id: CalId, request: Request, version: VersionQ = None):
    """Map image points (px) to robot points (mm) with a stored calibration."""
    svc = request.app.state.service
    body = await read_body(request)  # first: the calibration in force is the one once the body is here
    hit = svc.cached(cal_id, version)
    if hit is None:
        ver, cal = await run_in_threadpool(svc.served, cal_id, version)  # --require-signed: signed only
        hit = (ver.version, cal)
    req, pts = await parsed(body)
    return await mapped(hit[1], req, pts, cal_id, hit[0])


@router.post("/api/jobs/{job_id}/image-to-robot", response_model=MapResponse, openapi_extra=MAP_OPENAPI)
async def job_image_to_robot(job_id: JobId, request: Request):
    """Map image points (px) to robot points (mm) with a finished, unsaved fit."""
    svc = request.app.state.service
    fitted = svc.finished_fit(job_id)
    if svc.require_signed:  # an unsaved fit is signed by nobody
        raise ApiError(409, job_waits_for_signature(job_id), "signature")
    req, pts = await map_body(request)
    return await mapped(fitted.calibration, req, pts)
