"""Which store a reference names, and opening it: ``sqlite:PATH`` (a database file, or a folder that
holds ``calibrations.db``), ``postgresql://USER@HOST:PORT/DB``, or a bare folder (the data folder, as
``serve --data`` has always meant).

Also the copy of a whole store into an empty one (``eyetohand store copy``): every row verbatim, the
ids kept, then proved by comparing both stores' digests."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
from dataclasses import dataclass
from pathlib import Path

from eyetohand.server import schema
from eyetohand.server.audit import AuditQuery, parse_utc
from eyetohand.server.storage import DB_NAME, WAIT_S, StorageError, Store

PG_SCHEMES = ("postgresql://", "postgres://")
EXPECTED = "expected sqlite:PATH, postgresql://USER@HOST:PORT/DB or a data folder"


class StoreRefError(ValueError):
    """A store reference that names no store this program can open."""


@dataclass(frozen=True)
class StoreRef:
    """A parsed store reference: ``url`` for PostgreSQL, else the SQLite file ``path``."""

    url: str | None = None
    path: Path | None = None

    @classmethod
    def parse(cls, ref: str | os.PathLike) -> StoreRef:
        text = os.fspath(ref)
        if text.startswith(PG_SCHEMES):
            return cls(url=text)
        if text.startswith("sqlite:"):
            raw = text[len("sqlite:") :].removeprefix("//")
            if not raw:
                raise StoreRefError(f"{text!r}: sqlite: needs a path ({EXPECTED})")
            p = Path(raw)
            return cls(path=p / DB_NAME if p.is_dir() else p)
        head = text.split(":", 1)[0]
        if "://" in text and head.isalpha():
            raise StoreRefError(f"{text!r}: unknown kind of store {head!r} ({EXPECTED})")
        return cls(path=Path(text) / DB_NAME)

    @property
    def shared(self) -> bool:
        return self.url is not None

    def exists(self) -> bool:
        """A SQLite file that exists; a PostgreSQL database is taken to exist (its tables are made
        on first use)."""
        return self.url is not None or (self.path is not None and self.path.is_file())

    def __str__(self) -> str:
        if self.url is not None:
            from eyetohand.server.store_pg import masked

            return masked(self.url)
        return f"sqlite:{self.path}"


def open_store(ref: str | os.PathLike | StoreRef, wait_s: float = WAIT_S, *, create: bool = False) -> Store:
    """The store ``ref`` names (see :class:`StoreRef`). ``create``: a SQLite file may be made (a
    first start); PostgreSQL tables are always made on first use. :class:`StoreRefError` for a
    reference that names nothing openable; the store's own errors (:class:`StorageError`) else."""
    r = ref if isinstance(ref, StoreRef) else StoreRef.parse(ref)
    if r.url is not None:
        if importlib.util.find_spec("psycopg") is None:
            raise StoreRefError(
                f"{r}: a PostgreSQL store needs the psycopg package: pip install 'eyetohand[postgres]'"
            )
        from eyetohand.server.store_pg import PgStore

        return PgStore(r.url, wait_s)
    assert r.path is not None
    return Store(r.path.parent, wait_s, create=create, file_name=r.path.name)


# ------------------------------------------------------------------ copy
def _rows(run) -> dict[str, list[tuple]]:
    """Every row of every copied table (:data:`~eyetohand.server.schema.COPIED`) in a fixed order;
    ``run(sql)``: the rows of a query."""
    return {
        table: [tuple(r) for r in run(f"SELECT {', '.join(cols)} FROM {table} ORDER BY {order}")]
        for table, cols, order in schema.COPIED
    }


def _digest(rows: dict[str, list[tuple]]) -> str:
    h = hashlib.sha256()
    for table, table_rows in rows.items():
        h.update(table.encode())
        for row in table_rows:
            h.update(json.dumps(list(row), separators=(",", ":"), ensure_ascii=False).encode())
            h.update(b"\n")
    return h.hexdigest()


