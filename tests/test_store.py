"""The store of calibrations, the same suite on both backends: SQLite (a file) and PostgreSQL (a real
server: tests/pg.py starts one). Versions, the audit trail, the schema's versions, transactions,
concurrent writers from two stores, the copy between backends, and an unreachable server."""

from __future__ import annotations

import threading

import pytest

from eyetohand.server import schema
from eyetohand.server.audit import AuditQuery, acting_as
from eyetohand.server.storage import Conflict, NameTaken, NotFound, SchemaTooNew, StorageError, Store
from eyetohand.server.stores import StoreRef, StoreRefError, copy_store, open_store, store_digest


@pytest.fixture
def ref(store_url):
    """An empty store of each kind (tests/pg.py: a SQLite file, a fresh PostgreSQL database)."""
    return store_url


@pytest.fixture
def store(ref):
    s = open_store(ref, 10.0, create=True)
    yield s
    s.close()


def cal(n: int) -> dict:
    return {"model": {"name": "m", "n": n}, "fit": {"optimizer": "lm"}}


def pairs(n: int) -> list:
    return [{"id": f"p{i}", "u": 1.0 * i, "v": 2.0, "x": 3.0, "y": 4.0, "z": 0.5} for i in range(n)]


def trail(store: Store, **filters) -> list[tuple]:
    """(user, action, calibration, before, after) of the audit entries, oldest first."""
    entries = store.audit(AuditQuery(**filters))
    return [(e.user, e.action, e.calibration, e.version_before, e.version_after) for e in reversed(entries)]


def test_every_change_is_a_version_and_an_audit_entry(store):
    with acting_as("alice"):
        a = store.create("cell 1", {"source": "fit"}, cal(1), pairs(4), None)
        store.add_version(a.id, {"source": "fit"}, cal(2), pairs(5), pairs(2), "refit")
    with acting_as("bob"):
        store.add_version(a.id, {"source": "import"}, cal(3), [], None, "from file")
        store.add_version(a.id, {"source": "collection"}, cal(4), pairs(6), None, "collected")
        r = store.rollback(a.id, 2)
        store.add_verification(a.id, r.current_version, {"passed": True, "n": 3, "rms_mm": 0.12})
        store.rename(a.id, "cell 1 left")
    assert r.current_version == 5
    assert [v.version for v in store.versions(a.id)] == [1, 2, 3, 4, 5]
    assert store.version(a.id, 5).calibration == cal(2) and store.version(a.id, 5).pairs == pairs(5)
    assert store.version(a.id, 2).check == pairs(2)
    assert store.current(a.id) == ("cell 1 left", 5)
    assert trail(store) == [
        ("alice", "create", "cell 1", None, 1),
        ("alice", "new_version", "cell 1", 1, 2),
        ("bob", "import", "cell 1", 2, 3),
        ("bob", "cal_end", "cell 1", 3, 4),
        ("bob", "rollback", "cell 1", 4, 5),
        ("bob", "check", "cell 1", 5, 5),
        ("bob", "rename", "cell 1 left", 5, 5),
    ]
    notes = [e.note for e in reversed(store.audit())]
    assert notes[4] == "rollback to version 2"
    assert notes[5].startswith("passed on 3 points, rms 0.120 mm")
    assert notes[6] == "renamed from 'cell 1' to 'cell 1 left'"
    store.delete(a.id)
    with pytest.raises(NotFound):
        store.get(a.id)
    # the trail outlives the calibration
    assert trail(store)[-1] == ("local", "delete", "cell 1 left", 5, None)
    assert len(store.audit(AuditQuery(calibration_id=a.id))) == 8


