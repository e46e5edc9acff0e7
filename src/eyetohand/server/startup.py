"""What ``eyetohand serve`` runs: the workbench page and JSON API (uvicorn), and optionally the TCP line
service, on an event loop of its own in a thread (:class:`~eyetohand.positioning.tcp.LoopThread`: one robot
client's p50 went from 1.7-3.2x a minimal asyncio line server to 1.2-1.4x in five of six runs,
benchmarks/bench_server.py).
The command itself (its options) is :mod:`eyetohand.cli.serve`."""

from __future__ import annotations

import asyncio
import datetime as dt
import hashlib
import importlib.util
import ipaddress
import logging
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from eyetohand.calibration import Calibration, load_sign_key
from eyetohand.cell import Collector, LineReplies
from eyetohand.core import AuthBackoff, InputError, Role, current_actor, output_units
from eyetohand.positioning import (
    FIRST_LINE_S,
    HTTP_BUSY,
    LIMITS,
    FileBudgetError,
    FixedCalibration,
    LineServer,
    Locator,
    LoopThread,
    PendingCalibration,
    PlcServices,
    ServerCertificate,
    Slots,
    file_budget,
    guarded_factory,
    parse_allow,
    quiet_accept_errors,
    reachable_addresses,
)
from eyetohand.server.audit import acting_as
from eyetohand.server.config import ServeConfig, ServeError, is_loopback, parse_hostport
from eyetohand.server.plant import CellBeat
from eyetohand.server.storage import Ambiguous, NotFound, StorageError
from eyetohand.server.stored import SameFile, StoredCalibration, collection_rule, served_for_check
from eyetohand.server.stores import StoreRef, StoreRefError, open_store
from eyetohand.vision import open_source

if TYPE_CHECKING:
    from collections.abc import Mapping

    from eyetohand.cell import BeltProtocol
    from eyetohand.positioning import FileBudget, Limit, Served
    from eyetohand.server.service import Service
    from eyetohand.server.storage import Store


def check_options(args) -> ServeConfig:
    """Refuse unsafe or incomplete option sets before anything binds; the checked options as one
    typed value (what :func:`serve` takes)."""
    check_signing_options(args)  # --sign-key, --require-signed: before --calibration FILE is read
    check_store_option(args)
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
            ("--calibration", None if _plc_wanted(args) else args.calibration),
            ("--camera", camera),
            ("--conveyor", conveyor),
            ("--collect-dir", getattr(args, "collect_dir", None)),
        ):
            if given and flag == "--calibration":
                raise ServeError(
                    "--calibration is for the TCP, Modbus and OPC UA services: give --tcp, --modbus "
                    "or --opcua HOST:PORT too"
                )
            if given:
                raise ServeError(f"{flag} is for the TCP service: give --tcp HOST:PORT too")
    check_plc_options(args)
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
    check_line_options(args)

    args.calibration_file = None
    if args.calibration:
        path = calibration_path(args.calibration)
        if path is not None:
            try:
                args.calibration_file = signed_file(FixedCalibration, path, args)
            except InputError as exc:
                raise ServeError(f"--calibration: {exc}") from None
    return ServeConfig.from_args(args)


def check_store_option(args) -> None:
    """``--store URL``: a reference this program can open (docs/store.md)."""
    given = getattr(args, "store", None)
    if given:
        try:
            ref = StoreRef.parse(given)
        except StoreRefError as exc:
            raise ServeError(f"--store {exc}") from None
        if ref.shared and importlib.util.find_spec("psycopg") is None:
            raise ServeError(
                f"--store {ref}: a PostgreSQL store needs psycopg: pip install 'eyetohand[postgres]'"
            )


def store_ref(cfg: ServeConfig, data_dir):
    """The store ``serve`` uses: ``--store``, else the SQLite database in the data folder."""
    return StoreRef.parse(cfg.store or data_dir)


