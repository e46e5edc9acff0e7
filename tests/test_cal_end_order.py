"""CAL END's store and journal order (issue 40): the intent is journaled before the version is stored,
the end after. A crash between the store and the end's record, then END resent (after a restart), stores
nothing twice; a journal write that fails after the store answers OK (the version is in force), and a
restart settles it; a journal write that fails before the store says "nothing recorded" and stores
nothing. The faults are injected through the Collector's ``journal`` parameter (a journal that fails on
one kind of record) and its ``save_fn``: no private internals patched."""

import errno
import json

import numpy as np
import pytest
from helpers import view_square_mm

from eyetohand.cell.collect import Collector
from eyetohand.cell.journal import JsonlJournal
from eyetohand.sim.camera_sim import CellCamera
from eyetohand.sim.cell import load_cell
from eyetohand.sim.plate import simulate_plate
from eyetohand.vision.sources import open_source

SPEC = "chessboard:9x6:15"


class Crash(BaseException):
    """The process dies here (not an Exception: nothing in the Collector answers it)."""


class FaultyJournal:
    """A real JSONL journal whose write of a record with ``op`` fails once with ``exc``."""

    def __init__(self, path, op: str, exc: BaseException):
        self.inner, self.op, self.exc = JsonlJournal(path), op, exc
        self.path = path

    def records(self):
        return self.inner.records()

    def append(self, rec):
        if rec["op"] == self.op and self.exc is not None:
            exc, self.exc = self.exc, None
            raise exc
        self.inner.append(rec)

    def close(self):
        self.inner.close()


class Versions:
    """The store: every version saved (save_fn), the current one (load_fn)."""

    def __init__(self):
        self.saved: list = []

    def save(self, name, cal):
        self.saved.append((name, cal))

    def load(self, name):
        mine = [c for n, c in self.saved if n == name]
        return mine[-1] if mine else None


@pytest.fixture(scope="module")
def touches(cell_file):
    sim = simulate_plate(load_cell(cell_file), SPEC, seed=1, render=False)
    world = sim.placement.to_robot(sim.spec.points_mm())
    rng = np.random.default_rng(0)
    return [
        f"CAL TOUCH {k}," + ",".join(f"{v:.4f}" for v in world[i] + rng.normal(0, 0.05, 3))
        for k, i in (("A", 0), ("B", 8), ("C", 53), ("D", 45))
    ]


def plate_session(col, touches):
    ok = "(1," if col.reply_format == "ur" else "OK "
    assert col.handle(f"CAL PLATE {SPEC}").startswith(ok)
    for t in touches:
        assert col.handle(t).startswith(ok)


def collector(store, cell_file, versions, journal=None, reply_format="plain", save_fn=None):
    source = open_source(f"sim:{cell_file}?seed=5")
    source.show_plate(SPEC, 1)
    return Collector(
        store,
        source,
        calibration="cell1",
        save_fn=save_fn or versions.save,
        load_fn=versions.load,
        journal=journal,
        reply_format=reply_format,
    )


def ops(store):
    return [json.loads(x)["op"] for x in (store / "collect.jsonl").read_text().splitlines()]


def test_crash_between_store_and_journal_then_end_resent_stores_once(tmp_path, cell_file, touches):
    store, versions = tmp_path / "s", Versions()
    col = collector(store, cell_file, versions, FaultyJournal(store / "collect.jsonl", "end", Crash()))
    plate_session(col, touches)
    with pytest.raises(Crash):
        col.handle("CAL END")  # stored, then killed before the end's record
    col.close()
    assert len(versions.saved) == 1 and ops(store)[-1] == "ending"
    with collector(store, cell_file, versions) as again:  # restarted on the same journal
        assert again.handle("CAL STATUS") == "OK cell1,4,collecting"
        reply = again.handle("CAL END")  # the robot never had its reply: it sends END again
        assert reply.startswith("OK homography-radial,4,"), reply
        assert len(versions.saved) == 1  # settled against the store: nothing stored twice
        assert ops(store)[-2:] == ["ending", "end"] and again.handle("CAL STATUS") == "OK cell1,4,calibrated"
        assert again.handle("CAL END") == "ERR no collection open; send CAL BEGIN <name> first"


def test_crash_between_intent_and_store_then_end_resent_stores(tmp_path, cell_file, touches):
    store, versions = tmp_path / "s", Versions()

    def dies(name, cal):
        raise Crash()

    col = collector(store, cell_file, versions, save_fn=dies)
    plate_session(col, touches)
    with pytest.raises(Crash):
        col.handle("CAL END")  # the intent journaled, killed before the store
    col.close()
    assert versions.saved == [] and ops(store)[-1] == "ending"
    with collector(store, cell_file, versions) as again:
        assert again.handle("CAL END").startswith("OK homography-radial,4,")
        assert len(versions.saved) == 1 and ops(store)[-2:] == ["ending", "end"]