def test_a_refused_write_changes_nothing_and_audits_nothing(store, monkeypatch):
    a = store.create("a", {}, cal(1), [], None)
    store.create("b", {}, cal(2), [], None)
    before = len(store.audit())
    with pytest.raises(NameTaken):
        store.create("A", {}, cal(3), [], None)  # looks the same as "a"
    with pytest.raises(NameTaken):
        store.rename(a.id, "b")
    with pytest.raises(Conflict):
        store.add_version(a.id, {}, cal(4), [], None, "stale", if_match='"1.7.00000000"')
    with pytest.raises(NotFound):
        store.add_verification(999, 1, {"passed": False})

    def boom(*_a, **_k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(type(store), "_insert_version", staticmethod(boom))
    with pytest.raises(RuntimeError):
        store.add_version(a.id, {}, cal(5), [], None, "v2")
    with pytest.raises(RuntimeError):
        store.create("c", {}, cal(6), [], None)
    monkeypatch.undo()
    assert len(store.audit()) == before
    assert [(r.name, r.current_version) for r, _ in store.list()] == [("a", 1), ("b", 1)]
    assert store.add_version(a.id, {}, cal(7), [], None, "ok", if_match=a.etag).current_version == 2


def test_versions_and_the_trail_cannot_be_rewritten(store):
    """The triggers refuse, whoever connects: an UPDATE of a version, an UPDATE or DELETE of an entry."""
    a = store.create("a", {}, cal(1), [], None)
    for sql in (
        "UPDATE versions SET note = 'forged' WHERE calibration_id = ?",
        "UPDATE audit SET user_name = 'nobody' WHERE calibration_id = ?",
        "DELETE FROM audit WHERE calibration_id = ?",
    ):
        with pytest.raises(Exception, match="immutable|append-only"):
            with store._tx() as db:
                db.execute(sql, (a.id,))
    assert store.version(a.id, 1).note == "created"
    assert trail(store) == [("local", "create", "a", None, 1)]


def test_audit_filters_and_pages(store):
    ids = []
    for i, user in enumerate(["ann", "ben", "ann"]):
        with acting_as(user):
            ids.append(store.create(f"c{i}", {}, cal(i), [], None).id)
    with acting_as("ben"):
        for _ in range(3):
            store.add_version(ids[0], {}, cal(9), [], None, "refit")
    everything = store.audit()
    assert [e.id for e in everything] == sorted((e.id for e in everything), reverse=True)
    assert len(everything) == 6
    assert [e.action for e in store.audit(AuditQuery(calibration_id=ids[0]))] == ["new_version"] * 3 + [
        "create"
    ]
    assert [e.calibration for e in store.audit(AuditQuery(user="ann"))] == ["c2", "c0"]
    assert store.audit(AuditQuery(calibration_name="c1"))[0].user == "ben"
    first, second = store.audit(AuditQuery(limit=4)), store.audit(AuditQuery(limit=4, before=None))
    assert first == second and len(first) == 4
    rest = store.audit(AuditQuery(limit=4, before=first[-1].id))
    assert [e.id for e in first + rest] == [e.id for e in everything]
    mid = everything[2].utc
    assert all(e.utc >= mid for e in store.audit(AuditQuery(since=mid)))
    assert all(e.utc <= mid for e in store.audit(AuditQuery(until=mid)))
    assert store.audit(AuditQuery(since="2999-01-01T00:00:00.000+00:00")) == []


def test_concurrent_writers_from_two_stores_number_versions_without_gaps(ref, store):
    """Two stores on one database (two processes of a plant) and four threads each: every version
    number taken once, every change audited with the version it followed."""
    other = open_store(ref, 10.0)
    a = store.create("shared", {}, cal(0), [], None)
    errors: list[BaseException] = []

    def write(s: Store, k: int) -> None:
        try:
            for i in range(8):
                s.add_version(a.id, {}, cal(100 * k + i), [], None, f"w{k}.{i}")
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=write, args=(s, k)) for k, s in enumerate([store, other] * 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    other.close()
    assert errors == []
    assert [v.version for v in store.versions(a.id)] == list(range(1, 34))
    chain = [
        (e.version_before, e.version_after) for e in reversed(store.audit(AuditQuery(calibration_id=a.id)))
    ]
    assert chain == [(None, 1)] + [(v, v + 1) for v in range(1, 33)]


def test_schema_is_versioned_and_a_newer_one_is_refused(ref, store):
    assert store.schema_version == schema.LATEST and store.schema_found == 0
    store.create("a", {}, cal(1), [], None)
    store.close()
    again = open_store(ref)
    assert again.schema_found == schema.LATEST and again.list()[0][0].name == "a"
    with again._tx() as db:
        db.execute("UPDATE schema_version SET version = ?", (schema.LATEST + 1,))
    again.close()
    with pytest.raises(
        SchemaTooNew, match=rf"schema version {schema.LATEST + 1}, newer than this eyetohand's"
    ):
        open_store(ref)


def test_a_database_of_the_first_schema_is_migrated_keeping_its_rows(ref, store):
    """A database made before schema_version existed (the tables of step 1 only) gets the audit
    trail, and keeps every calibration and version as it was."""
    dialect = store.dialect
    store.close()
    if dialect == "sqlite":
        path = StoreRef.parse(ref).path
        assert path is not None
        path.unlink()
        for suffix in ("-wal", "-shm"):
            path.with_name(path.name + suffix).unlink(missing_ok=True)
        import sqlite3

        db = sqlite3.connect(path)
        run = db.execute
    else:
        import psycopg

        conn = psycopg.connect(ref, autocommit=True)
        for t in ("signatures", "cells", "audit", "schema_version", "verifications"):
            conn.execute(f"DROP TABLE {t}")
        for t in ("versions", "calibrations"):
            conn.execute(f"DROP TABLE {t}")
        conn.execute("DROP FUNCTION eyetohand_refuse")

        def run(sql, args=()):
            return conn.execute(sql.replace("?", "%s"), args or None)

    for sql in schema.STEPS[dialect][1]:
        run(sql)
    run(
        "INSERT INTO calibrations (id, name, created_utc, updated_utc, current_version) "
        "VALUES (7, 'old', 't', 't', 1)"
    )
    run(
        "INSERT INTO versions (calibration_id, version, created_utc, note, request_json, calibration_json, "
        "pairs_json) VALUES (7, 1, 't', 'n', '{}', '{\"k\": 1}', '[]')"
    )
    if dialect == "sqlite":
        db.commit()
        db.close()
    else:
        conn.close()
    s = open_store(ref)
    try:
        assert (s.schema_found, s.schema_version) == (1, schema.LATEST)
        assert s.version(7).calibration == {"k": 1} and s.audit() == []
        assert s.add_version(7, {}, cal(2), [], None, "after").current_version == 2
        assert trail(s) == [("local", "new_version", "old", 1, 2)]
    finally:
        s.close()


def test_copy_round_trip_sqlite_postgresql_sqlite(tmp_path, pg_url):
    src = open_store(f"sqlite:{tmp_path / 'a.db'}", create=True)
    with acting_as("carol"):
        a = src.create("cell 1", {"source": "fit"}, cal(1), pairs(3), pairs(1))
        src.create("cell 2", {"source": "import"}, cal(2), [], None)
        src.add_version(a.id, {}, cal(3), pairs(4), None, "refit ünïcode ✓")
        src.add_verification(a.id, 2, {"passed": False, "n": 4, "rms_mm": 1.5, "cause": "drift"})
        src.delete(src.find("cell 2").id)
        src.create("cell 3", {}, cal(4), [], None)  # a new id after a deleted one
    digest = store_digest(src)
    pg = open_store(pg_url)
    result = copy_store(src, pg)
    assert (result.calibrations, result.versions, result.verifications, result.audit) == (2, 3, 1, 6)
    assert result.digest == digest == store_digest(pg)
    back = open_store(f"sqlite:{tmp_path / 'b.db'}", create=True)
    assert copy_store(pg, back).digest == digest == store_digest(back)
    # the copies go on as the original would: same ids, next id after the copied ones, the same etags
    for s in (src, pg, back):
        assert [(r.id, r.name, r.etag) for r, _ in s.list()] == [
            (r.id, r.name, r.etag) for r, _ in src.list()
        ]
        assert s.verifications(a.id)[0]["cause"] == "drift"
    assert pg.create("cell 4", {}, cal(5), [], None).id == back.create("cell 4", {}, cal(5), [], None).id == 4
    with pytest.raises(StoreRefError, match="not empty"):
        copy_store(src, pg)
    for s in (src, pg, back):
        s.close()


def test_an_unreachable_server_is_a_storage_error_and_the_store_reconnects(pg_cluster, pg_url):
    s = open_store(pg_url, 1.0)
    a = s.create("a", {}, cal(1), [], None)
    pg_cluster.stop()
    try:
        with pytest.raises(StorageError, match="unreachable") as info:
            s.add_version(a.id, {}, cal(2), [], None, "while down")
        assert info.value.status == 503
        with pytest.raises(StorageError, match="unreachable"):
            s.get(a.id)
    finally:
        pg_cluster.start()
    assert s.add_version(a.id, {}, cal(3), [], None, "back").current_version == 2
    assert [e.note for e in s.audit()] == ["back", "created"]
    s.close()
    from pg import free_port

    with pytest.raises(StorageError, match=r"postgresql://u:\*\*\*@127.0.0.1:\d+/x is unreachable"):
        open_store(f"postgresql://u:secret@127.0.0.1:{free_port()}/x")


def test_store_references():
    assert StoreRef.parse("postgresql://u@h:5432/db").url == "postgresql://u@h:5432/db"
    assert StoreRef.parse("sqlite:/x/cells.db").path is not None
    assert str(StoreRef.parse("/data")) == "sqlite:/data/calibrations.db"
    assert str(StoreRef.parse("postgresql://u:secret@h:5432/db")) == "postgresql://u:***@h:5432/db"
    with pytest.raises(StoreRefError, match="unknown kind of store 'mysql'"):
        StoreRef.parse("mysql://u@h/db")
    with pytest.raises(StoreRefError, match="sqlite: needs a path"):
        StoreRef.parse("sqlite:")


def test_a_notification_wakes_the_follower_at_once(pg_url):
    """On PostgreSQL the follower LISTENs: with a poll every 30 s, another connection's write still
    reaches it within a second (the payload is only a wake-up: the change is read from the trail)."""
    import time

    from eyetohand.server.follow import Follower

    s, writer = open_store(pg_url), open_store(pg_url)
    a = writer.create("a", {}, cal(1), [], None)
    seen: list[int] = []
    f = Follower(s, seen.append, poll_s=30.0)
    f.start()
    try:
        time.sleep(1.0)  # the first poll (the last entry seen) and the LISTEN are in place
        t0 = time.monotonic()
        writer.add_version(a.id, {}, cal(2), [], None, "elsewhere")
        while not seen and time.monotonic() - t0 < 5:
            time.sleep(0.01)
        assert seen == [a.id] and time.monotonic() - t0 < 1.0
        assert f.state.reachable and f.last == max(e.id for e in s.audit())
    finally:
        f.stop()
        s.close()
        writer.close()


def test_a_notification_wakes_the_line_service_at_once(pg_url, paper_pairs):
    """The TCP line service polls every 30 s here, but the follower's notification wakes it
    (``LineServer.wake``, as ``serve`` wires it): another connection's new version is answered to a
    robot's ``VERSION`` within a second."""
    import asyncio
    import socket
    import time

    from eyetohand import calibrate
    from eyetohand.core import PointPairs
    from eyetohand.positioning import LineServer, LoopThread
    from eyetohand.server.follow import Follower
    from eyetohand.server.stored import StoredCalibration

    pairs, _ = paper_pairs
    shifted = PointPairs(pairs.uv_px, pairs.xyz_mm + [5.0, 0.0, 0.0], pairs.ids)
    cals = [calibrate(p, model="homography", optimizer="lm", loo=False).to_dict() for p in (pairs, shifted)]
    s, writer, follow_store = open_store(pg_url), open_store(pg_url), open_store(pg_url)
    a = writer.create("a", {}, cals[0], [], None)
    loop = LoopThread("test-tcp")
    server = LineServer(StoredCalibration(s, a.id), "127.0.0.1", 0, poll_s=30.0)
    f = Follower(follow_store, lambda _cal_id: server.wake(), poll_s=30.0)

    def version() -> str:
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
            sock.sendall(b"VERSION\n")
            return sock.makefile().readline().strip()

    try:
        asyncio.run(_call_on(loop, server.start()))
        f.start()
        time.sleep(1.0)  # the follower's first poll and its LISTEN are in place
        assert version().startswith("OK a,1,")
        t0 = time.monotonic()
        writer.add_version(a.id, {}, cals[1], [], None, "elsewhere")
        while not version().startswith("OK a,2,") and time.monotonic() - t0 < 5:
            time.sleep(0.02)
        took_s = time.monotonic() - t0
        print(f"line service answered the new version {took_s:.3f} s after the write")
        assert version().startswith("OK a,2,") and took_s < 1.0, took_s
    finally:
        f.stop()
        loop.loop.call_soon_threadsafe(server.close)
        loop.stop()
        for st in (s, writer, follow_store):
            st.close()


async def _call_on(loop, coro):
    return await loop.call(coro)


def test_an_id_beyond_int64_is_not_found(store):
    store.create("a", {}, cal(1), [], None)
    for ref in ("id:" + "9" * 30, "9" * 30):
        with pytest.raises(NotFound, match="no calibration (with id|named)"):
            store.find(ref)