def open_store_or_refuse(ref, cfg: ServeConfig, *, create: bool, http_sock=None):
    """The store ``ref`` names; a store that cannot be opened (unreachable, a newer schema, psycopg
    missing) is one :class:`ServeError` line naming it (``http_sock`` closed first)."""
    try:
        return open_store(ref, cfg.db_wait_s, create=create)
    except (StorageError, StoreRefError) as exc:
        if http_sock is not None:
            http_sock.close()
        raise ServeError(f"--store {ref}: {exc}") from None


def check_line_options(args) -> None:
    """``--reply-format``, ``--units``, ``--angle-units``: the TCP line service's words and units
    (``args.output_units``); refused without ``--tcp`` (Modbus registers are in µm and 0.001 deg, OPC UA
    in mm and deg whatever these say: docs/plc.md)."""
    units, angle = getattr(args, "units", None), getattr(args, "angle_units", None)
    try:
        args.output_units = output_units(units, angle)
    except InputError as exc:
        raise ServeError(str(exc)) from None
    if args.tcp:
        return
    for flag, given in (
        ("--reply-format", getattr(args, "reply_format", "plain") != "plain"),
        ("--units", units is not None),
        ("--angle-units", angle is not None),
    ):
        if given:
            raise ServeError(
                f"{flag} is for the TCP line service: give --tcp HOST:PORT too (Modbus registers are "
                "in um and 0.001 deg, OPC UA in mm and deg: docs/plc.md)"
            )


def check_plc_options(args) -> None:
    """``--modbus`` and ``--opcua``: addresses, who may connect, and something to map with."""
    modbus, opcua = getattr(args, "modbus", None), getattr(args, "opcua", None)
    allow = getattr(args, "allow_modbus_from", None)
    args.modbus_allow = None  # None: every client (a loopback address); else the parsed networks
    if allow and not modbus:
        raise ServeError("--allow-modbus-from is for the Modbus server: give --modbus HOST:PORT too")
    for flag, given, package in (("--modbus", modbus, "pymodbus"), ("--opcua", opcua, "asyncua")):
        if given and importlib.util.find_spec(package) is None:
            raise ServeError(f"{flag} needs the {package} package: pip install 'eyetohand[plc]'")
    if modbus:
        host, _ = parse_hostport(modbus, "--modbus")
        try:
            nets = parse_allow(allow.split(",")) if allow else []
        except ValueError as exc:
            raise ServeError(f"--allow-modbus-from: {exc}") from None
        if not is_loopback(host) and not nets:
            raise ServeError(
                f"--modbus {modbus}: Modbus has no authentication, so a non-loopback address needs "
                "--allow-modbus-from ADDR,... (the PLCs' addresses or networks); refusing to start"
            )
        args.modbus_allow = nets or None
    if opcua:
        host, _ = parse_hostport(opcua, "--opcua")
        if not is_loopback(host) and not args.token:
            raise ServeError(
                f"--opcua {opcua}: a non-loopback address needs --token T (OPC UA user "
                "'eyetohand', the token as password); refusing to start"
            )
    check_opcua_certificate(args, opcua)
    for flag, given in (("--modbus", modbus), ("--opcua", opcua)):
        if given and not args.calibration and not (args.tcp and getattr(args, "camera", None)):
            raise ServeError(
                f"{flag} needs --calibration NAME, id:N or FILE.json (the calibration to serve), or "
                "--tcp with --camera (a collection creates it)"
            )


def check_opcua_certificate(args, opcua: str | None) -> None:
    """``--opcua-cert/--opcua-key``: both or neither, with ``--opcua``; the pair read and checked now,
    before anything binds (``args.opcua_security``; None: the data folder's own, made at start)."""
    cert, key = getattr(args, "opcua_cert", None), getattr(args, "opcua_key", None)
    args.opcua_security = None
    if (cert or key) and not opcua:
        raise ServeError("--opcua-cert/--opcua-key are the OPC UA server's: give --opcua HOST:PORT too")
    if bool(cert) != bool(key):
        raise ServeError("--opcua-cert and --opcua-key go together: the certificate and its private key")
    if cert and key:
        try:
            args.opcua_security = ServerCertificate.from_files(cert, key)
        except InputError as exc:
            raise ServeError(str(exc)) from None


