"""``eyetohand serve``: the calibration workbench (web page + JSON API) and the TCP positioning service.

Parses the options and calls :func:`eyetohand.server.cli.serve`; the server is imported only when
the command runs (its dependencies are the heaviest of the package)."""

from __future__ import annotations

import os
import sys


def cmd_serve(args) -> int:
    from eyetohand.server import check_options, default_data_dir, serve

    args.token = args.token or os.environ.get("EYETOHAND_TOKEN") or None
    check_options(args)
    data_dir = args.data or default_data_dir()
    try:
        serve(args, data_dir)
    except OSError as exc:
        print(f"error: cannot serve: {exc}", file=sys.stderr)
        return 2
    return 0


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
        "--calibration",
        metavar="REF",
        default=None,
        help="what the TCP service maps with: a stored calibration's name (or name:NAME), "
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
    p.add_argument(
        "--reply-format",
        choices=["plain", "ur"],
        default="plain",
        help="form of the CAL replies: plain 'OK …'/'ERR …' lines, or ur: '(status,a,b,c)' "
        "for URScript's socket_read_ascii_float(4) (default plain)",
    )
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
    p.set_defaults(func=cmd_serve)
