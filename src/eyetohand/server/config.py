"""``eyetohand serve``'s options as one typed value (:class:`ServeConfig`), built once from the parsed
and checked argparse namespace (:func:`eyetohand.server.startup.check_options`); the start-up wiring
reads its fields, never the namespace."""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from eyetohand.core import MM_DEG, InputError, OutputUnits, Role, TokenTable

if TYPE_CHECKING:
    from eyetohand.positioning import FixedCalibration, ServerCertificate
    from eyetohand.server.signatures import SigningPolicy


class ServeError(InputError):
    """Bad ``serve`` options (exit 2)."""


def is_loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_hostport(text: str, flag: str = "--tcp") -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ServeError(f"{flag}: expected HOST:PORT (e.g. 127.0.0.1:7001), got {text!r}")
    return host.strip("[]"), int(port)


@dataclass(frozen=True)
class ServeConfig:
    """What ``serve`` runs, as checked. Addresses are parsed (``tcp``, ``modbus``, ``opcua``: (host,
    port) or None); ``tcp_text`` and friends keep the option as given, for the messages that quote it."""

    host: str = "127.0.0.1"
    port: int = 8765
    token: str | None = None  # the token file's first (one is given: a network address may be served)
    tokens: Mapping[str, str] | None = None  # names to tokens (--token-file): every interface, the audit
    roles: Mapping[str, Role] | None = None  # names to roles (--token-file name:role:token; else operator)
    store: str | None = None  # --store as given (None: the data folder's SQLite database)
    db_wait_s: float = 5.0
    log_level: str = "info"
    allow_hosts: tuple[str, ...] = ()
    sign_key: bytes | None = None
    require_signed: bool = False
    # what the positioning services map with
    calibration: str | None = None  # --calibration as given (a name, id:N or a file)
    calibration_file: FixedCalibration | None = None  # a file, proved intact by check_options
    # the TCP line service
    tcp: tuple[str, int] | None = None
    tcp_text: str = ""
    reply_format: str = "plain"
    units: OutputUnits = MM_DEG
    robot_addresses: tuple[str, ...] = ()
    first_line_s: float | None = None  # None: the line service's default
    # collection and the belt (need --tcp)
    camera: str | None = None
    conveyor: str | None = None
    collect_dir: Path | None = None
    # the PLC services
    modbus: tuple[str, int] | None = None
    modbus_word_order: str = "big"
    modbus_allow: tuple = field(default=())  # () with modbus: any local client; else the networks
    opcua: tuple[str, int] | None = None
    opcua_security: ServerCertificate | None = None  # --opcua-cert/--opcua-key (None: the data folder's)

    @property
    def token_table(self) -> TokenTable:
        """Every named token with its role, as HTTP, TCP and OPC UA check them (empty: none needed)."""
        return TokenTable.of(self.tokens or self.token, self.roles)

    @property
    def signing(self) -> SigningPolicy:
        """The key stored versions are signed with and whether only signed ones are served."""
        from eyetohand.server.signatures import SigningPolicy

        return SigningPolicy(self.sign_key, self.require_signed)

    def access_line(self) -> str | None:
        """The start-up line that says who may do what (the holders' names and roles, never a token)
        and how signing stands; None without tokens or key."""
        from eyetohand.calibration import key_id

        parts = []
        if self.token_table:
            holders = ", ".join(f"{a.name} ({a.role.label})" for a, _ in self.token_table.entries)
            parts.append(f"tokens {holders}")
        if self.sign_key is not None:
            parts.append(f"signing key {key_id(self.sign_key)} (a signer signs versions)")
        if self.require_signed:
            parts.append("--require-signed: only signed versions are mapped with")
        return ("access: " + "; ".join(parts)) if parts else None

    @property
    def plc_wanted(self) -> bool:
        return self.modbus is not None or self.opcua is not None

    @classmethod
    def from_args(cls, args) -> ServeConfig:
        """From the namespace ``check_options`` checked (and completed: ``calibration_file``,
        ``output_units``, ``sign_key_bytes``, ``modbus_allow``)."""
        ns = vars(args)
        modbus, opcua, tcp = ns.get("modbus"), ns.get("opcua"), ns.get("tcp")
        collect_dir = ns.get("collect_dir")
        return cls(
            host=args.host,
            port=args.port,
            token=args.token,
            tokens=ns.get("tokens"),
            roles=ns.get("roles"),
            store=ns.get("store"),
            db_wait_s=args.db_wait,
            log_level=ns.get("log_level") or "info",
            allow_hosts=tuple(ns.get("allow_host") or ()),
            sign_key=ns.get("sign_key_bytes"),
            require_signed=bool(ns.get("require_signed")),
            calibration=ns.get("calibration"),
            calibration_file=ns.get("calibration_file"),
            tcp=parse_hostport(tcp) if tcp else None,
            tcp_text=tcp or "",
            reply_format=ns.get("reply_format") or "plain",
            units=ns.get("output_units") or MM_DEG,
            robot_addresses=tuple(ns.get("robot_address") or ()),
            first_line_s=ns.get("tcp_first_line_s"),
            camera=ns.get("camera"),
            conveyor=ns.get("conveyor"),
            collect_dir=Path(collect_dir) if collect_dir else None,
            modbus=parse_hostport(modbus, "--modbus") if modbus else None,
            modbus_word_order=ns.get("modbus_word_order") or "big",
            modbus_allow=tuple(ns.get("modbus_allow") or ()),
            opcua=parse_hostport(opcua, "--opcua") if opcua else None,
            opcua_security=ns.get("opcua_security"),
        )


__all__ = ["ServeConfig", "ServeError", "is_loopback", "parse_hostport"]
