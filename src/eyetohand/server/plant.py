"""The plant view: every calibration of a shared store with its version in force, its last check and
drift, and the cells (``serve`` processes) that follow it.

Each ``serve`` registers itself in the store's ``cells`` table and beats every :data:`BEAT_S` (from its
store follower's thread: :mod:`~eyetohand.server.follow`): its name (host and HTTP address), what it
maps with (a stored calibration and the version it answers with now, or a file), when it started and
when it was last seen. A cell not seen for :data:`ALIVE_S` is shown as silent, not removed: a row goes
only when its cell beats again (same name) or an administrator deletes it. Beats are not changes of a
calibration: they are not audited and not copied by ``eyetohand store copy``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import socket
from dataclasses import asdict, dataclass

from eyetohand.server.storage import Store

BEAT_S = 5.0
ALIVE_S = 3 * BEAT_S


@dataclass(frozen=True)
class CellBeat:
    """One beat of a cell: who it is and what it answers with now."""

    cell: str  # "<host> <http address>": the same after a restart
    pid: int
    url: str
    calibration_id: int | None  # a stored calibration it follows (None: a file, or nothing yet)
    calibration: str  # its name, or the file it maps with
    version: int | None  # the version its robots are answered with now
    started_utc: str
    seen_utc: str = ""

    @classmethod
    def of_this_process(
        cls, url: str, calibration_id: int | None, calibration: str, version: int | None, started_utc: str
    ) -> CellBeat:
        return cls(
            f"{socket.gethostname()} {url}",
            os.getpid(),
            url,
            calibration_id,
            calibration,
            version,
            started_utc,
        )

    def to_dict(self, now: _dt.datetime | None = None) -> dict:
        d = asdict(self)
        d["alive"] = alive(self.seen_utc, now)
        return d


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def alive(seen_utc: str, now: _dt.datetime | None = None) -> bool:
    try:
        seen = _dt.datetime.fromisoformat(seen_utc)
    except ValueError:
        return False
    return ((now or _dt.datetime.now(_dt.UTC)) - seen).total_seconds() <= ALIVE_S


def beat(store: Store, b: CellBeat) -> None:
    """Register or refresh ``b`` (one upsert, in the store's write transaction)."""
    with store._tx() as db, store._errors():
        db.execute(
            "INSERT INTO cells (cell, pid, url, calibration_id, calibration, version, started_utc, seen_utc) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (cell) DO UPDATE SET pid = excluded.pid, "
            "url = excluded.url, calibration_id = excluded.calibration_id, "
            "calibration = excluded.calibration, version = excluded.version, "
            "started_utc = excluded.started_utc, seen_utc = excluded.seen_utc",
            (b.cell, b.pid, b.url, b.calibration_id, b.calibration, b.version, b.started_utc, _now()),
        )


def cells(store: Store) -> list[CellBeat]:
    rows = store._read(
        "SELECT cell, pid, url, calibration_id, calibration, version, started_utc, seen_utc "
        "FROM cells ORDER BY cell"
    )
    return [CellBeat(*r) for r in rows]


def _last_checks(store: Store) -> dict[int, dict]:
    """Each calibration's last verification entry (with the version it checked and when)."""
    rows = store._read(
        "SELECT v.calibration_id, v.version, v.utc, v.entry_json FROM verifications v "
        "JOIN (SELECT calibration_id, MAX(rowid) AS last FROM verifications GROUP BY calibration_id) m "
        "ON v.calibration_id = m.calibration_id AND v.rowid = m.last"
    )
    out = {}
    for cid, version, utc, entry_json in rows:
        e = json.loads(entry_json)
        out[int(cid)] = {
            "version": int(version),
            "utc": utc,
            "passed": e.get("passed"),
            "rms_mm": e.get("rms_mm"),
            "max_mm": e.get("max_mm"),
            "tolerance_mm": e.get("tolerance_mm"),
            "drift_significant": e.get("drift_significant"),
            "shift_mm": e.get("shift_mm"),
            "rotation_deg": e.get("rotation_deg"),
            "named": e.get("named"),
        }
    return out


def plant_view(store: Store) -> dict:
    """``GET /api/plant``: every calibration (id, name, version in force, ETag, last check, the cells
    that follow it) and every cell that follows none of them (a file, or nothing yet)."""
    now = _dt.datetime.now(_dt.UTC)
    checks = _last_checks(store)
    all_cells = cells(store)
    rows = []
    known = set()
    for rec, _ver in store.list():
        known.add(rec.id)
        rows.append(
            {
                "id": rec.id,
                "name": rec.name,
                "current_version": rec.current_version,
                "etag": rec.etag,
                "updated_utc": rec.updated_utc,
                "last_check": checks.get(rec.id),
                "cells": [c.to_dict(now) for c in all_cells if c.calibration_id == rec.id],
            }
        )
    others = [c.to_dict(now) for c in all_cells if c.calibration_id not in known]
    return {"calibrations": rows, "other_cells": others, "alive_s": ALIVE_S}