# ---- --sign-key / --require-signed / --allow-host (the http worktree; one block for easy merges)
def check_signing_options(args) -> None:
    """``args.sign_key_bytes``: the key of ``--sign-key FILE`` (None without); ``--require-signed``
    needs it. Every calibration file served (``--calibration FILE``) or imported over HTTP must then
    carry this key's signature, and exports are signed with it."""
    args.sign_key_bytes = None
    path = getattr(args, "sign_key", None)
    if path is not None:
        try:
            args.sign_key_bytes = load_sign_key(path)
        except InputError as exc:
            raise ServeError(f"--sign-key {exc}") from None
    if getattr(args, "require_signed", False) and args.sign_key_bytes is None:
        raise ServeError("--require-signed needs --sign-key FILE (the key the files must be signed with)")


def signed_file(fixed_cls, path, args):
    """``--calibration FILE`` loaded with the signature rules (``fixed_cls``: FixedCalibration)."""
    p = Path(path)
    key = getattr(args, "sign_key_bytes", None)
    cal = Calibration.load(p, sign_key=key, require_signed=bool(getattr(args, "require_signed", False)))
    return fixed_cls(cal, str(p.resolve()), hashlib.sha256(p.read_bytes()).hexdigest())


def allowed_hosts(cfg: ServeConfig) -> list[str] | None:
    """The Host names HTTP answers: on a loopback address the loopback names, the bound address and
    every ``--allow-host``; elsewhere any (None) unless ``--allow-host`` names them (then those, the
    bound address and the loopback names)."""
    from eyetohand.server.app import LOOPBACK_HOSTS  # FastAPI: loaded with the app, never on a refused option

    extra = [h.strip().lower() for h in cfg.allow_hosts if h.strip()]
    if not is_loopback(cfg.host) and not extra:
        return None
    host = cfg.host.lower()
    bound = [host, f"[{host}]"] if ":" in host and not host.startswith("[") else [host]
    return [*LOOPBACK_HOSTS, *bound, *extra]


# ---- end of the --sign-key / --require-signed / --allow-host block


def calibration_path(ref: str):
    """The file a ``--calibration`` value names, or None for a stored calibration.

    Unambiguous by its form: ``file:PATH``, or a value ending in ``.json`` or containing a path
    separator, is a file; ``id:N`` is the stored calibration with id N; ``name:NAME`` (or any other
    value) is a stored calibration's name (digits alone: the id, refused when another's name)."""
    if ref.startswith("file:"):
        return Path(ref[5:])
    if ref.lower().startswith(("id:", "name:")):
        return None
    if ref.lower().endswith(".json") or "/" in ref or (os.sep != "/" and os.sep in ref):
        return Path(ref)
    return None


def store_save_fn(store, on_saved=None, user: str = "robot"):
    """``save_fn(name, cal)`` for the Collector: a new version of calibration ``name`` in the
    server's database (a new calibration when the name is new), audited as ``cal_end`` by the TCP
    connection's token holder (its ``AUTH``), else ``user``; ``on_saved(record, cal)`` after."""

    def save(name: str, cal) -> None:
        actor = current_actor()
        with acting_as(actor if actor.named else user):
            _save(name, cal)

    def _save(name: str, cal) -> None:
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


def store_check_fn(store, user: str):
    """``on_check(record)`` for the Collector: a CAL CHECK of a stored calibration audited as
    ``check`` (its point and error in the note) by the connection's token holder, else ``user``. The
    record is in the collection's history file already: a store that cannot be written now is logged,
    the robot still gets its answer."""

    def on_check(rec: dict) -> None:
        found = store.by_name(rec["name"]) if rec.get("name") else None
        if found is None:
            return
        x, y, z = rec["xyz_mm"]
        note = (
            f"CAL CHECK at ({x:.3f}, {y:.3f}, {z:.3f}) mm: error {rec['error_mm']:.4f} mm "
            f"(dx {rec['dx_mm']:.4f}, dy {rec['dy_mm']:.4f})"
        )
        try:
            actor = current_actor()
            with acting_as(actor if actor.named else user):
                store.audit_event(found.id, "check", rec.get("version") or found.current_version, note)
        except StorageError as exc:
            logging.getLogger("eyetohand.store").warning("CAL CHECK not audited: %s", exc)

    return on_check