def test_failed_journal_write_after_the_store_answers_ok(tmp_path, cell_file, touches):
    store, versions = tmp_path / "s", Versions()
    full = OSError(errno.ENOSPC, "No space left on device")
    faulty = FaultyJournal(store / "collect.jsonl", "end", full)
    with collector(store, cell_file, versions, faulty, "ur") as col:
        plate_session(col, touches)
        reply = col.handle("CAL END")
        assert reply.startswith("(1,4,"), reply  # the version is in force: OK, not "nothing recorded"
        assert len(versions.saved) == 1 and col.handle("CAL STATUS") == "(1,4,2,0)"  # calibrated
    assert ops(store)[-1] == "ending"  # the journal kept the intent
    with collector(store, cell_file, versions, reply_format="ur") as again:  # restart: END settles it
        assert again.handle("CAL END") == reply
        assert len(versions.saved) == 1 and ops(store)[-1] == "end"


def test_failed_journal_write_before_the_store_stores_nothing(tmp_path, cell_file, touches):
    store, versions = tmp_path / "s", Versions()
    full = OSError(errno.ENOSPC, "No space left on device")
    with collector(store, cell_file, versions, FaultyJournal(store / "collect.jsonl", "ending", full)) as col:
        plate_session(col, touches)
        assert col.handle("CAL END") == "ERR journal write failed (No space left on device); nothing recorded"
        assert versions.saved == [] and col.handle("CAL STATUS") == "OK cell1,4,collecting"
        assert col.handle("CAL END").startswith("OK homography-radial,4,")
        assert len(versions.saved) == 1


def test_a_collection_killed_after_its_store_is_not_stored_twice(tmp_path, cell_file):
    """The same order for a collection (CAL BEGIN … POINT … END), with the default file store."""
    cx, cy, half = view_square_mm(CellCamera(load_cell(cell_file)).camera, 150.0, margin_px=40)
    store = tmp_path / "s"
    source = open_source(f"sim:{cell_file}?seed=5")
    col = Collector(store, source, journal=FaultyJournal(store / "collect.jsonl", "end", Crash()))
    rect = f"{cx - half:.3f},{cy - half:.3f},{cx + half:.3f},{cy + half:.3f}"
    assert col.handle(f"CAL BEGIN c1,grid:3x3,{rect},150") == "OK"
    while (r := col.handle("CAL NEXT")) != "OK DONE":
        assert col.handle("CAL POINT " + r.removeprefix("OK ")).startswith("OK ")
    with pytest.raises(Crash):
        col.handle("CAL END")
    col.close()
    first = (store / "c1.json").stat().st_mtime_ns
    with Collector(store, source) as again:
        assert again.handle("CAL END").startswith("OK ")
        assert (store / "c1.json").stat().st_mtime_ns == first  # not written again
        assert ops(store)[-2:] == ["ending", "end"]


def test_the_servers_store_settles_a_pending_end(tmp_path, cell_file, touches):
    """With the server's own save/load (a version in its database, read back and proven), the intent's
    data hash finds the version a killed END stored: one version, not two."""
    from eyetohand.server.startup import store_load_fn, store_save_fn
    from eyetohand.server.storage import Store

    db = Store(tmp_path / "data", create=True)
    try:
        store = tmp_path / "s"
        source = open_source(f"sim:{cell_file}?seed=5")
        source.show_plate(SPEC, 1)
        kw = {"calibration": "cell1", "save_fn": store_save_fn(db), "load_fn": store_load_fn(db)}
        col = Collector(store, source, journal=FaultyJournal(store / "collect.jsonl", "end", Crash()), **kw)
        plate_session(col, touches)
        with pytest.raises(Crash):
            col.handle("CAL END")
        col.close()
        with Collector(store, source, **kw) as again:
            assert again.handle("CAL END").startswith("OK homography-radial,4,")
        assert [v.version for v in db.versions(db.find("cell1").id)] == [1]
    finally:
        db.close()


def test_points_added_after_a_killed_end_are_fitted_not_settled(tmp_path, cell_file, touches):
    """A pending END settles only the points it was about: a touch added after the crash makes the next
    END fit and store a new version with it."""
    store, versions = tmp_path / "s", Versions()
    col = collector(store, cell_file, versions, FaultyJournal(store / "collect.jsonl", "end", Crash()))
    plate_session(col, touches[:3])
    with pytest.raises(Crash):
        col.handle("CAL END")
    col.close()
    with collector(store, cell_file, versions) as again:
        assert again.handle(touches[3]).startswith("OK 4,")
        assert again.handle("CAL END").startswith("OK homography-radial,4,")
    assert len(versions.saved) == 2 and len(versions.saved[1][1].plate.touches) == 4
