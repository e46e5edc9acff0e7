"""ASGI guards in front of the routes: body size and type, token and its role, Host. Each answers with
the API's JSON error body without reading more of the request than it needs."""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping

from eyetohand.core import AuthBackoff, Role, TokenTable, acting_as
from eyetohand.server.responses import error_response, send_response

JSON_TYPES = (b"application/json",)


class BodyTooLarge(Exception):
    """Raised from ``receive`` when a streamed body passes its limit (turned into a 413 here)."""


class BodyLimit:
    """Refuse a request body larger than ``limit_for(path)`` bytes with 413, from ``Content-Length``
    when given, else while it streams in, before any route parses it. The body is not buffered
    here (the route reads it once). A body that is not ``application/json`` gets 415."""

    def __init__(self, app, limit_for: Callable[[str], int]):
        self.app = app
        self.limit_for = limit_for

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            return await self.app(scope, receive, send)
        limit = self.limit_for(scope["path"])
        length = ctype = None
        chunked = False
        for k, v in scope.get("headers") or ():
            if k == b"content-length":
                length = v
            elif k == b"content-type":
                ctype = v
            elif k == b"transfer-encoding":
                chunked = b"chunked" in v.lower()
        too_big = f"request body larger than the limit of {limit} bytes for {scope['path']}"
        if length is not None:
            if not length.strip().isdigit():
                return await send_response(
                    send, error_response(400, "Content-Length is not a number", "Content-Length")
                )
            if int(length) > limit:
                return await send_response(send, error_response(413, too_big, "body"))
        if (chunked or (length is not None and int(length) > 0)) and (ctype or b"").split(b";")[
            0
        ].strip().lower() not in JSON_TYPES:
            return await send_response(
                send, error_response(415, "Content-Type must be application/json", "Content-Type")
            )
        received = 0
        exceeded = False

        async def limited():
            nonlocal received, exceeded
            msg = await receive()
            if msg["type"] == "http.request":
                received += len(msg.get("body", b""))
                if received > limit:
                    exceeded = True
                    raise BodyTooLarge
            return msg

        async def guarded_send(msg):
            if not exceeded:  # the app's own answer to a cut body (e.g. 400) is replaced below
                await send(msg)

        try:
            await self.app(scope, limited, guarded_send)
        except BodyTooLarge:
            pass
        if exceeded:
            await send_response(send, error_response(413, too_big, "body"))


# the POSTs that change nothing (a mapping, an evaluation, a parse): a viewer may send them
_READ_POSTS = re.compile(
    r"/api/(calibrations/\d+/(image-to-robot|evaluate)|jobs/[^/]+/image-to-robot|pairs/parse)"
)
_SIGN = re.compile(r"/api/calibrations/\d+/versions/\d+/sign")


def required_role(method: str, path: str) -> Role:
    """The least role that may send ``method path`` (docs/server.md "Tokens, roles and signing"):
    signer to sign a version; viewer to read (GET, HEAD) and to map or evaluate (the POSTs that store
    nothing); operator for every other request — so a route added later needs an operator unless it
    is named here."""
    if _SIGN.fullmatch(path):
        return Role.SIGNER
    if method in ("GET", "HEAD", "OPTIONS") or (method == "POST" and _READ_POSTS.fullmatch(path)):
        return Role.VIEWER
    return Role.OPERATOR