def tcp_user(cfg: ServeConfig) -> str:
    """Who the audit trail names for a change made over TCP (CAL END) when the connection named no
    token holder (a server without tokens): ``robot``."""
    return "robot"


def store_load_fn(store):
    """``load_fn(name) -> Calibration | None`` for the Collector: the current stored version."""

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
    return {"begin_rule": collection_rule(server_fn, wanted), "served_fn": served_for_check(server_fn)}


def tcp_options(
    cfg: ServeConfig,
    commands: dict,
    busy_replies: dict,
    backoff: AuthBackoff | None = None,
    limits: Mapping[str, Limit] | None = None,
) -> dict:
    """The LineServer's options from ``serve``'s: the token, the command handlers, their busy replies,
    the robot's reserved addresses, the first-line grace, the reply format and units, the
    failed-AUTH backoff (shared with HTTP and OPC UA) and its connections (``limits["tcp"]``)."""
    bound = (
        {}
        if limits is None
        else {
            "max_clients": limits["tcp"].total,
            "max_per_peer": limits["tcp"].per_address,
            "backlog": limits["tcp"].backlog,
        }
    )
    return {
        **bound,
        "token": cfg.token_table or None,
        "command_roles": {"CAL": Role.OPERATOR},  # a viewer maps and locates, never collects
        "commands": commands,
        "busy_replies": busy_replies,
        "robot_addresses": cfg.robot_addresses,
        "first_line_s": cfg.first_line_s or FIRST_LINE_S,
        "reply_format": cfg.reply_format,
        "units": cfg.units,
        "auth_backoff": backoff,
    }


def _not_a_cancellation(record: logging.LogRecord) -> bool:
    """A logging filter: False for a record of a cancelled task (Ctrl-C), True for any other."""
    exc = record.exc_info[1] if record.exc_info else None
    return not isinstance(exc, asyncio.CancelledError | KeyboardInterrupt)


async def _serve(cfg: ServeConfig, data_dir) -> None:
    loops: list = []  # the line service's loop thread, stopped however _run_serve ends
    try:
        await _run_serve(cfg, data_dir, loops)
    finally:
        for t in loops:
            t.stop()


@dataclass
class _Started:
    """What ``serve`` has started so far (closed in reverse by :meth:`close`, however it ends): the
    store and the served calibration, the line service with its collector, camera, belt and LOCATE,
    the PLC services, the app. The collection's ``on_saved`` reads it when a calibration is saved."""

    loops: list
    # failed tokens per address: one count for TCP AUTH, HTTP and the OPC UA user token
    backoff: AuthBackoff = field(default_factory=AuthBackoff)
    store: Store | None = None
    same_file: SameFile | None = None
    served: Served | None = None
    line_server: LineServer | None = None
    tcp_loop: LoopThread | None = None
    collector: Collector | None = None
    source: Any = None  # a camera (vision.Source)
    belt: BeltProtocol | None = None
    locator: Locator | None = None
    plc: PlcServices | None = None
    plc_loop: LoopThread | None = None
    budget: FileBudget | None = None  # the listeners' connections within the process's file handles
    app: Any = None  # the FastAPI app
    service: Service | None = None  # the app's (its store followed: /api/health, OPC UA StoreState)

    def store_reachable(self) -> bool | None:
        """Whether the store can be read now, as ``/api/health`` says (None until the app follows it)."""
        return None if self.service is None else self.service.store_reachable()

    def current_or_none(self) -> Served | None:
        """What the services serve now, or None when none is served (the workbench alone)."""
        return self.line_server.source if self.line_server is not None else self.served

    def current(self) -> Served:
        """The calibration the services serve now (the line service's, which a collection may change)."""
        if self.line_server is not None:
            return self.line_server.source
        assert self.served is not None  # read only once _served_calibration ran
        return self.served

    async def close(self) -> None:
        if self.plc is not None and self.plc_loop is not None:
            await self.plc_loop.call(self.plc.close())
        if self.line_server is not None and self.tcp_loop is not None:
            self.tcp_loop.loop.call_soon_threadsafe(self.line_server.close)
            self.tcp_loop.stop()  # before the collector and the store it uses are closed
        for part in (self.collector, self.source, self.store):
            if part is not None:
                part.close()


