"""The store's own If-Match check (``storage.require_match``, under every write) refuses a weak ETag with
the HTTP header's words, on both backends: ``W/"<the current tag>"`` was stripped to the strong tag and
passed (RFC 9110, 13.1.1: If-Match compares strongly). Nothing is changed or audited."""

from __future__ import annotations

import pytest
from fastapi import HTTPException

from eyetohand.server import open_store
from eyetohand.server.errors import ApiError
from eyetohand.server.routes import if_match_header
from eyetohand.server.storage import Conflict, WeakTag


@pytest.fixture
def store(store_url, paper_pairs):
    from eyetohand import calibrate

    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False).to_dict()
    s = open_store(store_url, create=True)
    s.create("cell", {"source": "import"}, cal, [], None)
    try:
        yield s
    finally:
        s.close()


def _state(s) -> tuple:
    rec = s.get(1)
    return rec.etag, rec.current_version, rec.name, len(s.audit())


def test_a_weak_etag_is_refused_by_the_store_with_the_http_words(store):
    tag = store.get(1).etag
    before = _state(store)
    writes = {
        "rename": lambda m: store.rename(1, "renamed", if_match=m),
        "rollback": lambda m: store.rollback(1, 1, if_match=m),
        "delete": lambda m: store.delete(1, if_match=m),
    }
    for if_match in (f"W/{tag}", f'"x", W/{tag}', f" W/{tag} "):
        try:
            if_match_header(if_match)
        except (ApiError, HTTPException) as exc:
            http_words = exc.message if isinstance(exc, ApiError) else str(exc.detail)
        else:
            raise AssertionError(f"the HTTP header took {if_match!r}")
        for what, write in writes.items():
            with pytest.raises(WeakTag) as got:
                write(if_match)
            assert str(got.value) == http_words, what
            assert "weak ETag" in str(got.value) and "W/" in str(got.value)
    assert _state(store) == before  # nothing changed, nothing audited
    # the strong tag still passes, a stale one is still a Conflict
    with pytest.raises(Conflict):
        store.rename(1, "renamed", if_match='"stale"')
    assert store.rename(1, "renamed", if_match=tag).name == "renamed"
