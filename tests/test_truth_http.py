"""One truth while serving (issue 27, HTTP side): every test runs `eyetohand serve` as a child process
and talks to it over real sockets. A refused import changes nothing; a relabelled, re-sealed or unsigned
file is refused with the same words by the library, the CLI and HTTP; every reply names the version its
own request created, and a stale If-Match gets 412; a database deleted or replaced under the server
answers 503 and is never recreated empty; the bound address is an allowed Host; half-sent requests are
closed; cross-site POSTs, look-alike names and duplicate JSON keys are refused; the token can come from
a file."""

from __future__ import annotations

import concurrent.futures as cf
import copy
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, ServeProcess, records, src_env

from eyetohand.calibration.file import V1_FIELDS, content_sha256
from eyetohand.server.app import create_app
from eyetohand.server.storage import DB_NAME

PAIRS = records(PAPER / "calibration_points.csv")
UV = (500.0, 700.0)


def seed(data: Path) -> dict:
    """Calibration 'cal 0' (id 1) stored in ``data``; returns its calibration file (a dict)."""
    app = create_app(data)
    with TestClient(app) as c:
        r = c.post("/api/calibrations", json={"name": "cal 0", "pairs": PAIRS, "model": "homography"})
        assert r.status_code == 201, r.text
        file = c.get("/api/calibrations/1").json()["calibration"]
    app.state.store.close()
    return file


def serve(data: Path, *extra: str) -> ServeProcess:
    return ServeProcess(data, "--calibration", "cal 0", *extra, log_level="error")


def cli(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "eyetohand.cli", *argv],
        capture_output=True,
        text=True,
        env=src_env(),
        timeout=timeout,
    )


def state(c: httpx.Client) -> list:
    """Every calibration with its whole version list (what a refused request must not change)."""
    out = []
    for row in c.get("/api/calibrations").json():
        versions = c.get(f"/api/calibrations/{row['id']}/versions").json()
        out.append((row["id"], row["name"], row["current_version"], versions["versions"]))
    return out


def relabelled(file: dict) -> dict:
    """A schema-2 file relabelled schema_version 1, its parameters x1.01, content_sha256 recomputed."""
    d = copy.deepcopy(file)
    d["schema_version"] = 1
    d["model"]["params"] = [p * 1.01 for p in d["model"]["params"]]
    d["content_sha256"] = content_sha256(d)
    return d


def write(path: Path, d: dict) -> Path:
    path.write_text(json.dumps(d, indent=2))
    return path


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("truth") / "data"
    file = seed(data)
    srv = serve(data)
    try:
        yield srv, file
    finally:
        srv.stop()


# ---------------------------------------------------------------- 2. import is atomic
def test_a_refused_import_changes_nothing(server):
    srv, file = server
    v1 = {k: copy.deepcopy(v) for k, v in file.items() if k in V1_FIELDS}
    v1["schema_version"] = 1
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        before = state(c)
        answers = [  # a new version of cal 0, and a new calibration
            c.post("/api/calibrations/import", json={"name": name, "calibration": v1})
            for name in ("cal 0", "a new name")
        ]
        assert state(c) == before  # was: a new, undecodable current version of cal 0
        for r in answers:
            assert r.status_code == 422, r.text
            assert r.json()["field"] == "calibration.schema_version"
            assert "eyetohand 0.1" in r.json()["error"] and "cannot prove" in r.json()["error"]
        assert c.get("/api/calibrations/1").status_code == 200  # the current version still decodes
        r = c.post("/api/calibrations/1/image-to-robot", json={"points": [list(UV)]})
        assert r.status_code == 200 and r.json()["version"] == before[0][2]