def connection_budget(cfg: ServeConfig) -> FileBudget:
    """The soft RLIMIT_NOFILE raised toward the hard one, and the connections of the listeners ``cfg``
    asks for fitted within it (:func:`eyetohand.positioning.limits.file_budget`); too few handles is a
    :class:`ServeError` saying how to raise them."""
    given = {"http": True, "tcp": cfg.tcp is not None, "modbus": cfg.modbus is not None}
    given["opcua"] = cfg.opcua is not None
    try:
        return file_budget({k: LIMITS[k] for k, on in given.items() if on})
    except FileBudgetError as exc:
        raise ServeError(str(exc)) from None


async def _run_serve(cfg: ServeConfig, data_dir, loops: list) -> None:
    import uvicorn  # uvicorn: only once every option is checked and every service refused or started

    budget = connection_budget(cfg)
    quiet_accept_errors(asyncio.get_running_loop(), "HTTP")
    http_sock = bind_http(cfg.host, cfg.port)
    # the database is created only at a first start: later, a missing one is an error, never a new one
    ref = store_ref(cfg, data_dir)
    fresh_db = not ref.exists()
    data_dir = Path(data_dir)
    run = _Started(loops, budget=budget)
    if cfg.tcp or cfg.plc_wanted:
        run.served, run.store, run.same_file = _served_calibration(
            cfg, ref, cfg.camera, http_sock, create=fresh_db
        )
    if cfg.tcp is not None:
        await _start_tcp(cfg, run, data_dir, ref, http_sock, fresh_db)
    if cfg.plc_wanted:
        locate = None if run.locator is None else run.locator.locate
        run.plc, run.plc_loop = await _start_plc(
            cfg,
            run.current,
            run.served,
            poll=run.line_server is None,
            locate=locate,
            http_sock=http_sock,
            auth_backoff=run.backoff,
            data_dir=data_dir,
            store_reachable=run.store_reachable,
            limits=budget.limits,
        )
        loops.append(run.plc_loop)

    run.app = app = _make_app(cfg, ref, fresh_db, http_sock, run.current_or_none, run.backoff)
    run.service = app.state.service
    line_server = run.line_server
    if line_server is not None:  # a change the store notifies reaches the robots' lines at once
        run.service.change_listeners.append(lambda _cal_id: line_server.wake())
    if run.collector is not None:
        from eyetohand.server.routes.collect import CameraView  # FastAPI: loaded with the app above

        app.state.collect = CameraView(run.collector, run.source)
    port = http_sock.getsockname()[1]
    print(f"workbench: http://{cfg.host}:{port}/  (API docs: /docs; data: {data_dir})", flush=True)
    if (access := cfg.access_line()) is not None:
        print(access, flush=True)
    print(budget.line(), flush=True)
    # uvicorn's h11 protocol, with head and body deadlines (slowloris): only once the app is built
    from eyetohand.server.protocol import GuardedH11Protocol

    # uvicorn calls Config.http (a class or any factory) with its keywords for each connection
    slots = Slots(f"HTTP {cfg.host}:{port}", budget.limits["http"], replace_own=True)
    http = guarded_factory(
        GuardedH11Protocol, slots, None, None, goodbye=HTTP_BUSY, waiting=GuardedH11Protocol.waiting
    )
    config = uvicorn.Config(
        app,
        log_level=cfg.log_level,
        timeout_graceful_shutdown=5,
        http=cast(Any, http),
        backlog=slots.limit.backlog,
    )
    # after Config (it configures uvicorn's loggers): Ctrl-C while the app starts cancels uvicorn's
    # lifespan task, which it logs as an ERROR with two tracebacks; the command ends with one line
    logging.getLogger("uvicorn.error").addFilter(_not_a_cancellation)
    server = uvicorn.Server(config)
    try:
        await server.serve(sockets=[http_sock])
    finally:
        await run.close()


