"""``eyetohand serve``: the calibration workbench (web page + JSON API) and the positioning service (TCP
lines, Modbus TCP, OPC UA).

Parses the options and calls :func:`eyetohand.server.startup.serve`; the server is imported only when
the command runs (its dependencies are the heaviest of the package)."""

from __future__ import annotations

import os
import sys

TOKEN_IN_PS = (
    "warning: --token on the command line is visible to every user of this machine (ps, /proc); "
    "give it with --token-file FILE or EYETOHAND_TOKEN instead"
)


def cmd_serve(args) -> int:
    from eyetohand.server import DEFAULT_TOKEN_NAME, check_options, default_data_dir, serve

    if args.token:  # on the command line: every user of this machine reads it in `ps`
        print(TOKEN_IN_PS, file=sys.stderr)
    args.token = args.token or os.environ.get("EYETOHAND_TOKEN") or None
    args.tokens = None if args.token is None else {DEFAULT_TOKEN_NAME: args.token}
    # ---- --token-file (http worktree): the token read from a file, so no process listing shows it
    args.roles = None  # a token without a role: operator
    if getattr(args, "token_file", None) is not None:
        args.tokens, args.roles = read_token_roles(args.token_file, given=args.token is not None)
        args.token = next(iter(args.tokens.values()))  # the file's first (TCP and OPC UA take every one)
    # ---- end --token-file
    config = check_options(args)  # the options as one typed value, checked once
    data_dir = args.data or default_data_dir()
    try:
        serve(config, data_dir)
    except OSError as exc:
        print(f"error: cannot serve: {exc}", file=sys.stderr)
        return 2
    return 0


def token_file_lines(path: str, expected: str) -> list[tuple[int, str]]:
    """The lines of token file ``path`` that say something (numbered from 1; blank lines and ``#``
    comments left out), read with its 4096-byte bound; refused in one line naming ``--token-file``
    (``expected``: what the caller wants in it). Shared by ``serve`` and ``sign``."""
    from eyetohand.cli.common import CliError

    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read(4097)
    except (OSError, UnicodeDecodeError) as exc:
        raise CliError(
            f"--token-file {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})"
        ) from None
    if len(text) > 4096:
        raise CliError(f"--token-file {path}: larger than 4096 bytes; {expected}")
    lines = [(n, ln.strip()) for n, ln in enumerate(text.splitlines(), 1)]
    return [(n, ln) for n, ln in lines if ln and not ln.startswith("#")]


def read_token_file(path: str, given: bool) -> dict[str, str]:
    """The named tokens in ``path`` (their roles left out): see :func:`read_token_roles`."""
    return read_token_roles(path, given)[0]


def read_token_roles(path: str, given: bool) -> tuple[dict[str, str], dict]:
    """The named tokens in ``path`` and their roles (:class:`eyetohand.core.Role`): lines
    ``name:token`` (role operator, as before roles existed) or ``name:role:token`` with role one of
    viewer, operator, signer (a name of letters, digits, ``._@-``; the token after the colon that
    ends the name, or the role); or one line holding a token alone (named ``default``, operator).
    Blank lines and ``#`` comments are left out; refused with --token too."""
    import re

    from eyetohand.cli.common import CliError
    from eyetohand.core import ROLE_NAMES, Role
    from eyetohand.server import DEFAULT_TOKEN_NAME

    if given:
        raise CliError("--token-file: give the token once: --token-file, or --token / EYETOHAND_TOKEN")
    lines = token_file_lines(path, "expected lines 'name:token'")
    if not lines:
        raise CliError(f"--token-file {path}: expected one line holding the token, or lines 'name:token'")
    if len(lines) == 1 and ":" not in lines[0][1]:
        return {DEFAULT_TOKEN_NAME: lines[0][1]}, {DEFAULT_TOKEN_NAME: Role.OPERATOR}
    tokens: dict[str, str] = {}
    roles: dict[str, Role] = {}
    for n, ln in lines:
        name, sep, token = (part.strip() for part in ln.partition(":"))
        role = Role.OPERATOR
        word, sep2, rest = token.partition(":")
        if sep2 and word.strip().lower() in ROLE_NAMES:  # name:role:token
            role, token = Role.parse(word), rest.strip()
        if not sep or not re.fullmatch(r"[A-Za-z0-9._@-]{1,64}", name) or not token:
            raise CliError(
                f"--token-file {path} line {n}: expected 'name:token' or 'name:role:token' (a name of "
                f"letters, digits and ._@- ; a role of {', '.join(ROLE_NAMES)}; then the token)"
            )
        if name in tokens:
            raise CliError(f"--token-file {path} line {n}: the name {name!r} is given twice")
        if token in tokens.values():
            raise CliError(f"--token-file {path} line {n}: this token is given to another name too")
        if len(token) < 8:
            raise CliError(
                f"--token-file {path} line {n}: the token of {name!r} is shorter than 8 characters"
            )
        tokens[name] = token
        roles[name] = role
    return tokens, roles


def add_opcua_certificate_options(p) -> None:
    """``--opcua-cert FILE`` and ``--opcua-key FILE``: the plant's certificate for OPC UA's secured
    endpoints (default: one made at the first start in DATA/opcua/)."""
    p.add_argument(
        "--opcua-cert",
        metavar="FILE",
        default=None,
        help="OPC UA server certificate (PEM or DER, with an application URI); default: one made at "
        "the first start in DATA/opcua/",
    )
    p.add_argument(
        "--opcua-key", metavar="FILE", default=None, help="the private key of --opcua-cert (PEM or DER)"
    )


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
    add_store_option(p)
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
        "loopback, else user 'eyetohand' with --token as password (off loopback only encrypted)",
    )
    add_opcua_certificate_options(p)
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
        help="read the tokens from FILE instead of --token, so no process listing shows them: lines "
        "'name:token' or 'name:role:token' (the name is the user in the audit trail; role viewer, "
        "operator (default) or signer: docs/server.md), or one line holding one token",
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
        "imports) and that a token of role signer signs stored versions with (POST "
        "/api/calibrations/ID/versions/N/sign; eyetohand sign); an export carries a version's signature",
    )
    p.add_argument(
        "--require-signed",
        action="store_true",
        help="serve only what is signed with --sign-key: a --calibration file must be signed; a stored "
        "version (fit, collection, plate, import) is kept but not mapped with until a signer signs it",
    )
    # ---- end of the http worktree's options
    p.set_defaults(func=cmd_serve)


def add_store_option(p) -> None:
    """``--store URL`` (docs/store.md)."""
    p.add_argument(
        "--store",
        metavar="URL",
        default=None,
        help="the store of calibrations: sqlite:PATH (a database file) or postgresql://USER@HOST:PORT/DB "
        "(a plant's shared database; pip install 'eyetohand[postgres]'); default sqlite in --data "
        "(docs/store.md)",
    )


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
