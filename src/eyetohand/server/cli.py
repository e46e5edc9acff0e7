"""What ``eyetohand serve`` runs: the workbench page and JSON API (uvicorn), and optionally the TCP line
service. The command itself (its options) is :mod:`eyetohand.cli.serve`."""

from __future__ import annotations

import asyncio
import ipaddress
import socket

from ..errors import InputError


class ServeError(InputError):
    """Bad ``serve`` options (exit 2)."""


def is_loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ServeError(f"--tcp: expected HOST:PORT (e.g. 127.0.0.1:7001), got {text!r}")
    return host.strip("[]"), int(port)


def check_options(args) -> None:
    """Refuse unsafe or incomplete option sets before anything binds."""
    if not 0 <= args.port <= 65535:
        raise ServeError(f"--port: expected 0..65535 (0: any free port), got {args.port}")
    if not 0 < args.db_wait <= 60:
        raise ServeError(f"--db-wait: expected seconds in (0, 60], got {args.db_wait:g}")
    if args.token is not None and len(args.token) < 8:
        raise ServeError("--token: use at least 8 characters")
    if not is_loopback(args.host) and not args.token:
        raise ServeError(
            f"--host {args.host}: serving beyond this machine needs --token T "
            "(or EYETOHAND_TOKEN); refusing to start without one"
        )
    if args.tcp:
        host, _ = parse_hostport(args.tcp)
        if not is_loopback(host) and not args.token:
            raise ServeError(f"--tcp {args.tcp}: a non-loopback address needs --token T; refusing to start")
        if not args.calibration:
            raise ServeError("--tcp needs --calibration NAME, id:N or FILE.json (the calibration to serve)")
    elif args.calibration:
        raise ServeError("--calibration is for the TCP service: give --tcp HOST:PORT too")
    args.calibration_file = None
    if args.calibration:
        path = calibration_path(args.calibration)
        if path is not None:
            from .tcp import FixedCalibration

            try:
                args.calibration_file = FixedCalibration.from_file(path)
            except InputError as exc:
                raise ServeError(f"--calibration: {exc}") from None


def calibration_path(ref: str):
    """The file a ``--calibration`` value names, or None for a stored calibration.

    Unambiguous by its form: ``file:PATH``, or a value ending in ``.json`` or containing a path
    separator, is a file; ``id:N`` is the stored calibration with id N; ``name:NAME`` (or any other
    value) is a stored calibration's name (digits alone: the id, refused when another's name)."""
    import os
    from pathlib import Path

    if ref.startswith("file:"):
        return Path(ref[5:])
    if ref.lower().startswith(("id:", "name:")):
        return None
    if ref.lower().endswith(".json") or "/" in ref or (os.sep != "/" and os.sep in ref):
        return Path(ref)
    return None


async def _serve(args, data_dir) -> None:
    import uvicorn

    from .app import LOOPBACK_HOSTS, create_app
    from .storage import Ambiguous, NotFound, StorageError, Store
    from .tcp import LineServer, StoredCalibration

    http_sock = bind_http(args.host, args.port)
    line_server = None
    if args.tcp:
        host, port = parse_hostport(args.tcp)
        source = getattr(args, "calibration_file", None)
        if source is None:
            store = Store(data_dir, wait_s=args.db_wait)
            try:
                rec = store.find(args.calibration)
                source = StoredCalibration(store, rec.id)
            except (NotFound, Ambiguous, StorageError, InputError) as exc:
                store.close()
                http_sock.close()
                raise ServeError(f"--calibration: {str(exc).strip(chr(39))} in {store.path}") from None
            what = (f"calibration {rec.name!r} (id {rec.id}, version {source.version}, followed: a new "
                    "version or a rollback takes effect within a second)")
        else:
            what = f"the file {source.label} (sha256 {source.sha256[:12]}…)"
        line_server = LineServer(source, host, port, token=args.token)
        try:
            await line_server.start()
        except OSError as exc:
            http_sock.close()
            raise ServeError(f"--tcp {args.tcp}: cannot listen there ({exc.strerror or exc})") from None
        print(f"TCP: {host}:{line_server.port} maps 'u,v[,z]' lines with {what}", flush=True)

    app = create_app(data_dir, token=args.token, db_wait_s=args.db_wait,
                     allowed_hosts=LOOPBACK_HOSTS if is_loopback(args.host) else None)
    port = http_sock.getsockname()[1]
    print(f"workbench: http://{args.host}:{port}/  (API docs: /docs; data: {data_dir})", flush=True)
    config = uvicorn.Config(app, log_level=args.log_level, timeout_graceful_shutdown=5)
    server = uvicorn.Server(config)
    try:
        await server.serve(sockets=[http_sock])
    finally:
        if line_server is not None:
            line_server.close()
            store = getattr(line_server.source, "store", None)
            if store is not None:
                store.close()


def bind_http(host: str, port: int) -> socket.socket:
    """The HTTP listening socket, bound here so that a busy port is one ``error:`` line (exit 2)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise ServeError(f"--host {host}: not an address of this machine ({exc})") from None
    family, kind, proto, _, addr = infos[0]
    # proto must be IPPROTO_TCP: asyncio sets TCP_NODELAY on accepted sockets only then (without it,
    # Nagle's algorithm and delayed ACKs add ~40 ms to every small response)
    sock = socket.socket(family, kind, proto or socket.IPPROTO_TCP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        raise ServeError(f"--port {port}: cannot listen on {host}:{port} ({exc.strerror or exc})") from None
    sock.setblocking(False)
    return sock


def serve(args, data_dir) -> None:
    """Run the workbench (and the TCP service with ``args.tcp``) until stopped; ``args`` as parsed by
    ``eyetohand serve`` (:mod:`eyetohand.cli.serve`), already checked by :func:`check_options`.
    Raises ``OSError`` when an address cannot be bound."""
    asyncio.run(_serve(args, data_dir))