async def _start_tcp(cfg: ServeConfig, run: _Started, data_dir: Path, ref, http_sock, fresh_db: bool) -> None:
    """Start the line service (and its CAL, BELT and LOCATE commands) on a loop of its own: the robot's
    lines never wait behind HTTP work. Prints its start-up lines; a refusal closes ``http_sock``."""
    assert cfg.tcp is not None and run.served is not None  # _served_calibration ran for --tcp
    host, port = cfg.tcp
    what = run.served.describe()
    commands: dict[str, Callable[[str], str]] = {}
    busy_replies: dict[str, Callable[[str], str]] = {}
    run.tcp_loop = LoopThread()
    run.loops.append(run.tcp_loop)
    quiet_accept_errors(run.tcp_loop.loop, "TCP")
    try:
        if cfg.camera:
            _open_collection(cfg, run, data_dir, ref, http_sock, fresh_db, commands, busy_replies)
        if cfg.conveyor:
            run.belt = open_belt(cfg, run.source, data_dir)
            commands["BELT"] = run.belt.handle
    except InputError as exc:
        http_sock.close()
        if run.store is not None:
            run.store.close()
        raise ServeError(str(exc).splitlines()[0]) from None
    run.line_server = LineServer(
        run.served,
        host,
        port,
        **tcp_options(cfg, commands, busy_replies, run.backoff, run.budget.limits if run.budget else None),
    )
    try:
        await run.tcp_loop.call(run.line_server.start())
    except OSError as exc:
        http_sock.close()
        raise ServeError(f"--tcp {cfg.tcp_text}: cannot listen there ({exc.strerror or exc})") from None
    what += units_note(cfg)
    print(f"TCP: {host}:{run.line_server.port} maps 'u,v[,z]' lines with {what}", flush=True)
    if run.collector is not None:
        print(
            f"TCP: 'CAL …' lines collect with camera {cfg.camera} (journal {run.collector.journal.path}, "
            f"replies {cfg.reply_format})",
            flush=True,
        )
    if run.belt is not None:
        print(f"TCP: 'BELT …' lines map with conveyor {cfg.conveyor}", flush=True)
    if run.locator is not None:
        print(f"TCP: 'LOCATE …' lines find parts with camera {cfg.camera}{sim_note(commands)}", flush=True)


def _open_collection(
    cfg: ServeConfig,
    run: _Started,
    data_dir: Path,
    ref,
    http_sock,
    fresh_db: bool,
    commands: dict,
    busy_replies: dict,
) -> None:
    """``--camera``: the camera, the CAL collection (saving into the store, after which the mapping lines
    serve what it saved) and LOCATE, added to ``commands``."""
    # eyetohand.sim (the virtual cell, ~20 modules): only with --camera; it offers the sim: camera
    import eyetohand.sim  # noqa: F401

    assert cfg.camera is not None and run.tcp_loop is not None
    run.source = open_source(cfg.camera)
    loop = run.tcp_loop.loop  # follow() is called on it from a collection's thread

    def on_saved(saved_rec, new_cal) -> None:
        # the collected calibration is what the mapping lines use from now on
        wanted = cfg.calibration or saved_rec.name
        if run.line_server is not None and saved_rec.name == wanted and run.store is not None:
            current = run.line_server.source
            if current.identity().cal_id == saved_rec.id:
                current.poll()  # at once, not at the next poll
            else:
                stored = StoredCalibration(run.store, saved_rec.id, run.same_file, cfg.signing)
                run.line_server.follow(stored, loop)
        if run.app is not None:  # the workbench's cache of current versions
            run.app.state.service.invalidate(saved_rec.id)

    if run.store is None:
        run.store = open_store_or_refuse(ref, cfg, create=fresh_db, http_sock=http_sock)
        run.same_file = SameFile(run.store)
    run.collector = Collector(
        cfg.collect_dir or (data_dir / "collect"),
        run.source,
        save_fn=store_save_fn(run.store, on_saved, tcp_user(cfg)),
        on_check=store_check_fn(run.store, tcp_user(cfg)),
        load_fn=store_load_fn(run.store),
        calibration=cfg.calibration,
        reply_format=cfg.reply_format,
        **one_calibration(lambda: run.line_server, cfg.calibration),
    )
    commands["CAL"] = run.collector.handle
    run.locator = add_locate(commands, run.source, run.current, cfg)
    busy_replies["CAL"] = run.collector.refuse


