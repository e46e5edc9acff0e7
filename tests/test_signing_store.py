"""Signatures in the store, on both backends (SQLite and a real PostgreSQL: tests/pg.py): a signer's
act audited in its transaction, once per version; a rollback carries the copied version's signature;
rows cannot be changed; a delete removes them; ``store copy`` moves them."""

from __future__ import annotations

import pytest

from eyetohand.core import Actor, Role, acting_as
from eyetohand.server.storage import AlreadySigned, NotFound
from eyetohand.server.stores import copy_store, open_store, store_digest


def cal(n: int) -> dict:
    return {
        "model": {"name": "homography"},
        "fit": {"optimizer": "lm", "fitness": 0.1},
        "train": {"rms_mm": n},
    }


def test_signatures_in_the_store(store_url, tmp_path):
    s = open_store(store_url, 10.0, create=True)
    try:
        with acting_as("otto"):
            rec = s.create("cell", {"source": "fit"}, cal(1), [], None)
            s.add_version(rec.id, {"source": "fit"}, cal(2), [], None, note="refit")
        assert s.signature(rec.id, 1) is None and s.signatures(rec.id) == {}
        with acting_as(Actor("sam", Role.SIGNER)):
            sig = s.sign(rec.id, 1, "kid", "mac1")
            with pytest.raises(AlreadySigned, match="version 1 is signed already"):
                s.sign(rec.id, 1, "kid", "mac-other")
            with pytest.raises(NotFound, match="has no version 9"):
                s.sign(rec.id, 9, "kid", "mac")
        assert (sig.signer, sig.origin, sig.key_id, sig.mac) == ("sam", "sign", "kid", "mac1")
        assert s.signature(rec.id, 1) == sig and s.signature(rec.id, 2) is None
        trail = [(e.user, e.action, e.version_after) for e in s.audit()]
        assert trail[0] == ("sam", "sign", 1) and len(trail) == 3  # the refused attempts left nothing
        with acting_as("otto"):
            back = s.rollback(rec.id, 1)
        carried = s.signature(rec.id, back.current_version)
        assert carried is not None and (carried.origin, carried.mac, carried.signer) == (
            "rollback",
            "mac1",
            "otto",
        )
        with pytest.raises(Exception, match="signatures are immutable"):
            with s._tx() as db:
                db.execute("UPDATE signatures SET mac = ? WHERE version = ?", ("forged", 1))
        assert s.signature(rec.id, 1).mac == "mac1"
        other = open_store(f"sqlite:{tmp_path / 'copy.db'}", 10.0, create=True)
        try:
            copy_store(s, other)
            assert other.signatures(rec.id) == s.signatures(rec.id) and store_digest(other) == store_digest(s)
        finally:
            other.close()
        s.delete(rec.id)
        assert s._read("SELECT COUNT(*) FROM signatures")[0][0] == 0
    finally:
        s.close()