# ---------------------------------------------------------------- 3. downgrades, re-seals, signatures
def test_a_relabelled_resealed_file_is_refused_with_the_same_words_everywhere(server, tmp_path):
    srv, file = server
    bad = write(tmp_path / "relabelled.json", relabelled(file))
    words = "field 'schema_version' is 1, but the file has field"
    run = cli("apply", str(bad), "--uv", *map(str, UV), "--allow-outside")  # was: exit 0, 0.06 mm off
    assert run.returncode == 2 and run.stderr.startswith("error: ") and words in run.stderr, run
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        before = state(c)
        r = c.post("/api/calibrations/import", json={"name": "cal 0", "calibration": relabelled(file)})
        assert r.status_code == 422 and words in r.json()["error"], r.text
        assert r.json()["field"] == "calibration.schema_version"
        assert state(c) == before
    run = cli(
        "serve",
        "--port",
        "0",
        "--data",
        str(tmp_path / "d"),
        "--tcp",
        "127.0.0.1:0",
        "--calibration",
        str(bad),
    )
    assert run.returncode == 2 and words in run.stderr, run


def test_signed_files_catch_a_deliberate_edit_that_content_sha256_cannot(tmp_path):
    key = tmp_path / "cell.key"
    key.write_bytes(os.urandom(32))
    signed = tmp_path / "signed.json"
    run = cli(
        "calibrate",
        str(PAPER / "calibration_points.csv"),
        "--model",
        "homography",
        "-o",
        str(signed),
        "--sign-key",
        str(key),
    )
    assert run.returncode == 0, run.stderr
    doc = json.loads(signed.read_text())
    assert doc["signature"]["alg"] == "hmac-sha256"
    unsigned = write(tmp_path / "unsigned.json", {k: v for k, v in doc.items() if k != "signature"})
    edited = copy.deepcopy(doc)  # a record changed and re-sealed: content_sha256 checks again
    edited["fit"]["message"] = "edited"
    edited["content_sha256"] = content_sha256(edited)
    edited_path = write(tmp_path / "edited.json", edited)

    data = tmp_path / "data"
    seed(data)
    base = [
        "serve",
        "--port",
        "0",
        "--data",
        str(data),
        "--tcp",
        "127.0.0.1:0",
        "--sign-key",
        str(key),
        "--require-signed",
    ]
    for path, words in (
        (unsigned, "field 'signature' missing"),
        (edited_path, "field 'signature' does not match the content"),
    ):
        run = cli(*base, "--calibration", str(path))
        assert (
            run.returncode == 2 and run.stderr.startswith("error: --calibration: ") and words in run.stderr
        ), run
    run = cli(
        "serve",
        "--port",
        "0",
        "--data",
        str(data),
        "--require-signed",
        "--tcp",
        "127.0.0.1:0",
        "--calibration",
        str(signed),
    )
    assert run.returncode == 2 and "--require-signed needs --sign-key" in run.stderr, run

    srv = ServeProcess(
        data, "--calibration", str(signed), "--sign-key", str(key), "--require-signed", log_level="error"
    )
    try:
        with socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=10) as s:
            s.sendall(b"%g,%g\n" % UV)
            reply = s.makefile().readline()
            assert reply and not reply.startswith("ERR"), reply
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            before = state(c)
            r = c.post("/api/calibrations/import", json={"name": "imported", "calibration": edited})
            assert r.status_code == 422 and r.json()["field"] == "calibration.signature", r.text
            assert "field 'signature' does not match the content" in r.json()["error"]
            assert state(c) == before
            # an unsigned file is stored, unsigned, and not mapped with until a signer signs it (issue 40)
            d = json.loads(unsigned.read_text())
            r = c.post("/api/calibrations/import", json={"name": "unsigned", "calibration": d})
            assert r.status_code == 201 and r.json()["waits_for_signature"] is True, r.text
            r = c.post(f"/api/calibrations/{r.json()['id']}/image-to-robot", json={"points": [list(UV)]})
            assert r.status_code == 409 and r.json()["field"] == "signature", r.text
            r = c.post("/api/calibrations/import", json={"name": "imported", "calibration": doc})
            assert r.status_code == 201, r.text
            exported = c.get(f"/api/calibrations/{r.json()['id']}/export").json()
            assert exported["signature"] == doc["signature"]  # the file's signature, carried
    finally:
        srv.stop()
    # without a key a re-sealed edit still loads (content_sha256 is for accidents): the key is the guard
    assert cli("apply", str(edited_path), "--uv", *map(str, UV)).returncode == 0


