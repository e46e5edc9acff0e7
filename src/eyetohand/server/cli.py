"""What ``eyetohand serve`` runs: the workbench page and JSON API (uvicorn), and optionally the TCP line
service. The command itself (its options) is :mod:`eyetohand.cli.serve`."""

from __future__ import annotations

import asyncio
import ipaddress
import socket
from pathlib import Path

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
            raise ServeError("--tcp needs --calibration NAME (the stored calibration to serve)")
    elif args.calibration:
        raise ServeError("--calibration is for the TCP service: give --tcp HOST:PORT too")


async def _serve(args, data_dir) -> None:
    import uvicorn

    from .app import LOOPBACK_HOSTS, create_app
    from .storage import DB_NAME, Ambiguous, NotFound, StorageError, Store
    from .tcp import LineServer

    http_sock = bind_http(args.host, args.port)
    line_server = None
    if args.tcp:
        host, port = parse_hostport(args.tcp)
        if not (Path(data_dir) / DB_NAME).is_file():  # a look-up must not create an empty database
            http_sock.close()
            raise ServeError(f"--calibration: {args.calibration!r} not found: no calibrations are stored in "
                             f"{data_dir} yet (no {DB_NAME}); save one in the workbench first")
        store = Store(data_dir, wait_s=args.db_wait)
        try:
            rec = store.find(args.calibration)
            ver = store.version(rec.id)
        except (NotFound, Ambiguous, StorageError) as exc:
            http_sock.close()
            raise ServeError(f"--calibration: {str(exc).strip(chr(39))} in {store.path}") from None
        finally:
            store.close()
        from ..calibration import Calibration

        cal = Calibration.from_dict(ver.calibration, f"calibration {rec.name!r}")
        line_server = LineServer(cal, host, port, token=args.token)
        try:
            await line_server.start()
        except OSError as exc:
            http_sock.close()
            raise ServeError(f"--tcp {args.tcp}: cannot listen there ({exc.strerror or exc})") from None
        print(f"TCP: {host}:{line_server.port} maps 'u,v[,z]' lines with calibration {rec.name!r} "
              f"(id {rec.id}, version {ver.version}, model {cal.model_name})", flush=True)

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
