"""Calibrations and their versions in an embedded SQLite database (one file, ``calibrations.db``).

Every change is one transaction; the database runs in WAL mode with ``synchronous=FULL``, so a
crash (of the process or of the machine) loses no committed change and never leaves half of one.
A calibration has a name (unique, stored as data only: it never reaches a file path) and a list of
versions 1, 2, 3, …; each version keeps the fitted calibration (the JSON that ``eyetohand apply``
reads), the pairs it was fitted on, the check pairs, the fit request and a note. Versions are never
changed or removed: a refit adds one, and rolling back to version *n* adds a new version that is a
copy of *n* (so the history still shows what was in force, and when).

The database file is the truth: the store creates it only when told to (``create=True``, at a first
start), every connection opens it read-write without ever creating it, and every read and write first
proves that the path still names the file the store opened (:meth:`Store.check_same_file`), so a
database deleted or replaced under a running server is refused (:class:`DatabaseGone`, 503), never
silently recreated empty nor served from the unlinked file.

The tables and their versions are in :mod:`~eyetohand.server.schema`; every change appends its audit
entry in its own transaction (:mod:`~eyetohand.server.audit`). The same class, its SQL unchanged, runs
on PostgreSQL as :class:`~eyetohand.server.store_pg.PgStore`; :func:`~eyetohand.server.stores.open_store`
opens either from a reference (docs/store.md).
"""

from __future__ import annotations

import builtins
import datetime as _dt
import hashlib
import json
import os
import sqlite3
import threading
import unicodedata
import urllib.parse
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from eyetohand.server import audit, schema
from eyetohand.server.audit import AuditEntry, AuditQuery

DB_NAME = "calibrations.db"
WAIT_S = 2.0
"""How long a write waits for another connection's write lock before giving up (:class:`Busy`)."""


