"""``eyetohand serve``: the calibration workbench (web page + JSON API) and the positioning service (TCP
lines, Modbus TCP, OPC UA).

Parses the options and calls :func:`eyetohand.server.startup.serve`; the server is imported only when
the command runs (its dependencies are the heaviest of the package)."""

from __future__ import annotations

import os
import sys


def cmd_serve(args) -> int:
    from eyetohand.server import check_options, default_data_dir, serve

    args.token = args.token or os.environ.get("EYETOHAND_TOKEN") or None
    # ---- --token-file (http worktree): the token read from a file, so no process listing shows it
    if getattr(args, "token_file", None) is not None:
        args.token = read_token_file(args.token_file, given=args.token is not None)
    # ---- end --token-file
    config = check_options(args)  # the options as one typed value, checked once
    data_dir = args.data or default_data_dir()
    try:
        serve(config, data_dir)
    except OSError as exc:
        print(f"error: cannot serve: {exc}", file=sys.stderr)
        return 2
    return 0


def read_token_file(path: str, given: bool) -> str:
    """The token in ``path`` (its first line, white space left out); refused with --token too."""
    from eyetohand.cli.common import CliError

    if given:
        raise CliError("--token-file: give the token once: --token-file, or --token / EYETOHAND_TOKEN")
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read(4097)
    except (OSError, UnicodeDecodeError) as exc:
        raise CliError(
            f"--token-file {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})"
        ) from None
    lines = text.strip().splitlines()
    if len(text) > 4096 or not lines or len(lines) > 1:
        raise CliError(f"--token-file {path}: expected one line holding the token")
    return lines[0].strip()


def register(sub) -> None:
    p = sub.add_parser(
        "serve",
        help="the calibration workbench (web page + JSON API) and the TCP positioning service",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default 127.0.0.1; a non-loopback one needs --token)",
    )
    p.add_argument("--port", type=int, default=8765, help="HTTP port (default 8765)")
    p.add_argument(
        "--data",
        metavar="DIR",
        default=None,
        help="folder of the calibration database (default: $XDG_DATA_HOME/eyetohand "
        "or ~/.local/share/eyetohand)",
    )
    p.add_argument(
        "--token",
        default=None,
        help="require 'Authorization: Bearer T' on the API (and 'AUTH T' on TCP); default $EYETOHAND_TOKEN",
    )
    p.add_argument(
        "--tcp",
        metavar="HOST:PORT",
        default=None,
        help="also answer 'u,v[,z]' lines with 'x,y,z' on this TCP address",
    )
    p.add_argument(
        "--modbus",
        metavar="HOST:PORT",
        default=None,
        help="also serve the Modbus TCP register map on this address (docs/plc.md); Modbus has no "
        "authentication: a non-loopback address needs --allow-modbus-from",
    )
    p.add_argument(
        "--modbus-word-order",
        choices=["big", "little"],
        default="big",
        help="order of an int32's two registers: big = high word first (default), little = low word "
        "first (e.g. Rockwell COP of a DINT)",
    )
    p.add_argument(
        "--allow-modbus-from",
        metavar="ADDR,...",
        default=None,
        help="the only clients the Modbus server answers (addresses or networks, e.g. "
        "10.0.0.5,10.0.1.0/24; this machine's loopback always)",
    )
    p.add_argument(
        "--opcua",
        metavar="HOST:PORT",
        default=None,
        help="also serve OPC UA on opc.tcp://HOST:PORT/eyetohand/ (docs/plc.md); anonymous on "
        "loopback, else user 'eyetohand' with --token as password",
    )
    p.add_argument(
        "--calibration",
        metavar="REF",
        default=None,
        help="what the TCP, Modbus and OPC UA services map with: a stored calibration's name (or name:NAME), "
        "id:N (followed: its current version, within 1 s), or a calibration file "
        "(FILE.json, a path, or file:PATH; proved intact before anything binds); with --camera "
        "a new name is created by CAL BEGIN … CAL END",
    )
    p.add_argument(
        "--camera",
        metavar="URI",
        default=None,
        help="camera source for the collection protocol on --tcp ('CAL …' lines): opencv:0, "
        "folder:DIR, sim:CELL.toml, genicam:PRODUCER.cti, pylon:[SERIAL] "
        "(docs/collection.md)",
    )
    add_line_options(p)
    p.add_argument(
        "--collect-dir",
        metavar="DIR",
        default=None,
        help="folder of the collection journal, verification histories and belt sessions "
        "(default DATA/collect)",
    )
    p.add_argument(
        "--conveyor",
        metavar="FILE",
        default=None,
        help="conveyor calibration (eyetohand conveyor calibrate -o FILE) served by 'BELT …' "
        "lines on --tcp (docs/conveyor.md)",
    )
    p.add_argument(
        "--db-wait",
        type=float,
        default=2.0,
        metavar="S",
        help="how long a write waits for another writer's database lock before answering "
        "503 with Retry-After (default 2 s)",
    )
    # -- the TCP line service's fairness (docs/server.md "TCP line protocol")
    p.add_argument(
        "--robot-address",
        metavar="ADDR",
        action="append",
        default=None,
        help="the robot's IP address (repeatable): its connections are served beyond the 256-client "
        "limit, so no flood of sockets from elsewhere locks it out",
    )
    p.add_argument(
        "--tcp-first-line",
        dest="tcp_first_line_s",
        type=float,
        default=None,
        metavar="S",
        help="close a TCP connection that sent no whole line this long after connecting (default 10 s)",
    )
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    # ---- --token-file, --allow-host, --sign-key, --require-signed (http worktree)
    p.add_argument(
        "--token-file",
        metavar="FILE",
        default=None,
        help="read the token from FILE (one line) instead of --token, so no process listing shows it",
    )
    p.add_argument(
        "--allow-host",
        metavar="NAME",
        action="append",
        default=None,
        help="also answer HTTP requests whose Host is NAME (e.g. the machine's DNS name); repeatable. "
        "The loopback names and the --host address are always answered",
    )
    p.add_argument(
        "--sign-key",
        metavar="FILE",
        default=None,
        help="HMAC-SHA256 key (>= 16 bytes) that checks signed calibration files (--calibration FILE, "
        "imports) and signs exports (eyetohand calibrate --sign-key FILE signs files)",
    )
    p.add_argument(
        "--require-signed",
        action="store_true",
        help="refuse calibration files not signed with --sign-key (--calibration FILE and imports)",
    )
    # ---- end of the http worktree's options
    p.set_defaults(func=cmd_serve)


def add_line_options(p) -> None:
    """The TCP line service's reply format and units (docs/server.md "Reply format and units")."""
    p.add_argument(
        "--reply-format",
        choices=["plain", "ur"],
        default="plain",
        help="form of every TCP reply: plain 'OK …'/'ERR …' lines, or ur: '(status,a,b,…)' with a "
        "fixed count per command (CAL 4, the rest 6) for URScript's socket_read_ascii_float(n) "
        "(default plain; docs/server.md)",
    )
    p.add_argument(
        "--units",
        default=None,
        metavar="mm|m",
        help="length unit of the TCP mapping and LOCATE lines, both ways: a line's z and the answer's x, "
        "y, z, sigma (default mm; CAL and BELT stay mm, Modbus and OPC UA too)",
    )
    p.add_argument(
        "--angle-units",
        default=None,
        metavar="deg|rad",
        help="angle unit of the rz those lines answer (default deg; a= and t= stay deg)",
    )
