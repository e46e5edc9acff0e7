"""The store in PostgreSQL (a plant's shared database): the same calibrations, versions, verifications
and audit trail as the SQLite store, through psycopg 3 (``pip install 'eyetohand[postgres]'``).

Every method of :class:`~eyetohand.server.storage.Store` works unchanged: the SQL is shared (written
with ``?`` placeholders, turned into psycopg's ``%s`` here), only the connection, the transaction and
the translation of failures differ. Each write is one transaction that first takes one advisory lock
(``pg_advisory_xact_lock``), so writes from every process on the database are serialised as SQLite's
``BEGIN IMMEDIATE`` serialises them in one file: a version number or a look-alike name is decided by
one writer at a time. A write waits at most ``wait_s`` for that lock (``lock_timeout``), then
:class:`~eyetohand.server.storage.Busy`; an unreachable database is
:class:`~eyetohand.server.storage.StorageError` (503), never a crash, and the next call reconnects.
Each committed change also sends ``NOTIFY eyetohand, '<calibration id>'`` (the id only: a follower
reads what changed from the tables).
"""

from __future__ import annotations

import queue
import select
import threading
import urllib.parse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from eyetohand.server.storage import WAIT_S, Busy, NoSpace, Record, StorageError, Store

LOCK_KEY = 0x6579_6574  # "eyet": the advisory lock every write takes
CHANNEL = "eyetohand"
CONNECT_TIMEOUT_S = 5
POOL_SIZE = 4
"""The most connections one store holds (a plant's cells share the server's ``max_connections``)."""


def masked(url: str) -> str:
    """``url`` with its password (if any) replaced by ``***``, for messages and logs."""
    parts = urllib.parse.urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username or ''}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urllib.parse.urlunsplit(parts._replace(netloc=netloc))


class _Conn:
    """A psycopg connection that takes the store's ``?`` placeholders."""

    def __init__(self, conn):
        self.conn = conn

    def execute(self, sql: str, args: tuple = ()):
        return self.conn.execute(sql.replace("?", "%s"), args or None)


class PgStore(Store):
    """The store on a PostgreSQL database through a small pool: at most :data:`POOL_SIZE`
    connections, each lent to one thread for one read or one transaction (autocommit outside the
    write transactions); a connection that failed is dropped and the next call opens a new one. A call
    that finds every connection lent waits at most ``wait_s``, then :class:`Busy`."""

    dialect = "postgresql"

    def __init__(self, url: str, wait_s: float = WAIT_S, *, create: bool = True):
        """Open the database at ``url`` (``postgresql://USER[:PASSWORD]@HOST:PORT/DB``; the password
        may come from ``PGPASSWORD`` or ``~/.pgpass`` instead). Its tables are made on first use
        (``create`` is accepted for the SQLite store's signature: a server's database is made by
        its administrator, the tables by the first program that opens it)."""
        import psycopg

        self._psycopg = psycopg
        self._integrity_error = psycopg.errors.IntegrityError
        self.url = url
        self.where = masked(url)
        self.path = Path(self.where)  # only named in messages; there is no file to check
        self.wait_s = float(wait_s)
        self._idle: queue.LifoQueue[Any] = queue.LifoQueue()
        self._slots = threading.BoundedSemaphore(POOL_SIZE)
        self._closed = False
        self._migrate()

    # ------------------------------------------------------------ connection and transaction
    def check_same_file(self) -> None:
        """Nothing to prove: a server's database is reached by its address, not a file."""

    def _errors(self):
        return _translated(self.where, self._psycopg)

    @contextmanager
    def _borrow(self) -> Iterator[Any]:
        """A connection of the pool for the time of the block (an idle one, else a new one)."""
        if self._closed:
            raise StorageError(f"the store of {self.where} is closed")
        if not self._slots.acquire(timeout=self.wait_s):
            raise Busy(
                f"all {POOL_SIZE} connections to the database {self.where} are busy; try again shortly"
            )
        conn = None
        try:
            while conn is None and not self._idle.empty():
                conn = self._idle.get_nowait()
                if conn.closed or conn.broken or _stale(conn):
                    conn.close()
                    conn = None
            if conn is None:
                with self._errors():
                    conn = self._psycopg.connect(self.url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S)
                    conn.execute(f"SET lock_timeout = {int(self.wait_s * 1000)}")
            yield conn
        finally:
            if conn is not None:
                if self._closed or conn.closed or conn.broken:
                    conn.close()
                else:
                    self._idle.put(conn)
            self._slots.release()

    @contextmanager
    def _tx(self) -> Iterator[Any]:
        """One transaction that holds the store's advisory lock: committed or rolled back whole. A
        connection lost during the COMMIT itself leaves the outcome unknown, and says so (a write is
        not idempotent: sent again blindly, it could add a second version)."""
        done = False
        try:
            with self._borrow() as conn, self._errors(), conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (LOCK_KEY,))
                yield _Conn(conn)
                done = True
        except StorageError as exc:
            if not done or isinstance(exc, Busy | NoSpace):
                raise
            raise StorageError(
                f"the database {self.where} was lost while committing: the change may or may not be "
                "stored; look at the audit trail (GET /api/audit, eyetohand audit) before sending it again"
            ) from None

    def _read(self, sql: str, args: tuple = ()) -> list:
        with self._borrow() as conn, self._errors():
            return _Conn(conn).execute(sql, args).fetchall()

    def _audit(self, db, action: str, rec: Record, before: int | None, after: int | None, note: str) -> None:
        super()._audit(db, action, rec, before, after, note)
        db.execute("SELECT pg_notify(?, ?)", (CHANNEL, str(rec.id)))

    def close(self) -> None:
        """Close the idle connections; those lent out close when they come back."""
        self._closed = True
        while not self._idle.empty():
            try:
                self._idle.get_nowait().close()
            except (queue.Empty, self._psycopg.Error):
                pass

    def integrity_check(self) -> str:
        """``ok``, or what is inconsistent: a calibration whose current version is not stored."""
        rows = self._read(
            "SELECT c.id, c.current_version FROM calibrations c LEFT JOIN versions v "
            "ON v.calibration_id = c.id AND v.version = c.current_version WHERE v.version IS NULL"
        )
        if not rows:
            return "ok"
        return "; ".join(f"calibration {i}: current version {v} is not stored" for i, v in rows)


@contextmanager
def _translated(where: str, psycopg) -> Iterator[None]:
    """psycopg's operational failures as :class:`StorageError` (503; a lock not had in time:
    :class:`Busy`; a full disk: :class:`NoSpace`). Integrity errors pass (the store names them)."""
    try:
        yield
    except psycopg.errors.LockNotAvailable:
        raise Busy(
            f"the database {where} is busy (another writer holds its lock); try again shortly"
        ) from None
    except psycopg.errors.DiskFull as exc:
        raise NoSpace(
            f"no space to write the database {where} ({_first_line(exc)}); nothing was changed"
        ) from None
    except psycopg.OperationalError as exc:
        raise StorageError(
            f"the database {where} is unreachable ({_first_line(exc)}); nothing was changed"
        ) from None


def _stale(conn) -> bool:
    """Has the server written to this idle connection? It says nothing unasked but its last words: a
    restarted or stopped server's "terminating connection" notice, or the socket's end. Such a
    connection would fail its next statement, and a change made just after the database came back
    was refused once (503) while /api/health, on another connection, said ok. One ``select`` with no
    wait, no round trip; a connection whose socket cannot be polled counts as stale."""
    try:
        readable, _, _ = select.select([conn.fileno()], [], [], 0)
    except (OSError, ValueError):
        return True
    return bool(readable)


def _first_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