# ---------------------------------------------------------------- 4. each reply names its own version
def test_concurrent_writes_each_name_their_own_version(server):
    srv, file = server
    n = 80

    def imp(i: int):
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            r = c.post(
                "/api/calibrations/import", json={"name": "cal 0", "calibration": file, "note": f"req {i}"}
            )
            return i, r.status_code, r.json()

    with cf.ThreadPoolExecutor(n) as pool:
        answers = list(pool.map(imp, range(n)))
    ok = [(i, d) for i, status, d in answers if status == 200]
    assert len(ok) >= n // 2, [a[1:] for a in answers if a[1] != 200][:3]
    wrong = [(i, d["version"], d["note"]) for i, d in ok if d["note"] != f"req {i}"]
    assert not wrong, f"{len(wrong)} of {len(ok)} answers named another request's version: {wrong[:3]}"
    assert len({d["version"] for _, d in ok}) == len(ok)
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        notes = {v["version"]: v["note"] for v in c.get("/api/calibrations/1/versions").json()["versions"]}
    assert all(notes[d["version"]] == f"req {i}" for i, d in ok)


def test_two_tabs_get_a_conflict_not_a_silent_overwrite(server):
    srv, _ = server
    with httpx.Client(base_url=srv.url, timeout=30) as a, httpx.Client(base_url=srv.url, timeout=30) as b:
        ra, rb = a.get("/api/calibrations/1"), b.get("/api/calibrations/1")
        tag = ra.headers["ETag"]
        assert tag == rb.headers["ETag"] == ra.json()["etag"]
        assert a.get("/api/calibrations/1/versions").headers["ETag"] == tag
        r = a.post("/api/calibrations/1/rollback", json={"version": 1}, headers={"If-Match": tag})
        assert r.status_code == 200 and r.headers["ETag"] != tag, r.text
        current = r.json()["version"]
        for method, path, body in (
            ("POST", "/api/calibrations/1/rollback", {"version": 1}),
            ("PATCH", "/api/calibrations/1", {"name": "renamed by tab b"}),
            ("DELETE", "/api/calibrations/1", None),
            ("POST", "/api/calibrations/import", {"name": "cal 0", "calibration": rb.json()["calibration"]}),
        ):
            r = b.request(method, path, json=body, headers={"If-Match": tag})
            assert r.status_code == 412, (method, path, r.text)
            assert r.json()["current_version"] == current and r.json()["field"] == "If-Match"
            assert r.headers["ETag"] == r.json()["etag"]
        after = b.get("/api/calibrations/1")
        assert after.json()["current_version"] == current and after.json()["name"] == "cal 0"


# ---------------------------------------------------------------- 5. the database file is the truth
def test_a_database_deleted_or_replaced_under_the_server_answers_503(tmp_path):
    data = tmp_path / "data"
    seed(data)
    db = data / DB_NAME
    srv = serve(data)
    try:
        with httpx.Client(base_url=srv.url, timeout=30) as c:
            assert (
                c.post("/api/calibrations/1/image-to-robot", json={"points": [list(UV)]}).status_code == 200
            )
            away = tmp_path / "moved.db"
            os.rename(db, away)  # deleted (as far as the path knows)
            for method, path, body in (
                ("GET", "/api/calibrations", None),
                ("POST", "/api/calibrations/1/image-to-robot", {"points": [list(UV)]}),  # the cached one
                ("POST", "/api/calibrations/1/rollback", {"version": 1}),
            ):
                r = c.request(method, path, json=body)
                assert r.status_code == 503, (path, r.text)
                assert r.json()["error"].startswith("database replaced or missing"), r.text
            assert not db.exists()  # no empty database created in its place
            os.rename(away, db)  # the same file back: sane again
            assert c.get("/api/calibrations").status_code == 200
            copy_ = tmp_path / "copy.db"
            shutil.copy(db, copy_)
            os.replace(copy_, db)  # replaced by another file (same content, another inode)
            r = c.post("/api/calibrations/1/image-to-robot", json={"points": [list(UV)]})
            assert r.status_code == 503 and "database replaced or missing" in r.json()["error"], r.text
    finally:
        srv.stop()