def default_data_dir() -> Path:
    """``$XDG_DATA_HOME/eyetohand``, else ``~/.local/share/eyetohand``."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "eyetohand"


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


class NotFound(LookupError):
    """No calibration (or version) with that id."""


class NameTaken(ValueError):
    """Another calibration already has that name."""


class Ambiguous(LookupError):
    """A reference that is the name of one calibration and the id of another."""


class StorageError(RuntimeError):
    """The database cannot do what was asked now (the request was not applied). ``status`` is the
    HTTP status to answer (503: try again later; 507: no space), ``retry_after_s`` a hint or None."""

    status = 503
    retry_after_s: int | None = None


class Busy(StorageError):
    """Another connection held the write lock for longer than the store waits."""

    retry_after_s = 1


class NoSpace(StorageError):
    """The disk (or the process's file-size limit) is full: the change was rolled back."""

    status = 507


class DatabaseGone(StorageError):
    """The database file this store opened was deleted, or its path now names another file (replaced
    under the running server): nothing is read or written until the path names it again."""


class SchemaTooNew(StorageError):
    """The database was written by a newer eyetohand (its schema version is newer than this one's):
    refused, nothing read or changed."""


class Conflict(Exception):
    """``If-Match`` named another state of the calibration than the current one (HTTP 412): the
    change was not applied. ``current_version`` and ``etag`` say what is current now."""

    def __init__(self, message: str, current_version: int, etag: str):
        super().__init__(message)
        self.current_version = current_version
        self.etag = etag


def etag_of(cal_id: int, version: int, name: str) -> str:
    """The entity tag of a calibration's current state: its id, current version and name (a refit,
    a rollback or a rename changes it), as a quoted strong ETag."""
    digest = hashlib.sha256(unicodedata.normalize("NFC", name).encode()).hexdigest()[:8]
    return f'"{cal_id}.{version}.{digest}"'


class WeakTag(ValueError):
    """An ``If-Match`` holding a weak ETag (``W/"…"``): refused, never compared (HTTP answers 400)."""


def weak_tag_refusal(if_match: str) -> str | None:
    """Why ``if_match`` is refused when it holds a weak ETag, else None: If-Match compares strongly
    (RFC 9110, 13.1.1), so ``W/"…"`` never matches, and taking it as the strong tag would pass a
    condition the client did not set. The words of every interface (the HTTP header's too)."""
    weak = next((t.strip() for t in if_match.split(",") if t.strip().startswith("W/")), None)
    if weak is None:
        return None
    return (
        f"If-Match: {weak[:80]!r} is a weak ETag; If-Match compares ETags strongly (RFC 9110, "
        "13.1.1): send the ETag as the server gave it, without W/"
    )


def require_match(rec: Record, if_match: str | None) -> None:
    """:class:`Conflict` unless ``if_match`` (an ``If-Match`` value: ETags separated by commas, or
    ``*``; None: no condition) names ``rec``'s current state; :class:`WeakTag` when it holds a weak
    ETag (:func:`weak_tag_refusal`)."""
    if if_match is None:
        return
    weak = weak_tag_refusal(if_match)
    if weak is not None:
        raise WeakTag(weak)
    given = [t.strip() for t in if_match.split(",")]
    if "*" in given or rec.etag in given:
        return
    raise Conflict(
        f"If-Match {if_match.strip()!r} is not the current state of calibration {rec.id} ({rec.etag}: "
        f"version {rec.current_version}, named {rec.name!r}); it was changed meanwhile: reload it, "
        "then decide again",
        rec.current_version,
        rec.etag,
    )


def _storage_error(exc: sqlite3.OperationalError, path: Path) -> StorageError:
    msg = str(exc)
    low = msg.lower()
    if "locked" in low or "busy" in low:
        return Busy(f"the database {path.name} is busy (another writer holds its lock); try again shortly")
    if "full" in low:
        return NoSpace(f"no space to write the database {path.name} ({msg}); nothing was changed")
    if "readonly" in low or "read-only" in low:
        return StorageError(f"the database {path.name} is read-only ({msg}); nothing was changed")
    return StorageError(f"the database {path.name} failed: {msg}; nothing was changed")


@contextmanager
def _translated(path: Path) -> Iterator[None]:
    try:
        yield
    except sqlite3.OperationalError as exc:
        raise _storage_error(exc, path) from None
    except OSError as exc:  # e.g. EFBIG from a file-size limit surfacing as an OS error
        raise NoSpace(f"cannot write the database {path.name} ({exc}); nothing was changed") from None


def is_id_like(text: str) -> bool:
    """A reference made only of ASCII digits reads as an id (so a name may not be one)."""
    return text.isascii() and text.isdigit()


BAD_CATEGORIES = {"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"}


def clean_text(text: str, what: str) -> str:
    """``text`` in NFC; ValueError naming ``what`` for control, format (zero-width, bidi),
    unassigned or private-use characters, which make invisible or look-alike names."""
    text = unicodedata.normalize("NFC", text)
    for i, ch in enumerate(text):
        cat = unicodedata.category(ch)
        if cat in BAD_CATEGORIES:
            raise ValueError(
                f"{what}: character {i} is U+{ord(ch):04X} "
                f"({unicodedata.name(ch, cat)}), not allowed in {what}s"
            )
    return text


# letters of other scripts drawn like Latin ones (after NFKC and casefold): the common Cyrillic, Greek
# and Armenian look-alikes of Unicode's confusables list, enough that a name cannot pass for another
_LOOKALIKES = {
    "a": "\u0430\u03b1",  # Cyrillic a, Greek alpha
    "b": "\u044c\u0432\u03b2",
    "c": "\u0441\u03c2\u0441",
    "d": "\u0501",
    "e": "\u0435\u03b5",
    "g": "\u0581",
    "h": "\u04bb\u043d\u0570",
    "i": "\u0456\u03b9\u0131",
    "j": "\u0458",
    "k": "\u043a\u03ba",
    "l": "\u04cf\u2113",
    "m": "\u043c",
    "n": "\u0578\u03b7",
    "o": "\u043e\u03bf\u0585",
    "p": "\u0440\u03c1",
    "q": "\u051b\u0566",
    "s": "\u0455",
    "t": "\u0442\u03c4",
    "u": "\u057d\u03c5",
    "v": "\u0475\u03bd",
    "w": "\u051d\u03c9",
    "x": "\u0445\u03c7",
    "y": "\u0443\u03b3",
    "-": "\u2010\u2011\u2012\u2013\u2212",
}
_CONFUSABLE = str.maketrans({ch: latin for latin, chars in _LOOKALIKES.items() for ch in chars})


def name_skeleton(name: str) -> str:
    """What a name looks like: NFKC, casefolded, and look-alike letters of other scripts read as their
    Latin twins. Two names with one skeleton read the same on a screen ("Cell 1", "cell 1", "Сеll 1"
    with Cyrillic С and е), so the store keeps only one of them."""
    return unicodedata.normalize("NFKC", name).casefold().translate(_CONFUSABLE)


@dataclass(frozen=True)
class Version:
    calibration_id: int
    version: int
    created_utc: str
    note: str
    request: dict
    calibration: dict
    pairs: list
    check: list | None

    def brief(self) -> dict:
        cal = self.calibration
        return {
            "version": self.version,
            "created_utc": self.created_utc,
            "note": self.note,
            "model": cal["model"]["name"],
            "optimizer": cal["fit"]["optimizer"],
            "fitness_mm": cal["fit"]["fitness"],
            "train_rms_mm": cal["train"]["rms_mm"],
            "check_rms_mm": cal["check"]["rms_mm"] if cal.get("check") else None,
        }


@dataclass(frozen=True)
class Signature:
    """A version's signature: the HMAC-SHA256 (``key_id``, ``mac``: the file format's ``signature``
    field) of its calibration JSON under a server's key, with who (``signer``) and when (``utc``).
    ``origin``: ``sign`` (a signer's act), ``import`` (carried by an imported signed file, ``signer``
    the importing token's holder) or ``rollback`` (the signature of the version a rollback copied)."""

    calibration_id: int
    version: int
    utc: str
    signer: str
    origin: str
    key_id: str
    mac: str

    ALG = "hmac-sha256"

    def file_field(self) -> dict:
        """The calibration file's ``signature`` field."""
        return {"alg": self.ALG, "key_id": self.key_id, "mac": self.mac}

    def to_dict(self) -> dict:
        return {
            "signed_by": self.signer,
            "signed_utc": self.utc,
            "origin": self.origin,
            "key_id": self.key_id,
        }


class AlreadySigned(ValueError):
    """The version has a signature already (a version is signed once)."""


@dataclass(frozen=True)
class Record:
    id: int
    name: str
    created_utc: str
    updated_utc: str
    current_version: int

    @property
    def etag(self) -> str:
        """The ETag of this state (id, current version, name): see :func:`etag_of`."""
        return etag_of(self.id, self.current_version, self.name)


class Store:
    """Thread-safe access to the database: one SQLite connection per thread, no Python lock.

    Reads never wait for a writer (WAL); a write waits at most ``wait_s`` for another connection's
    write lock, then raises :class:`Busy`; any other SQLite failure raises :class:`StorageError`
    (the transaction is rolled back). Nothing here holds a lock while SQLite waits."""

    dialect = "sqlite"
    _integrity_error: type[Exception] = sqlite3.IntegrityError

    def __init__(
        self,
        data_dir: str | os.PathLike,
        wait_s: float = WAIT_S,
        *,
        create: bool = False,
        file_name: str = DB_NAME,
    ):
        """Open ``data_dir/calibrations.db`` (``file_name``: another name in that folder).
        ``create``: make it (and ``data_dir``) when there is none yet — a first start; without it
        a missing database is :class:`DatabaseGone`. Either way, once open the store never
        creates the file again (see :meth:`check_same_file`)."""
        self.data_dir = Path(data_dir)
        self.path = self.data_dir / file_name
        self.where = str(self.path)
        self.wait_s = float(wait_s)
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._all_lock = threading.Lock()  # guards the list only, never held around SQLite
        self._closed = False
        self._identity: tuple[int, int] | None = None
        if not self.path.exists():
            if not create:
                raise DatabaseGone(
                    f"database replaced or missing: there is no {self.path} (it is created only at a "
                    "server's first start, with an empty data folder)"
                )
            self.data_dir.mkdir(parents=True, exist_ok=True)
            with _translated(self.path):
                sqlite3.connect(self._uri("rwc"), uri=True).close()
        st = os.stat(self.path)
        self._identity = (st.st_dev, st.st_ino)
        with _translated(self.path):
            db = self._db
            db.execute("PRAGMA journal_mode=WAL")
        self._migrate()

    def _migrate(self) -> None:
        """Create or upgrade the tables (:mod:`~eyetohand.server.schema`) in one write transaction."""
        try:
            with self._tx() as db, self._errors():

                def run(sql: str, args: tuple) -> list:
                    cur = db.execute(sql, args)
                    return cur.fetchall() if cur.description else []

                self.schema_found, self.schema_version = schema.migrate(run, self.dialect, self.where)
        except schema.SchemaTooNew as exc:
            self.close()
            raise SchemaTooNew(str(exc)) from None

    def _errors(self):
        """A context that turns this backend's failures into :class:`StorageError`."""
        return _translated(self.path)

    def _uri(self, mode: str) -> str:
        return f"file:{urllib.parse.quote(str(self.path.absolute()))}?mode={mode}"

    def check_same_file(self) -> None:
        """Prove that the database path still names the file this store opened; raise
        :class:`DatabaseGone` (a :class:`StorageError`, HTTP 503) when it is missing or another file
        (deleted, or replaced by a copy, a restore, another cell's database) — until it names the
        same file again (e.g. moved back), when this returns quietly.

        Contract: one ``os.stat`` of the path compared with the (device, inode) recorded at opening,
        no SQLite call, no lock: cheap enough to call before every request or robot line, safe from
        any thread. Every read and write of the store calls it first (inside the write transaction),
        so no answer comes from, and no acknowledged write goes to, a file that is no longer the
        database; a caller that answers from memory (a cached calibration: the HTTP mapping routes,
        the TCP line service) calls it itself and refuses while it raises."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            raise DatabaseGone(
                f"database replaced or missing: {self.path} was deleted under the running server "
                "(put it back, or restart the server on the database to use)"
            ) from None
        except OSError as exc:
            raise DatabaseGone(f"database replaced or missing: cannot stat {self.path} ({exc})") from None
        if (st.st_dev, st.st_ino) != self._identity:
            raise DatabaseGone(
                f"database replaced or missing: {self.path} is no longer the file this server opened "
                "(it was replaced under the running server; restart the server to use the new one)"
            )

    @property
    def _db(self) -> sqlite3.Connection:
        """This thread's connection (opened on first use, read-write: never creating the file)."""
        db = getattr(self._local, "db", None)
        if db is None:
            if self._closed:
                raise StorageError(f"the store of {self.path} is closed")
            self.check_same_file()
            try:
                db = sqlite3.connect(
                    self._uri("rw"),
                    uri=True,
                    check_same_thread=False,
                    isolation_level=None,
                    timeout=self.wait_s,
                )
            except sqlite3.OperationalError as exc:
                raise _storage_error(exc, self.path) from None
            self.check_same_file()  # the path was not swapped while it was being opened
            db.execute("PRAGMA synchronous=FULL")
            db.execute("PRAGMA foreign_keys=ON")
            db.execute(f"PRAGMA busy_timeout={int(self.wait_s * 1000)}")
            self._local.db = db
            with self._all_lock:
                self._all.append(db)
        return db

    def close(self) -> None:
        self._closed = True
        with self._all_lock:
            conns, self._all = self._all, []
        for db in conns:
            try:
                db.close()
            except sqlite3.Error:
                pass
        self._local = threading.local()

    def integrity_check(self) -> str:
        with _translated(self.path):
            return str(self._db.execute("PRAGMA integrity_check").fetchone()[0])

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One IMMEDIATE transaction: committed as a whole or rolled back as a whole."""
        db = self._db
        with _translated(self.path):
            db.execute("BEGIN IMMEDIATE")
        try:
            self.check_same_file()  # under the write lock: no acknowledged write to an unlinked file
            yield db
            with _translated(self.path):
                db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                try:
                    db.execute("ROLLBACK")
                except sqlite3.Error:
                    pass
            raise

    def _read(self, sql: str, args: tuple = ()) -> list:
        self.check_same_file()
        with _translated(self.path):
            return self._db.execute(sql, args).fetchall()

    def _audit(self, db, action: str, rec: Record, before: int | None, after: int | None, note: str) -> None:
        """Append the audit entry of a change, inside the change's transaction."""
        db.execute(
            "INSERT INTO audit (utc, user_name, action, calibration_id, calibration, version_before, "
            "version_after, note) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (_now(), audit.current_user(), action, rec.id, rec.name, before, after, note),
        )

    def audit_event(self, cal_id: int, action: str, version: int | None, note: str) -> None:
        """Append an audit entry that changes no row (a check made elsewhere: a CAL CHECK over TCP)."""
        with self._tx() as db, self._errors():
            rec = self._row(db, cal_id)
            self._audit(db, action, rec, version, version, note)

    def changed_since(self, after: int | None) -> tuple[int, builtins.list[int]]:
        """(the last audit entry's id, the calibrations changed after entry ``after``; None: none,
        only the id). Writes are serialised, so ids become visible in order: nothing is skipped."""
        if after is None:
            return int(self._read("SELECT COALESCE(MAX(id), 0) FROM audit")[0][0]), []
        rows = self._read("SELECT id, calibration_id FROM audit WHERE id > ? ORDER BY id", (after,))
        if not rows:
            return after, []
        return int(rows[-1][0]), list(dict.fromkeys(int(c) for _, c in rows if c is not None))

    # ------------------------------------------------------------------ signatures
    def sign(self, cal_id: int, version: int, key_id: str, mac: str) -> Signature:
        """Store the signature a signer (the acting token's holder) made of ``version``, audited as
        ``sign`` in the same transaction; :class:`AlreadySigned` when it has one, :class:`NotFound`
        when there is no such version."""
        with self._tx() as db, self._errors():
            rec = self._row(db, cal_id)
            if not db.execute(
                "SELECT 1 FROM versions WHERE calibration_id = ? AND version = ?", (cal_id, version)
            ).fetchall():
                raise NotFound(
                    f"calibration {cal_id} has no version {version} (versions 1..{rec.current_version})"
                )
            if self._signature(db, cal_id, version) is not None:
                raise AlreadySigned(f"calibration {rec.name!r} version {version} is signed already")
            sig = self._insert_signature(db, cal_id, version, (key_id, mac, "sign"))
            self._audit(db, "sign", rec, version, version, f"signed version {version} (key {key_id})")
        return sig

    def signature(self, cal_id: int, version: int) -> Signature | None:
        """The version's signature, or None (unsigned)."""
        rows = self._read(
            "SELECT calibration_id, version, utc, signer, origin, key_id, mac FROM signatures "
            "WHERE calibration_id = ? AND version = ?",
            (cal_id, version),
        )
        return _signature(rows[0]) if rows else None

    def signatures(self, cal_id: int) -> dict[int, Signature]:
        """Every signed version of a calibration: version -> its signature."""
        rows = self._read(
            "SELECT calibration_id, version, utc, signer, origin, key_id, mac FROM signatures "
            "WHERE calibration_id = ? ORDER BY version",
            (cal_id,),
        )
        return {int(r[1]): _signature(r) for r in rows}

    @staticmethod
    def _signature(db, cal_id: int, version: int) -> Signature | None:
        row = db.execute(
            "SELECT calibration_id, version, utc, signer, origin, key_id, mac FROM signatures "
            "WHERE calibration_id = ? AND version = ?",
            (cal_id, version),
        ).fetchone()
        return None if row is None else _signature(row)

    @staticmethod
    def _insert_signature(db, cal_id: int, version: int, carried: tuple[str, str, str]) -> Signature:
        """Insert (key_id, mac, origin) as the version's signature, signed by the acting holder."""
        key_id, mac, origin = carried
        sig = Signature(cal_id, version, _now(), audit.current_user(), origin, key_id, mac)
        db.execute(
            "INSERT INTO signatures (calibration_id, version, utc, signer, origin, key_id, mac) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (cal_id, version, sig.utc, sig.signer, origin, key_id, mac),
        )
        return sig

    def audit(self, query: AuditQuery | None = None) -> builtins.list[AuditEntry]:
        """Audit entries, newest first (see :class:`~eyetohand.server.audit.AuditQuery`)."""
        q = query or AuditQuery()
        where, args = q.where()
        rows = self._read(
            "SELECT id, utc, user_name, action, calibration_id, calibration, version_before, "
            f"version_after, note FROM audit{where} ORDER BY id DESC LIMIT ?",
            (*args, max(1, min(q.limit, AuditQuery.MAX_LIMIT))),
        )
        return [AuditEntry(*r) for r in rows]

    # ------------------------------------------------------------------ reads
    def list(self) -> list[tuple[Record, Version]]:
        rows = self._read(
            "SELECT c.id, c.name, c.created_utc, c.updated_utc, c.current_version, "
            "v.calibration_id, v.version, v.created_utc, v.note, v.request_json, "
            "v.calibration_json, v.pairs_json, v.check_json "
            "FROM calibrations c JOIN versions v "
            "ON v.calibration_id = c.id AND v.version = c.current_version ORDER BY c.id"
        )
        return [(Record(*r[:5]), _version(r[5:])) for r in rows]

    def get(self, cal_id: int) -> Record:
        if not 0 <= cal_id < 2**63:  # no row has it (and SQLite cannot even be asked: int64)
            raise NotFound(f"no calibration with id {cal_id}")
        rows = self._read(
            "SELECT id, name, created_utc, updated_utc, current_version FROM calibrations WHERE id = ?",
            (cal_id,),
        )
        row = rows[0] if rows else None
        if row is None:
            raise NotFound(f"no calibration with id {cal_id}")
        return Record(*row)

    def by_name(self, name: str) -> Record | None:
        rows = self._read(
            "SELECT id, name, created_utc, updated_utc, current_version FROM calibrations WHERE name = ?",
            (unicodedata.normalize("NFC", name),),
        )
        row = rows[0] if rows else None
        return None if row is None else Record(*row)

    def find(self, name_or_id: str) -> Record:
        """By exact name (NFC), or by id: digits, or ``id:N``. A reference that is the name of one
        calibration and the id of another (a name stored before digit-only names were refused) is
        refused as :class:`Ambiguous`, never resolved by guessing."""
        ref = name_or_id.strip()
        if ref.lower().startswith("name:"):
            rec = self.by_name(name_or_id.strip()[5:])
            if rec is None:
                raise NotFound(f"no calibration named {name_or_id.strip()[5:]!r}")
            return rec
        if ref.lower().startswith("id:") and is_id_like(ref[3:].strip()):
            return self.get(int(ref[3:].strip()))
        rec = self.by_name(name_or_id)
        if is_id_like(ref):
            try:
                by_id = self.get(int(ref))
            except NotFound:
                by_id = None
            if rec is not None and by_id is not None and rec.id != by_id.id:
                raise Ambiguous(
                    f"{ref!r} is the name of calibration {rec.id} and the id of calibration "
                    f"{by_id.id}; say 'id:{by_id.id}', or rename calibration {rec.id}"
                )
            rec = rec or by_id
        if rec is not None:
            return rec
        raise NotFound(f"no calibration named {name_or_id!r}")

    def version(self, cal_id: int, version: int | None = None) -> Version:
        rec = self.get(cal_id)
        v = rec.current_version if version is None else version
        rows = self._read(
            "SELECT calibration_id, version, created_utc, note, request_json, calibration_json, "
            "pairs_json, check_json FROM versions WHERE calibration_id = ? AND version = ?",
            (cal_id, v),
        )
        row = rows[0] if rows else None
        if row is None:
            raise NotFound(f"calibration {cal_id} has no version {v} (versions 1..{rec.current_version})")
        return _version(row)

    def versions(self, cal_id: int) -> builtins.list[Version]:
        self.get(cal_id)
        rows = self._read(
            "SELECT calibration_id, version, created_utc, note, request_json, calibration_json, "
            "pairs_json, check_json FROM versions WHERE calibration_id = ? ORDER BY version",
            (cal_id,),
        )
        return [_version(r) for r in rows]

    # ------------------------------------------------------------------ writes
    @staticmethod
    def _refuse_lookalike(db: sqlite3.Connection, name: str, cal_id: int | None) -> None:
        """NameTaken when another calibration's name looks the same (:func:`name_skeleton`); called
        inside the write transaction, so two requests cannot both take look-alike names."""
        want = name_skeleton(name)
        for other_id, other in db.execute("SELECT id, name FROM calibrations").fetchall():
            if other_id != cal_id and name_skeleton(other) == want:
                same = (
                    "" if other == name else f" ({name!r} looks the same: same letters up to case or script)"
                )
                raise NameTaken(f"a calibration named {other!r} exists already{same}")

    @staticmethod
    def _row(db: sqlite3.Connection, cal_id: int, if_match: str | None = None) -> Record:
        """The calibration's row inside a transaction; :class:`Conflict` when ``if_match`` (an
        ``If-Match`` value: one or more ETags, or ``*``) names none of its current state."""
        row = db.execute(
            "SELECT id, name, created_utc, updated_utc, current_version FROM calibrations WHERE id = ?",
            (cal_id,),
        ).fetchone()
        if row is None:
            raise NotFound(f"no calibration with id {cal_id}")
        rec = Record(*row)
        require_match(rec, if_match)
        return rec

    def create(
        self,
        name: str,
        request: dict,
        calibration: dict,
        pairs: builtins.list,
        check: builtins.list | None,
        note: str = "created",
        *,
        action: str | None = None,
        signature: tuple[str, str, str] | None = None,
    ) -> Record:
        """A new calibration with its version 1. ``action``: its audit action (default from
        ``request["source"]``: :func:`~eyetohand.server.audit.action_of`). ``signature``: (key_id,
        mac, origin) the version carries (an imported signed file), stored in the same transaction."""
        now = _now()
        try:
            with self._tx() as db, self._errors():
                self._refuse_lookalike(db, name, None)
                cal_id = int(
                    db.execute(
                        "INSERT INTO calibrations (name, created_utc, updated_utc, current_version) "
                        "VALUES (?, ?, ?, 1) RETURNING id",
                        (name, now, now),
                    ).fetchall()[0][0]
                )
                self._insert_version(db, cal_id, 1, now, note, request, calibration, pairs, check)
                if signature is not None:
                    self._insert_signature(db, cal_id, 1, signature)
                rec = Record(cal_id, name, now, now, 1)
                self._audit(db, action or audit.action_of(request, new=True), rec, None, 1, note)
        except self._integrity_error:
            raise NameTaken(f"a calibration named {name!r} exists already") from None
        return rec

    def add_version(
        self,
        cal_id: int,
        request: dict,
        calibration: dict,
        pairs: builtins.list,
        check: builtins.list | None,
        note: str,
        if_match: str | None = None,
        *,
        action: str | None = None,
        signature: tuple[str, str, str] | None = None,
    ) -> Record:
        """Add a version and make it current (``signature``: see :meth:`create`). Returns the record
        as this transaction left it: its ``current_version`` is the version this call created (never
        one a concurrent call added after the commit). ``if_match``: see :meth:`_row` (:class:`Conflict`,
        nothing written). ``action``: its audit action (default from ``request["source"]``)."""
        now = _now()
        with self._tx() as db, self._errors():
            rec = self._row(db, cal_id, if_match)
            latest = db.execute(
                "SELECT MAX(version) FROM versions WHERE calibration_id = ?", (cal_id,)
            ).fetchone()[0]
            new = int(latest) + 1
            self._insert_version(db, cal_id, new, now, note, request, calibration, pairs, check)
            if signature is not None:
                self._insert_signature(db, cal_id, new, signature)
            db.execute(
                "UPDATE calibrations SET current_version = ?, updated_utc = ? WHERE id = ?",
                (new, now, cal_id),
            )
            after = Record(rec.id, rec.name, rec.created_utc, now, new)
            self._audit(
                db, action or audit.action_of(request, new=False), after, rec.current_version, new, note
            )
        return after

    def rollback(self, cal_id: int, version: int, if_match: str | None = None) -> Record:
        """Make a copy of ``version`` the new current version (the history keeps everything); the
        record names the version this call created. The copy carries the signature of ``version``
        (the same content, signed), origin ``rollback``."""
        old = self.version(cal_id, version)
        sig = self.signature(cal_id, version)
        return self.add_version(
            cal_id,
            old.request,
            old.calibration,
            old.pairs,
            old.check,
            note=f"rollback to version {version}",
            if_match=if_match,
            action="rollback",
            signature=None if sig is None else (sig.key_id, sig.mac, "rollback"),
        )

    def rename(self, cal_id: int, name: str, if_match: str | None = None) -> Record:
        now = _now()
        try:
            with self._tx() as db, self._errors():
                rec = self._row(db, cal_id, if_match)
                self._refuse_lookalike(db, name, cal_id)
                db.execute(
                    "UPDATE calibrations SET name = ?, updated_utc = ? WHERE id = ?", (name, now, cal_id)
                )
                after = Record(rec.id, name, rec.created_utc, now, rec.current_version)
                v = rec.current_version
                self._audit(db, "rename", after, v, v, f"renamed from {rec.name!r} to {name!r}")
        except self._integrity_error:
            raise NameTaken(f"a calibration named {name!r} exists already") from None
        return after

    def current(self, cal_id: int) -> tuple[str, int] | None:
        """(name, current version) of a calibration, or None when it is gone: one indexed read, cheap
        enough to poll."""
        rows = self._read("SELECT name, current_version FROM calibrations WHERE id = ?", (cal_id,))
        return None if not rows else (str(rows[0][0]), int(rows[0][1]))

    def add_verification(self, cal_id: int, version: int, entry: dict) -> None:
        """Append one verification entry (see :mod:`eyetohand.calibration.verify`) to a calibration's
        history."""
        with self._tx() as db, self._errors():
            rec = self._row(db, cal_id)
            db.execute(
                "INSERT INTO verifications (calibration_id, version, utc, entry_json) VALUES (?, ?, ?, ?)",
                (cal_id, version, _now(), _dumps(entry)),
            )
            self._audit(db, "check", rec, version, version, audit.check_note(entry))

    def verifications(self, cal_id: int) -> builtins.list[dict]:
        """The verification history, oldest first, each entry with the version it checked."""
        self.get(cal_id)
        rows = self._read(
            "SELECT version, utc, entry_json FROM verifications WHERE calibration_id = ? ORDER BY rowid",
            (cal_id,),
        )
        return [{**json.loads(e), "version": int(v), "stored_utc": u} for v, u, e in rows]

    def delete(self, cal_id: int, if_match: str | None = None) -> None:
        with self._tx() as db, self._errors():
            rec = self._row(db, cal_id, if_match)
            self._audit(db, "delete", rec, rec.current_version, None, f"deleted {rec.name!r}")
            db.execute("DELETE FROM verifications WHERE calibration_id = ?", (cal_id,))
            db.execute("DELETE FROM signatures WHERE calibration_id = ?", (cal_id,))
            db.execute("DELETE FROM versions WHERE calibration_id = ?", (cal_id,))
            cur = db.execute("DELETE FROM calibrations WHERE id = ?", (cal_id,))
            if cur.rowcount == 0:
                raise NotFound(f"no calibration with id {cal_id}")

    @staticmethod
    def _insert_version(db, cal_id, version, now, note, request, calibration, pairs, check) -> None:
        db.execute(
            "INSERT INTO versions (calibration_id, version, created_utc, note, request_json, "
            "calibration_json, pairs_json, check_json) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (
                cal_id,
                version,
                now,
                note,
                _dumps(request),
                _dumps(calibration),
                _dumps(pairs),
                None if check is None else _dumps(check),
            ),
        )


def _dumps(obj) -> str:
    return json.dumps(obj, allow_nan=False, separators=(",", ":"))


def _version(row) -> Version:
    cid, ver, created, note, req, cal, pairs, check = row
    return Version(
        int(cid),
        int(ver),
        created,
        note,
        json.loads(req),
        json.loads(cal),
        json.loads(pairs),
        None if check is None else json.loads(check),
    )


def _signature(row) -> Signature:
    cid, ver, utc, signer, origin, key_id, mac = row
    return Signature(int(cid), int(ver), utc, signer, origin, key_id, mac)
