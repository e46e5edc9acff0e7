"""What ``eyetohand serve`` runs: the workbench page and JSON API (uvicorn), and optionally the TCP line
service, on an event loop of its own in a thread (:class:`~eyetohand.server.tcp.LoopThread`: one robot
client's p50 went from 1.7-3.2x a minimal asyncio line server to 1.2-1.4x in five of six runs,
benchmarks/bench_server.py).
The command itself (its options) is :mod:`eyetohand.cli.serve`."""

from __future__ import annotations

import asyncio
import ipaddress
import socket
from collections.abc import Callable
from pathlib import Path

from eyetohand.core import InputError


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
    camera = getattr(args, "camera", None)
    conveyor = getattr(args, "conveyor", None)
    if args.tcp:
        host, _ = parse_hostport(args.tcp)
        if not is_loopback(host) and not args.token:
            raise ServeError(f"--tcp {args.tcp}: a non-loopback address needs --token T; refusing to start")
        if not (args.calibration or camera or conveyor):
            raise ServeError(
                "--tcp needs --calibration NAME, id:N or FILE.json (the calibration to serve), "
                "--camera URI (collect one) or --conveyor FILE"
            )
    else:
        for flag, given in (
            ("--calibration", args.calibration),
            ("--camera", camera),
            ("--conveyor", conveyor),
            ("--collect-dir", getattr(args, "collect_dir", None)),
        ):
            if given:
                raise ServeError(f"{flag} is for the TCP service: give --tcp HOST:PORT too")
    first_line_s = getattr(args, "tcp_first_line_s", None)
    if first_line_s is not None and not 0 < first_line_s <= 3600:
        raise ServeError(f"--tcp-first-line: expected seconds in (0, 3600], got {first_line_s:g}")
    for addr in getattr(args, "robot_address", None) or ():
        try:
            ipaddress.ip_address(addr)
        except ValueError:
            raise ServeError(
                f"--robot-address: expected an IP address (e.g. 192.168.0.10), got {addr!r}"
            ) from None
    if getattr(args, "reply_format", "plain") != "plain" and not camera:
        raise ServeError("--reply-format is for the collection's CAL replies: give --camera URI too")

    args.calibration_file = None
    if args.calibration:
        path = calibration_path(args.calibration)
        if path is not None:
            from eyetohand.server.tcp import FixedCalibration

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


def store_save_fn(store, on_saved=None):
    """``save_fn(name, cal)`` for the Collector: a new version of calibration ``name`` in the
    server's database (a new calibration when the name is new); ``on_saved(record, cal)`` after."""

    def save(name: str, cal) -> None:
        request = {"source": "collection", "collection": name, "model": cal.model_name, "seed": 0}
        pairs = cal.pairs.to_records() if cal.pairs is not None else []
        check = cal.check_pairs.to_records() if cal.check_pairs is not None else None
        rec = store.by_name(name)
        if rec is None:
            rec = store.create(
                name, request, cal.to_dict(), pairs, check, note=f"collected ({len(pairs)} points)"
            )
        else:
            rec = store.add_version(
                rec.id, request, cal.to_dict(), pairs, check, note=f"collected ({len(pairs)} points)"
            )
        if on_saved is not None:
            on_saved(rec, cal)

    return save


def store_load_fn(store):
    """``load_fn(name) -> Calibration | None`` for the Collector: the current stored version."""
    from eyetohand.calibration import Calibration

    def load(name: str):
        rec = store.by_name(name)
        if rec is None:
            return None
        ver = store.version(rec.id)
        return Calibration.from_dict(ver.calibration, f"calibration {rec.name!r} version {ver.version}")

    return load


def one_calibration(server_fn, wanted: str | None) -> dict:
    """The Collector's options that make mapping lines and CAL CHECK use one calibration (docs/collection.md):
    BEGIN only for the served one (with ``--calibration``), CHECK checks what the mapping lines use."""
    from eyetohand.server.tcp import collection_rule, served_for_check

    return {"begin_rule": collection_rule(server_fn, wanted), "served_fn": served_for_check(server_fn)}


def tcp_options(args, commands: dict, busy_replies: dict) -> dict:
    """The LineServer's options from ``serve``'s: the command handlers, their busy replies, the robot's
    reserved addresses and the first-line grace."""
    from eyetohand.server.tcp import FIRST_LINE_S

    return {
        "commands": commands,
        "busy_replies": busy_replies,
        "robot_addresses": getattr(args, "robot_address", None) or (),
        "first_line_s": getattr(args, "tcp_first_line_s", None) or FIRST_LINE_S,
    }


async def _serve(args, data_dir) -> None:
    loops: list = []  # the line service's loop thread, stopped however _run_serve ends
    try:
        await _run_serve(args, data_dir, loops)
    finally:
        for t in loops:
            t.stop()


