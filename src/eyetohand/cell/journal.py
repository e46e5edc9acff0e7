"""The append-only journals of the line protocols' collections (CAL, BELT): JSON lines with fsync
(:class:`JsonlJournal`) or a table of an SQLite file (:class:`SqliteJournal`); a refused command leaves
no record, a record torn by a kill is cut off when opened."""

from __future__ import annotations

import datetime as _dt
import json
import os
import sqlite3
from pathlib import Path
from typing import Protocol

from eyetohand.core import InputError

SQLITE_SUFFIXES = (".db", ".sqlite", ".sqlite3")


def utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


class Journal(Protocol):
    """What a collection writes its records to: every record written (and fsync-ed) whole or not at all;
    ``path`` the file."""

    path: Path

    def records(self) -> list[dict]:
        """The records written so far, oldest first."""
        ...

    def append(self, rec: dict) -> None:
        """Write one record durably, or raise ``OSError`` / ``sqlite3.Error`` with nothing written."""
        ...

    def close(self) -> None: ...


class JsonlJournal:
    """Append-only JSON lines with fsync; a torn last line is cut off when opened."""

    def __init__(self, path: Path):
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._records = []
        if path.exists():
            data = path.read_bytes()
            cut = data.rfind(b"\n") + 1
            if cut < len(data):  # killed in mid-write: drop the partial record
                with open(path, "r+b") as fh:
                    fh.truncate(cut)
                    fh.flush()
                    os.fsync(fh.fileno())
            for k, line in enumerate(data[:cut].splitlines(), start=1):
                if line.strip():
                    try:
                        self._records.append(json.loads(line))
                    except json.JSONDecodeError:
                        raise InputError(f"{path} line {k}: not a journal record (invalid JSON)") from None
        # unbuffered: a write that fails leaves nothing behind in a buffer for a later write to flush
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def records(self) -> list[dict]:
        return list(self._records)

    def append(self, rec: dict) -> None:
        """Write and fsync one record, or raise ``OSError`` with the file as it was (a record written
        in part is cut off again): a refused command leaves no record, now or later."""
        data = (json.dumps(rec, allow_nan=False, separators=(",", ":")) + "\n").encode()
        size = os.fstat(self._fd).st_size
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view) :]
            os.fsync(self._fd)
        except OSError:
            try:
                os.ftruncate(self._fd, size)
                os.fsync(self._fd)
            except OSError:
                pass  # a torn tail is cut off when the journal is opened again
            raise
        self._records.append(rec)

    def close(self) -> None:
        os.close(self._fd)


class SqliteJournal:
    """The same records in one SQLite table (WAL, synchronous=FULL: a commit survives a crash)."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute(
            "CREATE TABLE IF NOT EXISTS collect_journal "
            "(seq INTEGER PRIMARY KEY AUTOINCREMENT, record TEXT NOT NULL)"
        )

    def records(self) -> list[dict]:
        return [json.loads(r) for (r,) in self._db.execute("SELECT record FROM collect_journal ORDER BY seq")]

    def append(self, rec: dict) -> None:
        with self._db:
            self._db.execute(
                "INSERT INTO collect_journal (record) VALUES (?)",
                (json.dumps(rec, allow_nan=False, separators=(",", ":")),),
            )

    def close(self) -> None:
        self._db.close()


__all__ = ["SQLITE_SUFFIXES", "Journal", "JsonlJournal", "SqliteJournal", "utc_now"]