async def _start_plc(
    cfg: ServeConfig,
    current,
    served,
    *,
    poll: bool,
    locate,
    http_sock,
    auth_backoff: AuthBackoff | None = None,
    data_dir: Path | None = None,
    store_reachable: Callable[[], bool | None] | None = None,
    limits: Mapping[str, Limit] | None = None,
):
    """Start ``--modbus`` / ``--opcua`` on a loop of their own, mapping with ``current()`` (the TCP
    service's served calibration when there is one, else ``served``, followed by polling when
    ``poll``; ``store_reachable()``: OPC UA's ``StoreState``); print their start-up lines. Returns
    (the services, their loop). OPC UA's certificate:
    ``--opcua-cert/--opcua-key``, else the one in ``data_dir``/opcua (created at the first start)."""
    security = cfg.opcua_security
    if cfg.opcua is not None and security is None and data_dir is not None:
        try:
            security = ServerCertificate.in_folder(
                Path(data_dir) / "opcua", reachable_addresses(cfg.opcua[0])
            )
        except (InputError, OSError) as exc:
            http_sock.close()
            raise ServeError(f"--opcua: the server certificate: {exc}") from None

    plc = PlcServices(
        current,
        modbus=cfg.modbus,
        word_order=cfg.modbus_word_order,
        allow_from=list(cfg.modbus_allow) or None,
        opcua=cfg.opcua,
        token=cfg.token_table or None,
        locate=locate,
        auth_backoff=auth_backoff,
        security=security,
        store_reachable=store_reachable,
        limits=LIMITS if limits is None else limits,
    )
    plc_loop = LoopThread("eyetohand-plc")
    quiet_accept_errors(plc_loop.loop, "Modbus/OPC UA")
    try:
        await plc_loop.call(plc.start(poll=poll))
    except OSError as exc:
        plc_loop.stop()
        http_sock.close()
        raise ServeError(f"{plc.starting}: cannot listen there ({exc.strerror or exc})") from None
    for line in plc.lines(served.describe()):
        print(line, flush=True)
    return plc, plc_loop


# ---- LOCATE and the sim: camera's SIM lines (the locate worktree; one block for easy merges)
def add_locate(commands: dict, source, served, cfg: ServeConfig):
    """The camera's :class:`~eyetohand.cell.Locator`, its line command ``LOCATE`` added to
    ``commands`` (and, for a ``sim:`` camera, ``SIM``: parts on the virtual table). ``served()``: the
    calibration in force, read at every LOCATE."""
    from eyetohand.sim import SimSource, sim_command  # eyetohand.sim: only with --camera

    locator = Locator(source, served, reply_format=cfg.reply_format, units=cfg.units)
    commands["LOCATE"] = locator.handle
    if isinstance(source, SimSource):
        commands["SIM"] = lambda line: sim_command(source, line)
    return locator


def open_belt(cfg: ServeConfig, source, data_dir: Path):
    """The BELT commands' protocol over ``--conveyor`` (its refusals in the line service's format)."""
    # the conveyor (cell.conveyor: its file, fit and report, ~15 modules): only with --conveyor
    from eyetohand.cell import BeltProtocol

    return BeltProtocol(
        cfg.conveyor,
        source=source,
        store_dir=cfg.collect_dir or (data_dir / "collect"),
        replies=LineReplies(cfg.reply_format, cfg.units),
    )


def units_note(cfg: ServeConfig) -> str:
    """The start-up line's note of the line service's words and units, when not plain mm and deg."""
    u = cfg.units
    parts = [] if u.is_default else [f"answers in {u.length} and {u.angle}"]
    if cfg.reply_format != "plain":
        parts.append(f"replies {cfg.reply_format}")
    return f" ({'; '.join(parts)})" if parts else ""


def sim_note(commands: dict) -> str:
    return ", 'SIM …' lines place and pick the virtual parts" if "SIM" in commands else ""