# ---------------------------------------------------------------- 9. HTTP hardening
def _serve_on(host: str, data: Path, *extra: str):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "eyetohand.cli",
            "serve",
            "--host",
            host,
            "--port",
            "0",
            "--data",
            str(data),
            "--log-level",
            "error",
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=src_env(),
    )
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("workbench: http://"):
            return proc, int(line.split(f"http://{host}:")[1].split("/")[0])
    raise AssertionError("serve did not start")


def test_the_bound_address_and_allowed_hosts_are_served(tmp_path):
    seed(tmp_path)
    proc, port = _serve_on("127.0.0.2", tmp_path, "--allow-host", "cell.local")
    try:
        url = f"http://127.0.0.2:{port}"
        deadline = time.monotonic() + 20
        while True:
            try:
                r = httpx.get(url + "/api/calibrations", timeout=2)
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline
                time.sleep(0.1)
        assert r.status_code == 200, r.text  # was 400: the bound address was not an allowed Host
        assert httpx.get(url + "/api/health", headers={"Host": "cell.local"}).status_code == 200
        r = httpx.get(url + "/api/health", headers={"Host": "evil.example"})
        assert r.status_code == 400 and r.json()["field"] == "Host"
    finally:
        proc.terminate()
        proc.wait(timeout=20)


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
@pytest.mark.long
def test_half_sent_requests_are_closed_while_a_normal_client_is_served(server):
    srv, _ = server
    slow: list[socket.socket] = []
    opened: list[float] = []  # when each connect returned: a burst past the listen backlog (64) waits
    # for the client's SYN retransmit (~1 s), so each socket's ~15 s runs from its own connect
    try:
        for i in range(500):
            s = socket.create_connection(("127.0.0.1", srv.http_port), timeout=5)
            if i % 10 == 0:  # a complete head promising a body that never comes
                s.sendall(
                    b"POST /api/pairs/parse HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                    b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{"
                )
            else:  # a head that never ends
                s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            slow.append(s)
            opened.append(time.monotonic())
        start = time.monotonic()
        with httpx.Client(base_url=srv.url, timeout=5) as c:
            assert c.get("/api/calibrations").status_code == 200
            assert (
                c.post("/api/calibrations/1/image-to-robot", json={"points": [list(UV)]}).status_code == 200
            )
        assert time.monotonic() - start < 3
        closed = 0
        for s, t_open in zip(slow, opened, strict=True):
            s.settimeout(max(0.1, t_open + 16 - time.monotonic()))
            try:
                data = s.recv(4096)
                while data:  # an answer (408/400) is fine, then the close
                    data = s.recv(4096)
                closed += 1
            except (ConnectionResetError, BrokenPipeError):
                closed += 1
            except TimeoutError:
                break
        assert closed == len(slow), f"{closed} of {len(slow)} half-sent requests closed within ~15 s"
    finally:
        for s in slow:
            s.close()


def test_cross_site_posts_are_refused(server):
    srv, _ = server
    url = srv.url
    r = httpx.post(url + "/api/collect/points/1/drop")  # body-less, as a form on any site can send it
    assert r.status_code == 403 and r.json()["field"] == "Content-Type", r.text
    r = httpx.post(
        url + "/api/calibrations/1/rollback",
        content=b'{"version": 1}',
        headers={"Content-Type": "text/plain"},
    )
    assert r.status_code == 415, r.text  # a form's text/plain body: refused unread
    r = httpx.post(
        url + "/api/calibrations/1/rollback", json={"version": 1}, headers={"Origin": "http://evil.example"}
    )
    assert r.status_code == 403 and r.json()["field"] == "Origin", r.text
    r = httpx.delete(url + "/api/calibrations/1", headers={"Origin": "null"})
    assert r.status_code == 403, r.text
    r = httpx.post(url + "/api/calibrations/1/rollback", json={"version": 1}, headers={"Origin": url})
    assert r.status_code == 200, r.text
    r = httpx.post(url + "/api/collect/points/1/drop", headers={"X-Requested-With": "x"})
    assert r.status_code == 404, r.text  # through the guard: no collection runs here


