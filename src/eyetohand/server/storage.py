"""Calibrations and their versions in an embedded SQLite database (one file, ``calibrations.db``).

Every change is one transaction; the database runs in WAL mode with ``synchronous=FULL``, so a
crash (of the process or of the machine) loses no committed change and never leaves half of one.
A calibration has a name (unique, stored as data only: it never reaches a file path) and a list of
versions 1, 2, 3, …; each version keeps the fitted calibration (the JSON that ``eyetohand apply``
reads), the pairs it was fitted on, the check pairs, the fit request and a note. Versions are never
changed or removed: a refit adds one, and rolling back to version *n* adds a new version that is a
copy of *n* (so the history still shows what was in force, and when).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

DB_NAME = "calibrations.db"

SCHEMA_SQL = """
CREATE TABLE IF NOT EXISTS calibrations (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    name TEXT NOT NULL UNIQUE,
    created_utc TEXT NOT NULL,
    updated_utc TEXT NOT NULL,
    current_version INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS versions (
    calibration_id INTEGER NOT NULL REFERENCES calibrations(id) ON DELETE CASCADE,
    version INTEGER NOT NULL,
    created_utc TEXT NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    request_json TEXT NOT NULL,
    calibration_json TEXT NOT NULL,
    pairs_json TEXT NOT NULL,
    check_json TEXT,
    PRIMARY KEY (calibration_id, version)
);
"""


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
class Record:
    id: int
    name: str
    created_utc: str
    updated_utc: str
    current_version: int


class Store:
    """Thread-safe access to the database: one connection, serialised by a lock (SQLite writes are
    serial anyway, and every operation here takes well under a millisecond)."""

    def __init__(self, data_dir: str | os.PathLike):
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.data_dir / DB_NAME
        self._lock = threading.RLock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._db.execute("PRAGMA busy_timeout=5000")
        with self._tx() as db:
            for stmt in SCHEMA_SQL.split(";"):
                if stmt.strip():
                    db.execute(stmt)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One IMMEDIATE transaction: committed as a whole or rolled back as a whole."""
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    # ------------------------------------------------------------------ reads
    def list(self) -> list[tuple[Record, Version]]:
        with self._lock:
            rows = self._db.execute(
                "SELECT c.id, c.name, c.created_utc, c.updated_utc, c.current_version, "
                "v.calibration_id, v.version, v.created_utc, v.note, v.request_json, "
                "v.calibration_json, v.pairs_json, v.check_json "
                "FROM calibrations c JOIN versions v "
                "ON v.calibration_id = c.id AND v.version = c.current_version ORDER BY c.id"
            ).fetchall()
        return [(Record(*r[:5]), _version(r[5:])) for r in rows]

    def get(self, cal_id: int) -> Record:
        with self._lock:
            row = self._db.execute(
                "SELECT id, name, created_utc, updated_utc, current_version FROM calibrations WHERE id = ?",
                (cal_id,),
            ).fetchone()
        if row is None:
            raise NotFound(f"no calibration with id {cal_id}")
        return Record(*row)

    def by_name(self, name: str) -> Record | None:
        with self._lock:
            row = self._db.execute(
                "SELECT id, name, created_utc, updated_utc, current_version FROM calibrations WHERE name = ?",
                (name,),
            ).fetchone()
        return None if row is None else Record(*row)

    def find(self, name_or_id: str) -> Record:
        """By exact name, else by numeric id."""
        rec = self.by_name(name_or_id)
        if rec is not None:
            return rec
        if name_or_id.isdigit():
            return self.get(int(name_or_id))
        raise NotFound(f"no calibration named {name_or_id!r}")

    def version(self, cal_id: int, version: int | None = None) -> Version:
        rec = self.get(cal_id)
        v = rec.current_version if version is None else version
        with self._lock:
            row = self._db.execute(
                "SELECT calibration_id, version, created_utc, note, request_json, calibration_json, "
                "pairs_json, check_json FROM versions WHERE calibration_id = ? AND version = ?",
                (cal_id, v),
            ).fetchone()
        if row is None:
            raise NotFound(f"calibration {cal_id} has no version {v} (versions 1..{rec.current_version})")
        return _version(row)

    def versions(self, cal_id: int) -> list[Version]:
        self.get(cal_id)
        with self._lock:
            rows = self._db.execute(
                "SELECT calibration_id, version, created_utc, note, request_json, calibration_json, "
                "pairs_json, check_json FROM versions WHERE calibration_id = ? ORDER BY version",
                (cal_id,),
            ).fetchall()
        return [_version(r) for r in rows]

    # ------------------------------------------------------------------ writes
    def create(self, name: str, request: dict, calibration: dict, pairs: list, check: list | None,
               note: str = "created") -> Record:
        now = _now()
        try:
            with self._tx() as db:
                cur = db.execute(
                    "INSERT INTO calibrations (name, created_utc, updated_utc, current_version) "
                    "VALUES (?, ?, ?, 1)",
                    (name, now, now),
                )
                cal_id = int(cur.lastrowid)
                self._insert_version(db, cal_id, 1, now, note, request, calibration, pairs, check)
        except sqlite3.IntegrityError:
            raise NameTaken(f"a calibration named {name!r} exists already") from None
        return self.get(cal_id)

    def add_version(self, cal_id: int, request: dict, calibration: dict, pairs: list,
                    check: list | None, note: str) -> Record:
        now = _now()
        with self._tx() as db:
            row = db.execute("SELECT current_version FROM calibrations WHERE id = ?", (cal_id,)).fetchone()
            if row is None:
                raise NotFound(f"no calibration with id {cal_id}")
            latest = db.execute(
                "SELECT MAX(version) FROM versions WHERE calibration_id = ?", (cal_id,)
            ).fetchone()[0]
            new = int(latest) + 1
            self._insert_version(db, cal_id, new, now, note, request, calibration, pairs, check)
            db.execute("UPDATE calibrations SET current_version = ?, updated_utc = ? WHERE id = ?",
                       (new, now, cal_id))
        return self.get(cal_id)

    def rollback(self, cal_id: int, version: int) -> Record:
        """Make a copy of ``version`` the new current version (the history keeps everything)."""
        old = self.version(cal_id, version)
        return self.add_version(cal_id, old.request, old.calibration, old.pairs, old.check,
                                note=f"rollback to version {version}")

    def rename(self, cal_id: int, name: str) -> Record:
        try:
            with self._tx() as db:
                cur = db.execute("UPDATE calibrations SET name = ?, updated_utc = ? WHERE id = ?",
                                 (name, _now(), cal_id))
                if cur.rowcount == 0:
                    raise NotFound(f"no calibration with id {cal_id}")
        except sqlite3.IntegrityError:
            raise NameTaken(f"a calibration named {name!r} exists already") from None
        return self.get(cal_id)

    def delete(self, cal_id: int) -> None:
        with self._tx() as db:
            db.execute("DELETE FROM versions WHERE calibration_id = ?", (cal_id,))
            cur = db.execute("DELETE FROM calibrations WHERE id = ?", (cal_id,))
            if cur.rowcount == 0:
                raise NotFound(f"no calibration with id {cal_id}")

    @staticmethod
    def _insert_version(db, cal_id, version, now, note, request, calibration, pairs, check) -> None:
        db.execute(
            "INSERT INTO versions (calibration_id, version, created_utc, note, request_json, "
            "calibration_json, pairs_json, check_json) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (cal_id, version, now, note, _dumps(request), _dumps(calibration), _dumps(pairs),
             None if check is None else _dumps(check)),
        )


def _dumps(obj) -> str:
    return json.dumps(obj, allow_nan=False, separators=(",", ":"))


def _version(row) -> Version:
    cid, ver, created, note, req, cal, pairs, check = row
    return Version(int(cid), int(ver), created, note, json.loads(req), json.loads(cal), json.loads(pairs),
                   None if check is None else json.loads(check))