async def _run_serve(args, data_dir, loops: list) -> None:
    import uvicorn

    from eyetohand.server.app import LOOPBACK_HOSTS, create_app
    from eyetohand.server.storage import DB_NAME, Ambiguous, NotFound, StorageError, Store
    from eyetohand.server.tcp import LineServer, LoopThread, PendingCalibration, SameFile, StoredCalibration

    http_sock = bind_http(args.host, args.port)
    line_server = None
    tcp_loop: LoopThread | None = None
    collector = source = belt = app = None
    data_dir = Path(data_dir)
    camera, conveyor = getattr(args, "camera", None), getattr(args, "conveyor", None)
    store = None
    same_file: SameFile | None = None
    if args.tcp:
        host, port = parse_hostport(args.tcp)
        served = getattr(args, "calibration_file", None)  # a file, proved intact by check_options
        if served is None:
            # a look-up must not create an empty database (with a camera, CAL END creates the calibration)
            if args.calibration and not camera and not (data_dir / DB_NAME).is_file():
                http_sock.close()
                raise ServeError(
                    f"--calibration: {args.calibration!r} not found: no calibrations are stored "
                    f"in {data_dir} yet (no {DB_NAME}); save one in the workbench first"
                )
            store = Store(data_dir, wait_s=args.db_wait)
            same_file = SameFile(store)  # the database file as opened: TCP refuses once it is another
            served = PendingCalibration(args.calibration)
            try:
                if args.calibration:
                    try:
                        rec = store.find(args.calibration)
                        served = StoredCalibration(store, rec.id, same_file)
                    except NotFound:
                        if not camera:  # with a camera, CAL BEGIN <name> … CAL END creates it
                            raise
            except (NotFound, Ambiguous, StorageError, InputError) as exc:
                http_sock.close()
                store.close()
                raise ServeError(f"--calibration: {str(exc).strip(chr(39))} in {store.path}") from None
        if isinstance(served, StoredCalibration):
            what = (
                f"calibration {served.name!r} (id {served.cal_id}, version {served.version}, followed: a "
                "new version or a rollback takes effect within a second)"
            )
        elif isinstance(served, PendingCalibration):
            what = "no calibration yet (a collection creates it)"
        else:
            what = f"the file {served.label} (sha256 {served.sha256[:12]}…)"
        commands: dict[str, Callable[[str], str]] = {}
        busy_replies: dict[str, Callable[[str], str]] = {}
        # the line service runs on a loop of its own: the robot's lines never wait behind HTTP work
        tcp_loop = LoopThread()
        loops.append(tcp_loop)
        loop = tcp_loop.loop  # follow() is called on it from a collection's thread
        try:
            if camera:
                import eyetohand.sim  # noqa: F401  (the interfaces offer the virtual cell's sim: camera)
                from eyetohand.cell import Collector
                from eyetohand.vision import open_source

                source = open_source(camera)

                def on_saved(saved_rec, new_cal) -> None:
                    # the collected calibration is what the mapping lines use from now on
                    wanted = args.calibration or saved_rec.name
                    if line_server is not None and saved_rec.name == wanted and store is not None:
                        current = line_server.source
                        if isinstance(current, StoredCalibration) and current.cal_id == saved_rec.id:
                            current.poll()  # at once, not at the next poll
                        else:
                            line_server.follow(StoredCalibration(store, saved_rec.id, same_file), loop)
                    if app is not None:  # the workbench's cache of current versions
                        app.state.service.invalidate(saved_rec.id)

                if store is None:
                    store = Store(data_dir, wait_s=args.db_wait)
                    same_file = SameFile(store)
                collect_dir = args.collect_dir or (data_dir / "collect")
                collector = Collector(
                    collect_dir,
                    source,
                    save_fn=store_save_fn(store, on_saved),
                    load_fn=store_load_fn(store),
                    calibration=args.calibration,
                    reply_format=args.reply_format,
                    **one_calibration(lambda: line_server, args.calibration),
                )
                commands["CAL"] = collector.handle
                busy_replies["CAL"] = collector.refuse
            if conveyor:
                from eyetohand.cell import BeltProtocol

                belt = BeltProtocol(
                    conveyor, source=source, store_dir=args.collect_dir or (data_dir / "collect")
                )
                commands["BELT"] = belt.handle
        except InputError as exc:
            http_sock.close()
            if store is not None:
                store.close()
            raise ServeError(str(exc).splitlines()[0]) from None
        line_server = LineServer(
            served, host, port, token=args.token, **tcp_options(args, commands, busy_replies)
        )
        try:
            await tcp_loop.call(line_server.start())
        except OSError as exc:
            http_sock.close()
            raise ServeError(f"--tcp {args.tcp}: cannot listen there ({exc.strerror or exc})") from None
        print(f"TCP: {host}:{line_server.port} maps 'u,v[,z]' lines with {what}", flush=True)
        if collector is not None:
            print(
                f"TCP: 'CAL …' lines collect with camera {camera} (journal {collector.journal.path}, "
                f"replies {args.reply_format})",
                flush=True,
            )
        if belt is not None:
            print(f"TCP: 'BELT …' lines map with conveyor {conveyor}", flush=True)

    app = create_app(
        data_dir,
        token=args.token,
        db_wait_s=args.db_wait,
        allowed_hosts=LOOPBACK_HOSTS if is_loopback(args.host) else None,
    )
    if collector is not None:
        from eyetohand.server.routes.collect import CameraView

        app.state.collect = CameraView(collector, source)
    port = http_sock.getsockname()[1]
    print(f"workbench: http://{args.host}:{port}/  (API docs: /docs; data: {data_dir})", flush=True)
    config = uvicorn.Config(app, log_level=args.log_level, timeout_graceful_shutdown=5)
    server = uvicorn.Server(config)
    try:
        await server.serve(sockets=[http_sock])
    finally:
        if line_server is not None and tcp_loop is not None:
            tcp_loop.loop.call_soon_threadsafe(line_server.close)
            tcp_loop.stop()  # before the collector and the store it uses are closed
        if collector is not None:
            collector.close()
        if source is not None:
            source.close()
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