def store_digest(store: Store) -> str:
    """sha256 of every copied row: two stores with one digest hold the same calibrations (ids and
    names), versions (their JSON byte for byte), verifications and audit trail."""
    return _digest(_rows(store._read))


@dataclass(frozen=True)
class CopyResult:
    calibrations: int
    versions: int
    verifications: int
    audit: int
    digest: str


def copy_store(src: Store, dst: Store) -> CopyResult:
    """Copy everything in ``src`` into ``dst`` (which must hold no calibration and no audit entry
    yet) in one transaction of ``dst``, read it back inside that transaction and compare digests:
    a copy that does not read back identical is rolled back, nothing kept."""
    rows = _rows(src._read)
    want = _digest(rows)
    with dst._tx() as db, dst._errors():

        def run(sql: str) -> list:
            return db.execute(sql, ()).fetchall()

        for table in ("calibrations", "audit"):
            n = int(run(f"SELECT COUNT(*) FROM {table}")[0][0])
            if n:
                raise StoreRefError(
                    f"{dst.where} is not empty ({n} rows in {table}): copy only into an empty store"
                )
        for table, cols, _ in schema.COPIED:
            sql = f"INSERT INTO {table} ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})"
            for row in rows[table]:
                db.execute(sql, row)
        if dst.dialect == "postgresql":  # the identity columns go on after the copied ids
            for table, col in (("calibrations", "id"), ("audit", "id"), ("verifications", "rowid")):
                run(
                    f"SELECT setval(pg_get_serial_sequence('{table}', '{col}'), "
                    f"COALESCE((SELECT MAX({col}) FROM {table}), 0) + 1, false)"
                )
        got = _digest(_rows(run))
        if got != want:
            raise StorageError(
                f"the copy in {dst.where} does not read back as {src.where} holds it; nothing was kept"
            )
    return CopyResult(
        len(rows["calibrations"]), len(rows["versions"]), len(rows["verifications"]), len(rows["audit"]), want
    )


# ------------------------------------------------------------------ audit queries
MAX_ID = 2**62
"""The largest calibration id the API takes (as its paths do)."""


class QueryError(ValueError):
    """A bad filter of the audit trail; ``field`` names it."""

    def __init__(self, message: str, field: str):
        super().__init__(message)
        self.field = field


def audit_query(
    store: Store,
    *,
    calibration: str | None = None,
    user: str | None = None,
    since: str | None = None,
    until: str | None = None,
    before: int | None = None,
    limit: int = 100,
) -> AuditQuery:
    """The query of ``GET /api/audit`` and ``eyetohand audit``, checked (:class:`QueryError` naming
    the filter). ``calibration``: a name or id as everywhere (``id:N``, ``name:NAME``); a name no
    calibration has now still finds the entries recorded under it (a deleted one's trail)."""
    from eyetohand.server.storage import NotFound, is_id_like

    if not 1 <= limit <= AuditQuery.MAX_LIMIT:
        raise QueryError(f"limit: expected 1..{AuditQuery.MAX_LIMIT}, got {limit}", "limit")
    if before is not None and before < 1:
        raise QueryError(f"before: expected an entry id >= 1, got {before}", "before")
    times = {}
    for fld, value in (("since", since), ("until", until)):
        if value is not None:
            try:
                times[fld] = parse_utc(value, fld)
            except ValueError as exc:
                raise QueryError(str(exc), fld) from None
    cal_id = cal_name = None
    if calibration is not None:
        ref = calibration.strip()
        bare = ref[3:].strip() if ref.lower().startswith("id:") else ref
        if is_id_like(bare) and int(bare) > MAX_ID:
            raise QueryError(
                f"calibration: {ref!r} is no calibration's id (ids are at most 2**62)", "calibration"
            )
        try:
            cal_id = store.find(ref).id
        except NotFound:
            if is_id_like(bare):
                cal_id = int(bare)
            else:
                cal_name = ref[5:] if ref.lower().startswith("name:") else ref
    return AuditQuery(
        calibration_id=cal_id,
        calibration_name=cal_name,
        user=user,
        since=times.get("since"),
        until=times.get("until"),
        before=before,
        limit=limit,
    )