# ---- end of the LOCATE block


def cell_heartbeat(cfg: ServeConfig, http_sock, source_fn):
    """The plant view's heartbeat of this serve (:class:`~eyetohand.server.plant.CellBeat`): its
    HTTP address and what its robots are answered with now (``source_fn()``: the served calibration,
    None for the workbench alone)."""
    started = dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")
    url = f"http://{cfg.host}:{http_sock.getsockname()[1]}"

    def beat() -> CellBeat:
        src = source_fn()
        who = src.identity() if src is not None else None  # a stored calibration: its id and version
        if who is not None and who.cal_id is not None:
            return CellBeat.of_this_process(url, who.cal_id, who.name, who.version, started)
        return CellBeat.of_this_process(url, None, who.file if who is not None else "", None, started)

    return beat


def _make_app(cfg: ServeConfig, ref, fresh_db: bool, http_sock, source_fn, backoff: AuthBackoff):
    """The workbench's app on the store ``ref`` (beating as :func:`cell_heartbeat`; ``backoff``: failed
    tokens per address, shared with TCP and OPC UA); a store that cannot be opened is one
    :class:`ServeError` line (exit 2)."""
    from eyetohand.server.app import create_app  # FastAPI: only once the options are checked

    try:
        return create_app(
            ref,
            token=cfg.token_table or None,
            db_wait_s=cfg.db_wait_s,
            allowed_hosts=allowed_hosts(cfg),
            create_db=fresh_db,
            sign_key=cfg.sign_key,
            require_signed=cfg.require_signed,
            heartbeat=cell_heartbeat(cfg, http_sock, source_fn),
            auth_backoff=backoff,
        )
    except (StorageError, StoreRefError) as exc:  # unreachable, a newer schema: one line (exit 2)
        http_sock.close()
        raise ServeError(f"--store {ref}: {exc}") from None


def _plc_wanted(args) -> bool:
    return bool(getattr(args, "modbus", None) or getattr(args, "opcua", None))


def _served_calibration(
    cfg: ServeConfig, ref, camera, http_sock, *, create: bool
) -> tuple[Served, Store | None, SameFile | None]:
    """(the served-calibration object, the store or None, its :class:`SameFile` or None) for
    ``--calibration``: a file (proved by
    check_options), a stored calibration (followed), or none yet (with a camera, a collection creates
    it). A refusal closes ``http_sock`` and raises :class:`ServeError`. ``create``: the database may be
    created (a first start only)."""
    fixed = cfg.calibration_file  # a file, proved intact by check_options
    if fixed is not None:
        return fixed, None, None
    # a look-up must not create an empty database (with a camera, CAL END creates the calibration)
    if cfg.calibration and not camera and not ref.exists():
        http_sock.close()
        raise ServeError(
            f"--calibration: {cfg.calibration!r} not found: no calibrations are stored "
            f"in {ref.path.parent} yet (no {ref.path.name}); save one in the workbench first"
        )
    store = open_store_or_refuse(ref, cfg, create=create, http_sock=http_sock)
    same_file = SameFile(store)  # the database file as opened: TCP refuses once it is another
    served: Served = PendingCalibration(cfg.calibration)
    try:
        if cfg.calibration:
            try:
                rec = store.find(cfg.calibration)
                served = StoredCalibration(store, rec.id, same_file, cfg.signing)
            except NotFound:
                if not camera:  # with a camera, CAL BEGIN <name> … CAL END creates it
                    raise
    except (NotFound, Ambiguous, StorageError, InputError) as exc:
        http_sock.close()
        store.close()
        raise ServeError(f"--calibration: {str(exc).strip(chr(39))} in {store.where}") from None
    return served, store, same_file


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


def serve(cfg: ServeConfig, data_dir) -> None:
    """Run the workbench (and the TCP service with ``cfg.tcp``) until stopped; ``cfg`` what
    :func:`check_options` returned for ``eyetohand serve``'s options (:mod:`eyetohand.cli.serve`).
    Raises ``OSError`` when an address cannot be bound."""
    asyncio.run(_serve(cfg, data_dir))
