"""``eyetohand audit`` (the store's audit trail) and ``eyetohand store copy SRC DST`` (a cell's whole
history from one store to another: SQLite and PostgreSQL, either way). docs/store.md."""

from __future__ import annotations

from dataclasses import asdict

from eyetohand.cli.common import CliError, emit_json


def _store_of(args, *, create: bool = False):
    """The store ``--store`` (else ``--data``'s, else the default data folder's) names, opened."""
    from eyetohand.server import StorageError, StoreRef, StoreRefError, default_data_dir, open_store

    given = args.store or args.data or default_data_dir()
    try:
        return open_store(StoreRef.parse(given), create=create)
    except (StorageError, StoreRefError) as exc:
        raise CliError(f"--store {given}: {exc}") from None


def cmd_audit(args) -> int:
    from eyetohand.server import QueryError, StorageError

    if args.store and args.data:
        raise CliError("give the store once: --store URL or --data DIR")
    store = _store_of(args)
    try:
        q = store_query(store, args)
        entries = store.audit(q)
    except QueryError as exc:
        raise CliError(f"--{exc}") from None  # its words start with the filter's name
    except (StorageError, LookupError) as exc:
        raise CliError(f"{store.where}: {str(exc).strip(chr(39))}") from None
    finally:
        store.close()
    if args.json:
        emit_json({"entries": [e.to_dict() for e in entries]})
        return 0
    if not entries:
        print("no audit entries match")
        return 0
    print(f"{'utc':<29} {'user':<12} {'action':<11} {'calibration':<20} {'version':<9} note")
    for e in entries:
        before = "-" if e.version_before is None else str(e.version_before)
        after = "-" if e.version_after is None else str(e.version_after)
        print(
            f"{e.utc:<29} {e.user:<12} {e.action:<11} {e.calibration:<20} {before + '>' + after:<9} {e.note}"
        )
    return 0


def store_query(store, args):
    from eyetohand.server import audit_query

    return audit_query(
        store,
        calibration=args.calibration,
        user=args.user,
        since=args.since,
        until=args.until,
        before=args.before,
        limit=args.limit,
    )


def cmd_store_copy(args) -> int:
    from eyetohand.server import StorageError, StoreRef, StoreRefError, copy_store, open_store

    try:
        src_ref, dst_ref = StoreRef.parse(args.src), StoreRef.parse(args.dst)
    except StoreRefError as exc:
        raise CliError(str(exc)) from None
    if str(src_ref) == str(dst_ref):
        raise CliError(f"SRC and DST are the same store ({src_ref})")
    if not src_ref.exists():
        raise CliError(f"SRC {src_ref}: no such database")
    stores = []
    try:
        stores.append(open_store(src_ref))
        stores.append(open_store(dst_ref, create=True))
        result = copy_store(*stores)
    except (StorageError, StoreRefError) as exc:
        raise CliError(str(exc)) from None
    finally:
        for s in stores:
            s.close()
    if args.json:
        emit_json({"src": str(src_ref), "dst": str(dst_ref), **asdict(result)})
        return 0
    print(
        f"copied {result.calibrations} calibrations, {result.versions} versions, {result.verifications} "
        f"verifications and {result.audit} audit entries from {src_ref} to {dst_ref} "
        f"(identical: sha256 {result.digest[:16]}…)"
    )
    return 0


def register(sub) -> None:
    p = sub.add_parser("audit", help="the store's audit trail: who changed which calibration, when and why")
    where = p.add_argument_group("which store (default: the data folder's, as eyetohand serve)")
    where.add_argument("--store", metavar="URL", help="sqlite:PATH or postgresql://USER@HOST:PORT/DB")
    where.add_argument("--data", metavar="DIR", help="the data folder of a serve (its calibrations.db)")
    p.add_argument("--calibration", metavar="REF", help="one calibration: its name, id:N or name:NAME")
    p.add_argument("--user", help="changes by this user (the token's name)")
    p.add_argument("--since", metavar="UTC", help="at or after this time (ISO 8601, e.g. 2026-12-04T05:00Z)")
    p.add_argument("--until", metavar="UTC", help="at or before this time")
    p.add_argument("--before", type=int, metavar="ID", help="entries older than this entry id (paging)")
    p.add_argument("--limit", type=int, default=100, metavar="N", help="at most N entries (default 100)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_audit)

    s = sub.add_parser("store", help="copy a store's whole history between SQLite and PostgreSQL")
    ssub = s.add_subparsers(dest="store_command", metavar="ACTION", required=True, parser_class=type(p))
    c = ssub.add_parser(
        "copy",
        help="copy every calibration, version, verification and audit entry of SRC into an empty DST",
    )
    c.add_argument("src", metavar="SRC", help="sqlite:PATH, a data folder, or postgresql://USER@HOST:PORT/DB")
    c.add_argument("dst", metavar="DST", help="the same kinds; must hold no calibration yet")
    c.add_argument("--json", action="store_true", help="print JSON (the counts copied and the digest)")
    c.set_defaults(func=cmd_store_copy)