# ---------------------------------------------------------------- 10. names, duplicate keys, token file
def test_look_alike_names_and_duplicate_keys_are_refused(server):
    srv, file = server
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        before = state(c)
        for name in ("Cal 0", "\u0441al 0", "c\u0430l\u00a00"):  # case, Cyrillic с / а, a no-break space
            r = c.post("/api/calibrations/import", json={"name": name, "calibration": file})
            assert r.status_code == 409 and r.json()["field"] == "name", (name, r.text)
        assert state(c) == before
        pairs = json.dumps(PAIRS[:4])
        raw = '{"name": "dup", "model": "homography", "pairs": ' + pairs[:-2] + ', "u": 1}]}'
        r = c.post("/api/calibrations", content=raw.encode(), headers={"Content-Type": "application/json"})
        assert r.status_code == 400 and r.json()["field"] == "pairs[3].u", r.text
        raw = '{"points": [[600, 700]], "points": [[1e6, 1e6]]}'
        r = c.post(
            "/api/calibrations/1/image-to-robot",
            content=raw.encode(),
            headers={"Content-Type": "application/json"},
        )
        assert r.status_code == 400 and r.json()["field"] == "points", r.text
        assert state(c) == before


def test_deep_bodies_and_weak_or_long_if_match_are_refused_with_the_field(server):
    """A body nested 990 levels deep (was 500, RecursionError) is 400 naming the body, on the mapping
    route and a write; If-Match W/"<the current tag>" (strong comparison, RFC 9110 13.1.1; it was taken
    as the tag) and an If-Match over 1024 characters (was 422, no field) are 400 naming If-Match;
    nothing changes."""
    srv, _ = server
    with httpx.Client(base_url=srv.url, timeout=30) as c:
        before = state(c)
        for depth in (990, 5000):
            deep = "[" * depth + "]" * depth
            for path, body in (
                ("/api/calibrations/1/image-to-robot", '{"points": ' + deep + "}"),
                ("/api/calibrations/1/image-to-robot", deep),
                ("/api/calibrations", '{"name": "deep", "model": "homography", "pairs": ' + deep + "}"),
                ("/api/calibrations/1/rollback", '{"version": ' + deep + "}"),
            ):
                r = c.post(path, content=body.encode(), headers={"Content-Type": "application/json"})
                assert r.status_code == 400 and r.json()["field"] == "body", (depth, path, r.text)
        tag = c.get("/api/calibrations/1").headers["ETag"]
        for if_match in (f"W/{tag}", f'"x", W/{tag}', ", ".join([tag] * 80)):
            for method, path, body in (
                ("PATCH", "/api/calibrations/1", {"name": "renamed"}),
                ("POST", "/api/calibrations/1/rollback", {"version": 1}),
                ("DELETE", "/api/calibrations/1", None),
            ):
                r = c.request(method, path, json=body, headers={"If-Match": if_match})
                assert r.status_code == 400 and r.json()["field"] == "If-Match", (if_match[:20], r.text)
                words = r.json()["error"]
                assert ("weak ETag" in words) if "W/" in if_match else ("more than 1024" in words), words
        assert state(c) == before


def test_the_token_can_come_from_a_file_not_the_command_line(tmp_path):
    seed(tmp_path / "data")
    token = "s3cret-token-" + os.urandom(6).hex()
    tf = tmp_path / "token"
    tf.write_text(token + "\n")
    srv = serve(tmp_path / "data", "--token-file", str(tf))
    try:
        cmdline = Path(f"/proc/{srv.proc.pid}/cmdline").read_bytes()
        assert token.encode() not in cmdline
        assert httpx.get(srv.url + "/api/calibrations").status_code == 401
        r = httpx.get(srv.url + "/api/calibrations", headers={"Authorization": f"Bearer {token}"})
        assert r.status_code == 200
    finally:
        srv.stop()
