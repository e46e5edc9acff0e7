"""The shared store through every interface: the HTTP API with named tokens (who changed what, in
GET /api/audit), the command line (eyetohand audit, eyetohand store copy), and a real `serve --store
postgresql://…` process whose robot lines follow a version written by another process."""

from __future__ import annotations

import json
import socket
import time

import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, ServeProcess, records

from eyetohand.cli import main
from eyetohand.server import create_app, open_store, store_digest
from eyetohand.server.audit import acting_as

TOKENS = {"alice": "alice-token-1", "bob": "bob-token-22"}


def auth(user: str) -> dict:
    return {"Authorization": f"Bearer {TOKENS[user]}"}


@pytest.fixture(scope="module")
def cal_files(paper_pairs):
    """Two calibration files of the paper's cell (the second one's pairs shifted 5 mm in x)."""
    from eyetohand import calibrate
    from eyetohand.core import PointPairs

    pairs, _ = paper_pairs
    shifted = PointPairs(pairs.uv_px, pairs.xyz_mm + [5.0, 0.0, 0.0], pairs.ids)
    return [calibrate(p, model="homography", optimizer="lm", loo=False) for p in (pairs, shifted)]


def test_http_changes_are_audited_under_the_tokens_names(store_url, cal_files):
    app = create_app(store_url, token=TOKENS)
    with TestClient(app) as c:
        r = c.post(
            "/api/calibrations/import",
            json={"name": "cell 1", "calibration": cal_files[0].to_dict()},
            headers=auth("alice"),
        )
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        body = {"name": "cell 1", "calibration": cal_files[1].to_dict(), "note": "moved the camera"}
        assert c.post("/api/calibrations/import", json=body, headers=auth("bob")).status_code == 200
        r = c.post(f"/api/calibrations/{cid}/rollback", json={"version": 1}, headers=auth("alice"))
        assert r.status_code == 200 and r.json()["version"] == 3
        check = {"pairs": records(PAPER / "calibration_points.csv")[::2], "tolerance_mm": 1.0}
        assert c.post(f"/api/calibrations/{cid}/verify", json=check, headers=auth("bob")).status_code == 200
        r = c.patch(f"/api/calibrations/{cid}", json={"name": "cell 1 left"}, headers=auth("bob"))
        assert r.status_code == 200

        assert c.get("/api/audit").status_code == 401
        got = c.get("/api/audit", headers=auth("alice")).json()
        rows = [(e["user"], e["action"], e["version_before"], e["version_after"]) for e in got["entries"]]
        assert rows == [
            ("bob", "rename", 3, 3),
            ("bob", "check", 3, 3),
            ("alice", "rollback", 2, 3),
            ("bob", "import", 1, 2),
            ("alice", "import", None, 1),
        ]
        assert got["next_before"] is None
        assert got["entries"][3]["note"] == "moved the camera"
        assert got["entries"][1]["note"].startswith("passed on ")

        by_bob = c.get("/api/audit", params={"user": "bob"}, headers=auth("bob")).json()["entries"]
        assert {e["user"] for e in by_bob} == {"bob"} and len(by_bob) == 3
        # by its name now, or its id; paged newest first
        for ref in ("cell 1 left", str(cid), f"id:{cid}"):
            page = c.get("/api/audit", params={"calibration": ref, "limit": 2}, headers=auth("bob")).json()
            assert [e["action"] for e in page["entries"]] == ["rename", "check"]
            nxt = page["next_before"]
            rest = c.get("/api/audit", params={"calibration": ref, "before": nxt}, headers=auth("bob")).json()
            assert [e["action"] for e in rest["entries"]] == ["rollback", "import", "import"]
        r = c.get("/api/audit", params={"since": "yesterday"}, headers=auth("bob"))
        assert r.status_code == 422 and r.json()["field"] == "since"
        assert "ISO 8601" in r.json()["error"]
        r = c.get("/api/audit", params={"limit": 0}, headers=auth("bob"))
        assert r.status_code == 422
        r = c.get("/api/audit", params={"calibration": "id:" + "9" * 30}, headers=auth("bob"))
        assert r.status_code == 422 and r.json()["field"] == "calibration"
        future = c.get("/api/audit", params={"since": "2999-01-01"}, headers=auth("bob")).json()
        assert future == {"entries": [], "next_before": None}
    app.state.store.close()