class TokenGuard:
    """With tokens set, every /api/ request needs ``Authorization: Bearer <token>`` of one of them
    (``token``: one token, names to tokens, or a :class:`~eyetohand.core.TokenTable` with roles), and
    its token's role must allow the request (:func:`required_role`; else 403 naming both). The
    request then acts as that token's holder (:func:`~eyetohand.core.acting_as`): its changes are
    audited under the name. After repeated wrong tokens from one address (``backoff``), its
    requests get 429 with ``Retry-After``, unjudged, until the delay is over."""

    def __init__(
        self, app, token: str | Mapping[str, str] | TokenTable | None, backoff: AuthBackoff | None = None
    ):
        self.app = app
        self.table = TokenTable.of(token)
        self.backoff = AuthBackoff() if backoff is None else backoff

    async def __call__(self, scope, receive, send):
        if (
            self.table
            and scope["type"] == "http"
            and scope["path"].startswith("/api/")
            and scope["path"] != "/api/health"
        ):
            client = scope.get("client")
            addr = str(client[0]) if client else "?"
            auth = dict(scope.get("headers") or []).get(b"authorization", b"")
            given = auth[7:].strip() if auth[:7].lower() == b"bearer " else b""
            wait_s = self.backoff.wait_s(addr) if given else 0.0  # no token tried: not held back
            if wait_s > 0:
                retry = str(math.ceil(wait_s))
                return await send_response(
                    send,
                    error_response(
                        429,
                        f"too many wrong tokens from {addr}: the next request is judged in {retry} s",
                        "Authorization",
                        headers={"Retry-After": retry},
                    ),
                )
            actor = self.table.match(given)
            if actor is None:
                if given:  # a token tried and wrong (none at all is no guess: not counted)
                    self.backoff.failed(addr, "HTTP token")
                return await send_response(
                    send,
                    error_response(
                        401,
                        "missing or wrong token: send the header 'Authorization: Bearer <token>'",
                        "Authorization",
                    ),
                )
            self.backoff.succeeded(addr)
            method, path = scope["method"], scope["path"]
            refused = actor.refusal(required_role(method, path), f"{method} {path}")
            if refused is not None:
                return await send_response(send, error_response(403, refused, "Authorization"))
            with acting_as(actor):
                return await self.app(scope, receive, send)
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
                return await send_response(
                    send, error_response(400, f"Host {host!r} is not served here", "Host")
                )
        return await self.app(scope, receive, send)


SAFE_METHODS = ("GET", "HEAD", "OPTIONS")
FORGERY_HEADERS = (b"x-requested-with", b"x-eyetohand")


class SameOrigin:
    """Refuse cross-site request forgery: a request that changes state must not be one a page of
    another site can make the browser send.

    - ``Origin``, when the browser sends one on such a request, must name this server (its
      host[:port] equal to ``Host``); ``Origin: null`` (a sandboxed or file page) is refused too.
    - A ``POST`` — the one state-changing method an HTML form or a "simple" cross-site ``fetch`` can
      send — must carry ``Content-Type: application/json`` or an ``X-Requested-With`` header, which
      a cross-site page can only send after a CORS preflight this server never grants. (``PUT``,
      ``PATCH`` and ``DELETE`` always need that preflight.) A body-less one is refused here (403
      naming the header); one with a body of another type is refused by :class:`BodyLimit` (415)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in SAFE_METHODS:
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or ())
        origin = headers.get(b"origin")
        if origin is not None:
            host = headers.get(b"host", b"").decode("latin-1").strip().lower()
            text = origin.decode("latin-1").strip()
            netloc = text.lower().partition("://")[2].rstrip("/")
            scheme = text.lower().partition("://")[0]
            default = {"http": ":80", "https": ":443"}.get(scheme, "")
            if not netloc or (netloc != host and netloc.removesuffix(default) != host.removesuffix(default)):
                return await send_response(
                    send,
                    error_response(
                        403,
                        f"Origin {text!r} is not this server (Host {host!r}): a request from another "
                        "site's page may not change anything here",
                        "Origin",
                    ),
                )
        bodyless = headers.get(b"content-length", b"0").strip() in (b"", b"0") and (
            b"transfer-encoding" not in headers
        )  # a body must be application/json anyway (BodyLimit: 415)
        if scope["method"] == "POST" and bodyless:
            ctype = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
            if ctype not in JSON_TYPES and not any(h in headers for h in FORGERY_HEADERS):
                return await send_response(
                    send,
                    error_response(
                        403,
                        "a POST must be sent as Content-Type: application/json or with the header "
                        "X-Requested-With (a form on another site can send neither)",
                        "Content-Type",
                    ),
                )
        return await self.app(scope, receive, send)


class DatabaseGuard:
    """Every /api/ request first proves that the database file is still the one the server opened
    (``store.check_same_file()``: one stat); while it is missing or replaced, 503 ``database replaced
    or missing``. The mapping routes answer from memory, so without this they would keep mapping with
    a database that is no longer the truth."""

    def __init__(self, app, check: Callable[[], None]):
        self.app = app
        self.check = check

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http" and scope["path"].startswith("/api/"):
            from eyetohand.server.storage import DatabaseGone

            try:
                self.check()
            except DatabaseGone as exc:
                return await send_response(send, error_response(503, str(exc), "database"))
        return await self.app(scope, receive, send)