def test_cli_audit_and_store_copy_both_ways(tmp_path, pg_url, capsys):
    src_url = f"sqlite:{tmp_path / 'cell.db'}"
    s = open_store(src_url, create=True)
    with acting_as("dana"):
        a = s.create("press 4", {"source": "fit"}, {"k": 1}, [], None, note="first fit")
        s.add_version(a.id, {"source": "fit"}, {"k": 2}, [], None, "refit after crash")
    digest = store_digest(s)
    s.close()

    assert main(["audit", "--store", src_url, "--json"]) == 0
    entries = json.loads(capsys.readouterr().out)["entries"]
    assert [(e["user"], e["action"], e["note"]) for e in entries] == [
        ("dana", "new_version", "refit after crash"),
        ("dana", "create", "first fit"),
    ]
    assert main(["audit", "--data", str(tmp_path / "nothing-here")]) == 2
    assert "no " in capsys.readouterr().err
    assert main(["audit", "--store", src_url, "--since", "last tuesday"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --since: expected an ISO 8601 time"), err

    assert main(["store", "copy", src_url, pg_url]) == 0
    assert "copied 1 calibrations, 2 versions, 0 verifications and 2 audit entries" in capsys.readouterr().out
    back_url = f"sqlite:{tmp_path / 'back.db'}"
    assert main(["store", "copy", pg_url, back_url, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["calibrations"], out["versions"], out["audit"], out["digest"]) == (1, 2, 2, digest)
    for url in (pg_url, back_url):
        t = open_store(url)
        assert store_digest(t) == digest
        t.close()
    assert main(["audit", "--store", pg_url, "--calibration", "press 4", "--user", "dana"]) == 0
    table = capsys.readouterr().out
    assert "refit after crash" in table and "1>2" in table
    # a second copy into a store that is no longer empty is refused, and changes nothing
    assert main(["store", "copy", src_url, pg_url]) == 2
    assert "not empty" in capsys.readouterr().err


def _ask(port: int, line: str) -> str:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(line.encode() + b"\n")
        return s.makefile().readline().strip()


@pytest.mark.long
def test_serve_on_postgresql_follows_a_version_written_elsewhere(tmp_path, pg_url, cal_files):
    """`serve --store postgresql://…` maps robot lines with the stored calibration; a new version
    written by another process (here: this test's own connection) is answered within 2 s."""
    store = open_store(pg_url)
    cal0, cal1 = cal_files
    rec = store.create("cell", {"source": "import"}, cal0.to_dict(), [], None)
    tf = tmp_path / "tokens"
    tf.write_text("# the cell's users\noffice:office-token-1\nrobot:robot-token-22\n")
    srv = ServeProcess(tmp_path / "data", "--store", pg_url, "--calibration", "cell", "--token-file", str(tf))
    try:
        first = _ask(srv.tcp_port, "AUTH office-token-1")
        assert first == "OK", first
        with socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=5) as s:
            f = s.makefile("rw")
            f.write("AUTH office-token-1\n554.166,1283.44\n")
            f.flush()
            assert f.readline().strip() == "OK"
            before = f.readline().strip()
            with acting_as("office"):
                store.add_version(rec.id, {"source": "import"}, cal1.to_dict(), [], None, "office write")
            t0 = time.monotonic()
            while True:
                f.write("554.166,1283.44\n")
                f.flush()
                now = f.readline().strip()
                if now != before:
                    break
                assert time.monotonic() - t0 < 2.0, f"still {now!r} 2 s after the write"
                time.sleep(0.02)
        x0, x1 = (float(reply.split()[-1].split(",")[0]) for reply in (before, now))  # [OK ]x,y,z
        assert x1 - x0 == pytest.approx(5.0, abs=0.05)
        import httpx

        h = {"Authorization": "Bearer robot-token-22"}
        entries = httpx.get(srv.url + "/api/audit", headers=h).json()["entries"]
        assert [(e["user"], e["action"]) for e in entries] == [("office", "import"), ("local", "import")]

        def following() -> list:  # the plant view: this serve beats with the version it answers with
            (row,) = httpx.get(srv.url + "/api/plant", headers=h).json()["calibrations"]
            return [(c["version"], c["alive"]) for c in row["cells"]]

        assert _until(lambda: following() == [(2, True)], 7.0), following()
    finally:
        srv.stop()
        store.close()


def _map(c: TestClient, cid: int) -> tuple[int, float | None]:
    r = c.post(f"/api/calibrations/{cid}/image-to-robot", json={"points": [[554.166, 1283.44]]})
    body = r.json()
    return r.status_code, (body["points"][0][0] if r.status_code == 200 else None)


def _until(what, timeout_s: float, step_s: float = 0.05):
    """``what()``'s first truthy answer within ``timeout_s`` (else the last answer, falsy)."""
    t0 = time.monotonic()
    while True:
        got = what()
        if got or time.monotonic() - t0 > timeout_s:
            return got
        time.sleep(step_s)


def test_two_servers_on_one_store_follow_each_others_changes(store_url, cal_files):
    """Server B answers with the version server A wrote within 2 s (its cache follows the trail)."""
    a_app, b_app = create_app(store_url), create_app(store_url)
    with TestClient(a_app) as a, TestClient(b_app) as b:
        cid = a.post(
            "/api/calibrations/import", json={"name": "cell", "calibration": cal_files[0].to_dict()}
        ).json()["id"]
        status, x0 = _map(b, cid)
        assert status == 200
        assert (
            a.post(
                "/api/calibrations/import", json={"name": "cell", "calibration": cal_files[1].to_dict()}
            ).status_code
            == 200
        )
        t0 = time.monotonic()
        assert _until(lambda: _map(b, cid)[1] != x0, 2.0), "B still maps with version 1 after 2 s"
        assert time.monotonic() - t0 < 2.0
        assert _map(b, cid)[1] - x0 == pytest.approx(5.0, abs=0.05)
        assert b.get("/api/health").json()["store"]["reachable"] is True


def test_an_unreachable_database_keeps_the_version_in_force_and_refuses_changes(
    pg_cluster, pg_url, cal_files
):
    app = create_app(pg_url, db_wait_s=1.0)
    with TestClient(app) as c:
        cid = c.post(
            "/api/calibrations/import", json={"name": "cell", "calibration": cal_files[0].to_dict()}
        ).json()["id"]
        status, x0 = _map(c, cid)
        pg_cluster.stop()
        try:
            health = _until(lambda: c.get("/api/health").json()["status"] == "degraded", 3.0)
            assert health, c.get("/api/health").json()
            h = c.get("/api/health").json()["store"]
            assert h["reachable"] is False and "unreachable" in h["reason"] and h["since_utc"]
            assert _map(c, cid) == (200, x0)  # the robot is still answered, with the version in force
            r = c.post(
                "/api/calibrations/import", json={"name": "cell", "calibration": cal_files[1].to_dict()}
            )
            assert (
                r.status_code == 503
                and "unreachable" in r.json()["error"]
                and "nothing was changed" in r.json()["error"]
            )
        finally:
            pg_cluster.start()
        assert _until(lambda: c.get("/api/health").json()["status"] == "ok", 5.0)
        r = c.post("/api/calibrations/import", json={"name": "cell", "calibration": cal_files[1].to_dict()})
        assert r.status_code == 200 and r.json()["version"] == 2
        assert _until(lambda: _map(c, cid)[1] != x0, 2.0)
        entries = c.get("/api/audit").json()["entries"]
        assert [(e["action"], e["version_after"]) for e in entries] == [("import", 2), ("import", 1)]


@pytest.mark.parametrize("mode", ["fast", "immediate"])
def test_a_change_right_after_the_database_comes_back_is_stored(pg_cluster, pg_url, cal_files, mode):
    """The pool's idle connections died with the server: the first change after it came back took one
    of them and was refused (503) while /api/health, on a fresh connection, said ok (a run of this file
    failed so once, under load). A connection the server wrote its last words to is dropped when borrowed."""
    app = create_app(pg_url, db_wait_s=1.0)
    with TestClient(app) as c:
        body = {"name": "cell", "calibration": cal_files[0].to_dict()}
        assert c.post("/api/calibrations/import", json=body).status_code == 201
        store = app.state.store
        with store._borrow(), store._borrow():  # two connections, both left idle in the pool
            pass
        pg_cluster.stop(mode)
        pg_cluster.start()
        body = {"name": "cell", "calibration": cal_files[1].to_dict()}
        r = c.post("/api/calibrations/import", json=body)
        assert r.status_code == 200 and r.json()["version"] == 2, r.text


def test_plant_view_lists_calibrations_checks_and_following_cells(store_url, cal_files):
    from eyetohand.server.plant import CellBeat, beat

    app = create_app(store_url)
    with TestClient(app) as c:
        cid = c.post(
            "/api/calibrations/import", json={"name": "press 4", "calibration": cal_files[0].to_dict()}
        ).json()["id"]
        c.post("/api/calibrations/import", json={"name": "press 4", "calibration": cal_files[1].to_dict()})
        check = {"pairs": records(PAPER / "calibration_points.csv")[::2], "tolerance_mm": 1.0}
        assert c.post(f"/api/calibrations/{cid}/verify?version=1", json=check).status_code == 200
        store = app.state.store
        beat(
            store,
            CellBeat.of_this_process("http://10.0.0.7:8765", cid, "press 4", 1, "2026-12-04T05:00:00+00:00"),
        )
        beat(
            store, CellBeat("old-pc http://10.0.0.9:8765", 1, "http://10.0.0.9:8765", cid, "press 4", 2, "t")
        )
        beat(
            store,
            CellBeat("pc3 http://10.0.0.8:8765", 2, "http://10.0.0.8:8765", None, "/srv/cal.json", None, "t"),
        )
        with store._tx() as db:  # the old PC last beat a minute ago
            db.execute(
                "UPDATE cells SET seen_utc = ? WHERE cell = ?",
                ("2026-01-01T00:00:00.000+00:00", "old-pc http://10.0.0.9:8765"),
            )
        view = c.get("/api/plant").json()
        (row,) = view["calibrations"]
        assert (row["name"], row["current_version"]) == ("press 4", 2)
        assert row["last_check"]["version"] == 1 and row["last_check"]["passed"] is True
        assert [(x["url"], x["version"], x["alive"]) for x in row["cells"]] == [
            ("http://10.0.0.9:8765", 2, False),
            ("http://10.0.0.7:8765", 1, True),
        ]
        assert [(x["calibration"], x["alive"]) for x in view["other_cells"]] == [("/srv/cal.json", True)]
        # activation from the office: rollback with the ETag the view showed; a stale one is refused
        r = c.post(
            f"/api/calibrations/{cid}/rollback", json={"version": 1}, headers={"If-Match": row["etag"]}
        )
        assert r.status_code == 200 and r.json()["version"] == 3
        r = c.post(
            f"/api/calibrations/{cid}/rollback", json={"version": 2}, headers={"If-Match": row["etag"]}
        )
        assert r.status_code == 412
        assert c.get("/api/plant").json()["calibrations"][0]["current_version"] == 3
        page = c.get("/plant")
        assert page.status_code == 200 and "/static/plant.js" in page.text
        assert c.get("/static/plant.js").status_code == 200


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("s3cret-token-1\n", {"default": "s3cret-token-1"}),
        (
            "# users\noffice: office-token-1\n\nrobot:tok:en:with:colons\n",
            {"office": "office-token-1", "robot": "tok:en:with:colons"},
        ),
        ("office:abc\n", "line 1: the token of 'office' is shorter than 8 characters"),
        ("a:aaaaaaaa1\na:bbbbbbbb2\n", "line 2: the name 'a' is given twice"),
        ("a:aaaaaaaa1\nb:aaaaaaaa1\n", "line 2: this token is given to another name too"),
        ("one token\ntwo:tokens-here\n", "line 1: expected 'name:token'"),
        ("\n# nothing\n", "expected one line holding the token, or lines 'name:token'"),
    ],
)
def test_token_file_names_its_tokens(tmp_path, text, expected):
    from eyetohand.cli.common import CliError
    from eyetohand.cli.serve import read_token_file

    f = tmp_path / "tokens"
    f.write_text(text)
    if isinstance(expected, dict):
        assert read_token_file(str(f), given=False) == expected
    else:
        with pytest.raises(CliError, match=expected):
            read_token_file(str(f), given=False)
