"""The workbench's JSON API, its SQLite store, the TCP line service and `eyetohand serve`."""

from __future__ import annotations

import asyncio
import csv
import json
import time
from pathlib import Path

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, ServeProcess, records

from eyetohand import InputError, load_pairs
from eyetohand.calibration.file import Calibration
from eyetohand.cli import main as cli_main
from eyetohand.core import MAX_PAIRS
from eyetohand.positioning import MAX_LINE, LineServer
from eyetohand.positioning import answer as tcp_answer
from eyetohand.server.app import LOOPBACK_HOSTS, MAX_POINTS, create_app
from eyetohand.server.storage import Store

PAIRS = records(PAPER / "calibration_points.csv")
CHECK = records(PAPER / "check_points.csv")


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(tmp_path / "data")) as c:
        yield c


def create(client, name="cal", **kw):
    body = {"name": name, "pairs": PAIRS, "check": CHECK, "model": "homography", "optimizer": "lm", **kw}
    r = client.post("/api/calibrations", json=body)
    assert r.status_code == 201, r.text
    return r.json()


# ---------------------------------------------------------------------- API


def test_create_get_list_and_summary(client):
    d = create(client, "cell 3", model="paper", optimizer="hybrid-pso", seed=0)
    assert d["id"] == 1 and d["version"] == 1 and d["name"] == "cell 3"
    s = d["summary"]
    assert s["model"] == "paper" and s["optimizer"] == "hybrid-pso"
    assert len(s["history"]) == 150 and s["history"] == sorted(s["history"], reverse=True)
    assert 0.09 < s["fitness_mm"] < 0.12  # the paper's Fig. 4 levels off near 0.1 mm
    assert s["check"]["n"] == 9 and s["check"]["max_mm"] < 0.1
    assert {v["id"] for v in s["vectors"]["check"]} == {r["id"] for r in CHECK}
    listed = client.get("/api/calibrations").json()
    assert [(c["id"], c["name"], c["current_version"]) for c in listed] == [(1, "cell 3", 1)]
    full = client.get("/api/calibrations/1").json()
    assert full["pairs"][0]["u"] == PAIRS[0]["u"] and len(full["check"]) == 9
    assert full["calibration"]["schema"] == "eyetohand.calibration"


def test_versions_exclude_rollback_and_delete(client):
    create(client, "a")
    r = client.post(
        "/api/calibrations/1/versions",
        json={"pairs": PAIRS, "check": CHECK, "model": "affine", "exclude": ["3", "7"], "note": "drop 3, 7"},
    )
    assert r.status_code == 201, r.text
    v2 = r.json()
    assert v2["version"] == 2 and v2["summary"]["n_pairs"] == 14
    assert [p["id"] for p in v2["summary"]["excluded"]["points"]] == ["3", "7"]
    r = client.post("/api/calibrations/1/rollback", json={"version": 1})
    assert r.status_code == 200 and r.json()["version"] == 3 and r.json()["note"] == "rollback to version 1"
    vs = client.get("/api/calibrations/1/versions").json()
    assert [v["model"] for v in vs["versions"]] == ["homography", "affine", "homography"]
    one = client.get("/api/calibrations/1", params={"version": 1}).json()["calibration"]
    three = client.get("/api/calibrations/1").json()["calibration"]
    assert one == three
    assert client.post("/api/calibrations/1/rollback", json={"version": 9}).status_code == 404
    assert client.delete("/api/calibrations/1").status_code == 204
    r = client.get("/api/calibrations/1")
    assert r.status_code == 404 and r.json() == {"error": "no calibration with id 1", "field": "id"}


def test_errors_name_the_field(client):
    def post(body, path="/api/calibrations"):
        r = client.post(path, json=body)
        assert 400 <= r.status_code < 500, r.text
        return r.status_code, r.json()

    base = {"name": "x", "pairs": PAIRS}
    bad = [dict(p) for p in PAIRS]
    bad[3]["u"] = "abc"
    assert post({**base, "pairs": bad}) == (
        422,
        {"error": "pairs[3].u: Input should be a valid number, not a string", "field": "pairs[3].u"},
    )
    dup = [dict(p) for p in PAIRS]
    dup[5]["id"] = "2"
    status, err = post({**base, "pairs": dup})
    assert status == 422 and err["field"] == "pairs[5].id" and "duplicate id '2'" in err["error"]
    status, err = post({**base, "model": "nope"})
    assert status == 422 and err["field"] == "model"
    status, err = post({**base, "pairs": PAIRS[:2]})
    assert status == 422 and err["field"] == "pairs" and "pairs" in err["error"]
    status, err = post({**base, "exclude": ["99"]})
    assert (status, err["field"]) == (422, "exclude[0]")
    status, err = post({"pairs": PAIRS})
    assert (status, err["field"]) == (422, "name")
    status, err = post({**base, "optimizer": "hybrid-pso", "particles": 1000, "iterations": 1000})
    assert (status, err["field"]) == (422, "iterations")
    create(client, "x")
    status, err = post(base)
    assert (status, err["field"]) == (409, "name")
    status, err = post({**base, "name": "1"})  # only digits would read as an id
    assert (status, err["field"]) == (422, "name") and "id" in err["error"]
    create(client, "1a")
    r = client.post("/api/calibrations", content=b'{"name": ', headers={"Content-Type": "application/json"})
    assert r.status_code == 400 and r.json()["field"] == "body"
    r = client.post("/api/calibrations", content=json.dumps(base), headers={"Content-Type": "text/plain"})
    assert 400 <= r.status_code < 500 and "error" in r.json()
    status, err = post({"text": "u,v,x,y\n1,2,3\n", "source": "f.csv"}, "/api/pairs/parse")
    assert (status, err["field"], err["line"]) == (422, "text", 2)
    assert err["error"] == "f.csv line 2: 3 fields, the header has 4"
    r = client.post("/api/calibrations/1/image-to-robot", json={"points": [[1, 2]], "z": [1, 2]})
    assert r.status_code == 422 and r.json()["field"] == "z"
    r = client.post("/api/calibrations/1/image-to-robot", json={"points": []})
    assert r.status_code == 422 and r.json()["field"] == "points"
    r = client.get("/api/calibrations/0")
    assert r.status_code == 422 and r.json()["field"] == "cal_id"


def test_openapi_schema_is_precise(client):
    spec = client.get("/openapi.json").json()
    paths = spec["paths"]
    for p in (
        "/api/calibrations",
        "/api/calibrations/{cal_id}",
        "/api/calibrations/{cal_id}/image-to-robot",
        "/api/calibrations/{cal_id}/versions",
        "/api/calibrations/{cal_id}/rollback",
        "/api/calibrations/{cal_id}/export",
        "/api/jobs/{job_id}",
    ):
        assert p in paths, p
    pair = spec["components"]["schemas"]["PairIn"]
    assert set(pair["required"]) == {"u", "v", "x", "y"} and pair["additionalProperties"] is False
    create_req = spec["components"]["schemas"]["CreateCalibration"]
    assert create_req["properties"]["max_pairs"]["default"] == MAX_PAIRS  # the cap a request may raise
    assert "paper" in create_req["properties"]["model"]["enum"]
    body = paths["/api/calibrations/{cal_id}/image-to-robot"]["post"]["requestBody"]
    assert body["content"]["application/json"]["schema"]["properties"]["points"]["maxItems"] == MAX_POINTS


def test_jobs_progress_save_and_cancel(client):
    r = client.post(
        "/api/jobs/fit",
        json={"pairs": PAIRS, "check": CHECK, "model": "paper", "optimizer": "hybrid-pso", "seed": 1},
    )
    assert r.status_code == 202
    jid = r.json()["id"]
    seen, history = set(), []
    deadline = time.monotonic() + 60
    while True:
        j = client.get(f"/api/jobs/{jid}", params={"since": len(history)}).json()
        assert j["history_from"] == len(history)
        history += j["history"]
        seen.add(j["status"])
        if j["status"] in ("done", "failed", "cancelled"):
            break
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert j["status"] == "done", j
    assert len(history) == 150 and history == j["result"]["history"]
    r = client.post(f"/api/jobs/{jid}/image-to-robot", json={"points": [[600, 900]]})
    unsaved = r.json()["points"]
    saved = client.post(f"/api/jobs/{jid}/save", json={"name": "from job"}).json()
    r = client.post(f"/api/calibrations/{saved['id']}/image-to-robot", json={"points": [[600, 900]]})
    assert r.json()["points"] == unsaved
    assert client.get(f"/api/jobs/{jid}").json()["saved"]["id"] == saved["id"]
    # cancel: a long run stops early and leaves no result
    r = client.post(
        "/api/jobs/fit",
        json={"pairs": PAIRS, "model": "paper", "optimizer": "pso", "iterations": 1000, "particles": 400},
    )
    jid = r.json()["id"]
    client.delete(f"/api/jobs/{jid}")  # at once: the swarm now finishes 400 x 1000 in well under a second
    deadline = time.monotonic() + 30
    while (j := client.get(f"/api/jobs/{jid}").json())["status"] in ("queued", "running"):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert j["status"] == "cancelled" and j["result"] is None and len(j["history"]) < 1000
    r = client.post(f"/api/jobs/{jid}/save", json={"name": "nope"})
    assert r.status_code == 409 and r.json()["field"] == "id"
    assert client.get("/api/jobs/nope").status_code == 404


def test_compare_job(client):
    r = client.post("/api/jobs/compare", json={"pairs": PAIRS, "check": CHECK})
    jid = r.json()["id"]
    deadline = time.monotonic() + 90
    while (j := client.get(f"/api/jobs/{jid}").json())["status"] in ("queued", "running"):
        assert time.monotonic() < deadline
        time.sleep(0.2)
    assert j["status"] == "done"
    combos = {(row["model"], row["optimizer"]) for row in j["compare"]}
    assert ("paper", "hybrid-pso") in combos and ("homography", "lm") in combos


# ---------------------------------------------------------------------- same numbers as the CLI


def test_mappings_equal_eyetohand_apply(client, tmp_path):
    rng = np.random.default_rng(7)
    train = load_pairs(PAPER / "calibration_points.csv").uv_px  # points inside its calibrated region
    w = rng.dirichlet(np.ones(3), 300)
    uv = np.einsum("nk,nkj->nj", w, train[rng.integers(0, len(train), (300, 3))])
    src = tmp_path / "points.csv"
    src.write_text("u,v\n" + "".join(f"{float(u)!r},{float(v)!r}\n" for u, v in uv))
    fits = (("h", "homography", "lm"), ("p", "paper", "hybrid-pso"), ("r", "homography-radial", "lm"))
    for name, model, opt in fits:
        d = create(client, name, model=model, optimizer=opt, seed=3)
        cal_file = tmp_path / f"{name}.json"
        r = client.get(f"/api/calibrations/{d['id']}/export")
        assert r.status_code == 200 and f'filename="{name}-v1.json"' in r.headers["content-disposition"]
        cal_file.write_bytes(r.content)
        out = tmp_path / f"{name}.csv"
        assert cli_main(["apply", str(cal_file), str(src), "-o", str(out)]) == 0
        with open(out, newline="") as fh:
            cli_xyz = np.array([[float(row[c]) for c in "xyz"] for row in csv.DictReader(fh)])
        api = client.post(f"/api/calibrations/{d['id']}/image-to-robot", json={"points": uv.tolist()})
        api_xyz = np.array(api.json()["points"])
        assert api_xyz.shape == (300, 3)
        assert np.abs(api_xyz - cli_xyz).max() <= 1e-9, name
        # and the TCP service answers the same numbers
        cal = Calibration.load(cal_file)
        tcp_xyz = asyncio.run(_tcp_map(cal, uv[:50]))
        assert np.abs(tcp_xyz - cli_xyz[:50]).max() <= 1e-9, name


async def _tcp_map(cal, uv) -> np.ndarray:
    srv = LineServer(cal, "127.0.0.1", 0)
    await srv.start()
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        writer.write("".join(f"{float(u)!r},{float(v)!r}\n" for u, v in uv).encode())
        await writer.drain()
        lines = [await reader.readline() for _ in uv]
        writer.close()
        await writer.wait_closed()
    finally:
        srv.close()
    return np.array([[float(x) for x in ln.decode().split(",")] for ln in lines])


# ---------------------------------------------------------------------- persistence


def _stored(c) -> dict:
    """Every version list and stored calibration file of calibrations 1 (3 versions) and 2 (1)."""
    return {
        i: (
            c.get(f"/api/calibrations/{i}/versions").json(),
            [
                c.get(f"/api/calibrations/{i}", params={"version": v}).json()["calibration"]
                for v in range(1, 4 if i == 1 else 2)
            ],
        )
        for i in (1, 2)
    }


def test_restart_keeps_every_calibration_and_its_history(tmp_path):
    data = tmp_path / "data"
    with TestClient(create_app(data)) as c:
        create(c, "one")
        create(c, "two", model="affine")
        c.post("/api/calibrations/1/versions", json={"pairs": PAIRS, "model": "affine", "exclude": ["0"]})
        c.post("/api/calibrations/1/rollback", json={"version": 1})
        c.patch("/api/calibrations/2", json={"name": "two renamed"})
        before = _stored(c)
        mapped = c.post("/api/calibrations/1/image-to-robot", json={"points": [[500, 700]]}).json()
        c.app.state.store.close()
    with TestClient(create_app(data)) as c:
        after = _stored(c)
        assert after == before
        assert before[1][0]["current_version"] == 3 and before[2][0]["name"] == "two renamed"
        assert c.post("/api/calibrations/1/image-to-robot", json={"points": [[500, 700]]}).json() == mapped


def test_store_write_is_all_or_nothing(tmp_path, monkeypatch):
    store = Store(tmp_path, create=True)
    store.create("a", {}, {"x": 1}, [], None)

    def boom(*_a, **_k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(Store, "_insert_version", staticmethod(boom))
    with pytest.raises(RuntimeError):
        store.create("b", {}, {"x": 2}, [], None)
    with pytest.raises(RuntimeError):
        store.add_version(1, {}, {"x": 3}, [], None, "v2")
    monkeypatch.undo()
    assert [(r.name, r.current_version) for r, _ in store.list()] == [("a", 1)]
    assert [v.version for v in store.versions(1)] == [1]
    assert store._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store.close()


# ---------------------------------------------------------------------- limits and safety


def test_body_limit_gives_413(tmp_path):
    with TestClient(create_app(tmp_path, max_body_bytes=4096)) as c:
        r = c.post("/api/pairs/parse", json={"text": "x" * 5000})
        assert r.status_code == 413 and r.json()["field"] == "body"
        r = c.post(
            "/api/pairs/parse",
            content=iter([b'{"text": "', b"x" * 5000, b'"}']),
            headers={"Content-Type": "application/json"},
        )  # chunked: no Content-Length
        assert r.status_code == 413
        r = c.post("/api/pairs/parse", json={"text": "u,v,x,y\n1,2,3,4\n"})
        assert r.status_code == 200


@pytest.mark.long
def test_a_million_points_work_and_more_get_413(client):
    create(client, "big")
    rng = np.random.default_rng(0)
    uv = np.round(rng.uniform(0, 2000, (MAX_POINTS, 2)), 2)
    body = orjson.dumps(
        {"points": uv, "z": 167.4166, "allow_outside": True, "sigma": False},
        option=orjson.OPT_SERIALIZE_NUMPY,
    )
    t0 = time.perf_counter()
    r = client.post(
        "/api/calibrations/1/image-to-robot", content=body, headers={"Content-Type": "application/json"}
    )
    seconds = time.perf_counter() - t0
    assert r.status_code == 200
    xyz = np.array(orjson.loads(r.content)["points"])
    assert xyz.shape == (MAX_POINTS, 3) and np.isfinite(xyz).all()
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    idx = rng.choice(MAX_POINTS, 1000, replace=False)
    assert np.abs(xyz[idx] - cal.image_to_robot(uv[idx], 167.4166, allow_outside=True)).max() <= 1e-9
    inside = np.array(orjson.loads(r.content)["inside"])
    assert inside.dtype == bool and 0 < inside.sum() < MAX_POINTS
    print(f"1e6 points: {seconds:.1f} s")
    body = b'{"points": [' + b",".join([b"[1,2]"] * (MAX_POINTS + 1)) + b"]}"
    r = client.post(
        "/api/calibrations/1/image-to-robot", content=body, headers={"Content-Type": "application/json"}
    )
    assert r.status_code == 413 and r.json()["field"] == "points"
    assert "1000000" in r.json()["error"]


def test_token_and_host_guards(tmp_path):
    app = create_app(tmp_path, token="s3cret-token", allowed_hosts=LOOPBACK_HOSTS)
    with TestClient(app, base_url="http://127.0.0.1:8765") as c:
        assert c.get("/api/health").status_code == 200
        r = c.get("/api/calibrations")
        assert r.status_code == 401 and r.json()["field"] == "Authorization"
        assert c.get("/api/calibrations", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert c.get("/api/calibrations", headers={"Authorization": "Bearer s3cret-token"}).status_code == 200
        r = c.get("/", headers={"Host": "evil.example:8765"})
        assert r.status_code == 400 and r.json()["field"] == "Host"


def test_serve_refuses_unsafe_options(capsys):
    assert cli_main(["serve", "--host", "0.0.0.0"]) == 2
    assert "needs --token" in capsys.readouterr().err
    assert cli_main(["serve", "--tcp", "127.0.0.1:7001"]) == 2
    assert "--calibration" in capsys.readouterr().err
    assert cli_main(["serve", "--tcp", "0.0.0.0:7001", "--calibration", "x"]) == 2
    assert cli_main(["serve", "--tcp", "nonsense", "--calibration", "x"]) == 2


def test_names_are_data_not_paths(client, tmp_path):
    name = "../../etc/passwd; DROP TABLE calibrations;--"
    d = create(client, name)
    assert client.get(f"/api/calibrations/{d['id']}").json()["name"] == name
    r = client.get(f"/api/calibrations/{d['id']}/export")
    assert 'filename="etc_passwd_DROP_TABLE_calibrations_--' in r.headers["content-disposition"]
    assert sorted(p.name for p in (tmp_path / "data").iterdir()) <= [
        "calibrations.db",
        "calibrations.db-shm",
        "calibrations.db-wal",
    ]


# ---------------------------------------------------------------------- TCP line service


def test_tcp_service_many_clients_and_errors(paper_pairs):
    from eyetohand import calibrate

    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False)
    asyncio.run(_tcp_session(cal))


async def _tcp_session(cal):
    srv = LineServer(cal, "127.0.0.1", 0)
    await srv.start()
    try:

        async def client(k: int) -> list[str]:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            out = []
            for i in range(20):
                writer.write(f"{400 + k + i},{600 + i}\n".encode())
                await writer.drain()
                out.append((await reader.readline()).decode())
            writer.close()
            await writer.wait_closed()
            return out

        answers = await asyncio.gather(*(client(k) for k in range(64)))
        for k, lines in enumerate(answers):
            for i, ln in enumerate(lines):
                got = np.array([float(x) for x in ln.strip().split(",")])
                want = cal.image_to_robot(np.array([[400.0 + k + i, 600.0 + i]]))[0]
                assert np.abs(got - want).max() <= 1e-9

        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        for line, want in (
            (b"1,2,3,4\n", "ERR 4 numbers"),
            (b"abc,2\n", "ERR u: 'abc' is not a number"),
            (b"1,nan\n", "ERR v: 'nan' is not a finite number"),
            (b"\n", "ERR empty line"),
            (b"\xff,1\n", "ERR not ASCII"),
            (b"600,900,167.4\n", ""),
        ):
            writer.write(line)
            await writer.drain()
            got = (await reader.readline()).decode()
            assert got.startswith(want) and got.endswith("\n"), (line, got)
        writer.write(b"1" * (MAX_LINE + 10) + b"\n")
        await writer.drain()
        got = (await reader.readline()).decode()
        assert got.startswith("ERR line longer than")
        assert await reader.read() == b""  # closed
        writer.close()
    finally:
        srv.close()
    # with a token the first line must authenticate
    srv = LineServer(cal, "127.0.0.1", 0, token="s3cret-token")
    await srv.start()
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        writer.write(b"600,900\n")
        assert (await reader.readline()).startswith(b"ERR send 'AUTH")
        writer.close()
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        writer.write(b"AUTH s3cret-token\n600,900\n")
        assert await reader.readline() == b"OK\n"
        assert len((await reader.readline()).split(b",")) == 3
        writer.close()
    finally:
        srv.close()


# ---------------------------------------------------------------------- the real command


def test_eyetohand_serve_http_and_tcp(tmp_path):
    """`eyetohand serve --tcp … --calibration NAME` as a subprocess: the page, the API and TCP agree."""
    import socket

    import httpx

    data = tmp_path / "data"
    app = create_app(data)
    create(TestClient(app), "cell 3")
    app.state.store.close()

    srv = ServeProcess(data, "--calibration", "cell 3")
    try:
        url, tcp_port = srv.url, srv.tcp_port
        assert "eyetohand workbench" in httpx.get(url + "/").text
        api = httpx.post(
            url + "/api/calibrations/1/image-to-robot", json={"points": [[600.5, 900.25]]}
        ).json()
        with socket.create_connection(("127.0.0.1", tcp_port), timeout=10) as s:
            s.sendall(b"600.5,900.25\n")
            reply = s.makefile("rb").readline().decode()
        assert [float(x) for x in reply.split(",")] == api["points"][0]
        r = httpx.get(url + "/api/calibrations", headers={"Host": "attacker.example"})
        assert r.status_code == 400  # loopback binding answers loopback Host names only
    finally:
        srv.stop()
    assert any(line.startswith("TCP: 127.0.0.1") for line in srv.out)


# ---------------------------------------------------------------------- hostile input, races, small items


def test_numbers_are_strict_and_names_clean(client):
    for bad, why in ((True, "boolean"), ("6_00", "string"), ("600", "string"), (None, "null")):
        pairs = [dict(p) for p in PAIRS]
        pairs[3]["u"] = bad
        r = client.post("/api/calibrations", json={"name": "x", "pairs": pairs})
        assert r.status_code == 422 and r.json()["field"] == "pairs[3].u", (bad, r.text)
        assert why in r.json()["error"] or bad is None
    r = client.post("/api/calibrations", json={"name": "x", "pairs": PAIRS, "seed": True})
    assert (r.status_code, r.json()["field"]) == (422, "seed")
    create(client, "m", model="homography")
    for bad in (True, "2", 2.5):  # as `apply --symmetry` and the library: a whole number, not true or "2"
        body = {"points": [[600, 900]], "angles": [10], "symmetry": bad}
        r = client.post("/api/calibrations/1/image-to-robot", json=body)
        assert (r.status_code, r.json()["field"]) == (422, "symmetry"), (bad, r.text)
    for ch in ("\x00", "\x1b", "\x07", "\x7f", "\u200b", "\u202e", "\u2028"):
        r = client.post("/api/calibrations", json={"name": f"cell{ch}3", "pairs": PAIRS})
        assert (r.status_code, r.json()["field"]) == (422, "name"), repr(ch)
        assert f"U+{ord(ch):04X}" in r.json()["error"]
    for name in (" cell", "cell ", "42"):
        r = client.post("/api/calibrations", json={"name": name, "pairs": PAIRS})
        assert (r.status_code, r.json()["field"]) == (422, "name"), name
    d = create(client, "cafe\u0301")  # decomposed é: stored in NFC
    assert d["name"] == "caf\u00e9"
    r = client.post("/api/calibrations", json={"name": "caf\u00e9", "pairs": PAIRS, "model": "homography"})
    assert (r.status_code, r.json()["field"]) == (409, "name")
    pairs = [dict(p) for p in PAIRS]
    pairs[2]["id"] = "a\u200bb"
    r = client.post("/api/calibrations", json={"name": "y", "pairs": pairs})
    assert (r.status_code, r.json()["field"]) == (422, "pairs[2].id")


def test_store_find_refuses_ambiguous_references(tmp_path):
    from eyetohand.server.storage import Ambiguous

    store = Store(tmp_path, create=True)
    store.create("a", {}, {"x": 1}, [], None)
    store.create("1", {}, {"x": 2}, [], None)  # a digit-only name stored before they were refused
    with pytest.raises(Ambiguous, match="id:1"):
        store.find("1")
    assert store.find("id:1").name == "a" and store.find("2").name == "1"
    store.close()


def test_bodies_refused_before_parsing(tmp_path):
    with TestClient(create_app(tmp_path)) as c:
        big = b'{"name": "x", "pairs": [' + b",".join([b'{"u":1,"v":2,"x":3,"y":4}'] * 200_000) + b"]}"
        r = c.post("/api/calibrations", content=big, headers={"Content-Type": "application/json"})
        assert r.status_code == 413 and r.json()["field"] == "body"  # 5 MiB: over the fit limit
        r = c.post(
            "/api/calibrations",
            content=iter([big[:1000], big[1000:]]),
            headers={"Content-Type": "application/json"},
        )  # streamed, no Content-Length
        assert r.status_code == 413
        r = c.post("/api/calibrations", content=b"{}", headers={"Content-Type": "text/plain"})
        assert (r.status_code, r.json()["field"]) == (415, "Content-Type")
        r = c.post("/api/calibrations/1/image-to-robot", content=b"{}", headers={"Content-Type": "text/csv"})
        assert r.status_code == 415
        r = c.head("/api/calibrations/1/image-to-robot")
        assert r.status_code == 405 and r.headers["Allow"] == "POST"


def test_docs_work_offline(client):
    html = client.get("/docs").text
    assert "swagger-ui" in html and "cdn" not in html.lower() and "https://" not in html
    for asset in ("/docs-assets/swagger-ui-bundle.js", "/docs-assets/swagger-ui.css"):
        r = client.get(asset)
        assert r.status_code == 200 and len(r.content) > 10_000, asset
    spec = client.get("/openapi.json").json()
    responses = spec["paths"]["/api/calibrations"]["post"]["responses"]
    assert "415" in responses and "503" in responses


def test_mapping_uses_the_cache_and_sees_new_versions(client, monkeypatch):
    create(client, "m")
    body = {"points": [[600, 900]]}
    first = client.post("/api/calibrations/1/image-to-robot", json=body).json()
    store = client.app.state.service.store
    calls = []
    real = store.version
    monkeypatch.setattr(store, "version", lambda *a, **k: calls.append(a) or real(*a, **k))
    for _ in range(5):
        assert client.post("/api/calibrations/1/image-to-robot", json=body).json() == first
    assert calls == []  # no database read per mapping request
    client.post("/api/calibrations/1/versions", json={"pairs": PAIRS, "model": "affine"})
    second = client.post("/api/calibrations/1/image-to-robot", json=body).json()
    assert second["version"] == 2 and second["points"] != first["points"]
    client.post("/api/calibrations/1/rollback", json={"version": 1})
    third = client.post("/api/calibrations/1/image-to-robot", json=body).json()
    assert third["version"] == 3 and third["points"] == first["points"]
    assert client.delete("/api/calibrations/1").status_code == 204
    assert client.post("/api/calibrations/1/image-to-robot", json=body).status_code == 404


@pytest.mark.long
def test_delete_while_workers_fill_the_cache(tmp_path):
    import sys
    import threading

    app = create_app(tmp_path / "data")
    svc = app.state.service
    cal = create(TestClient(app), "base")
    calib = svc.store.version(cal["id"]).calibration
    ids = [svc.store.create(f"c{k}", {}, calib, [], None).id for k in range(60)]
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    errors: list[BaseException] = []
    stop = threading.Event()

    def filler(k: int) -> None:
        while not stop.is_set():
            for v in (1, None):
                try:
                    svc.calibration(cal["id"], v)
                except BaseException as exc:  # noqa: BLE001
                    errors.append(exc)

    threads = [threading.Thread(target=filler, args=(k,)) for k in range(3)]
    try:
        for t in threads:
            t.start()
        with TestClient(app) as c:
            for i in ids:
                c.get(f"/api/calibrations/{i}")  # puts i in the cache
                assert c.delete(f"/api/calibrations/{i}").status_code == 204
    finally:
        stop.set()
        for t in threads:
            t.join()
        sys.setswitchinterval(old)
        app.state.store.close()
    assert errors == []


def test_tcp_cut_last_line_and_auth_timeout(paper_pairs):
    from eyetohand import calibrate

    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False)

    async def run() -> None:
        srv = LineServer(cal, "127.0.0.1", 0)
        await srv.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"600,900\n600,9")  # the second line is cut off
            writer.write_eof()
            assert (await reader.readline()).count(b",") == 2
            assert await reader.read() == b""  # no answer to "600,9"
            writer.close()
        finally:
            srv.close()
        srv = LineServer(cal, "127.0.0.1", 0, token="s3cret-token", auth_s=0.3)
        await srv.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            t0 = time.monotonic()
            reply = await asyncio.wait_for(reader.readline(), 5)
            assert reply.startswith(b"ERR send 'AUTH") and time.monotonic() - t0 < 2
            writer.close()
        finally:
            srv.close()

    asyncio.run(run())


def test_tcp_idle_timeout_counts_from_the_last_line(paper_pairs):
    """A connection is closed after ``idle_s`` without a line (with one ERR line saying so); every
    line starts the count again, so a client sending more often than that is never cut off."""
    from eyetohand import calibrate

    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False)

    async def run() -> None:
        srv = LineServer(cal, "127.0.0.1", 0, idle_s=0.4)
        await srv.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            t0 = time.monotonic()
            for _ in range(6):  # 1.2 s in all, three times the idle limit
                writer.write(b"600,900\n")
                assert (await asyncio.wait_for(reader.readline(), 5)).count(b",") == 2
                await asyncio.sleep(0.2)
            assert time.monotonic() - t0 > 1.0
            t1 = time.monotonic()
            assert await asyncio.wait_for(reader.readline(), 5) == b"ERR idle for 0.4 s; closing\n"
            assert 0.1 < time.monotonic() - t1 < 2.0
            assert await asyncio.wait_for(reader.read(), 5) == b""
            writer.close()
            assert srv.clients == 0
        finally:
            srv.close()

    asyncio.run(run())


def test_serve_port_errors_are_one_line(capsys, tmp_path):
    import socket
    import subprocess
    import sys

    assert cli_main(["serve", "--port", "99999", "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --port") and err.count("\n") == 1
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "eyetohand.cli",
                "serve",
                "--port",
                str(s.getsockname()[1]),
                "--data",
                str(tmp_path),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert r.returncode == 2 and r.stderr.startswith("error: --port") and r.stderr.count("\n") == 1, r.stderr


def test_guarded_mapping_over_http_and_tcp_says_the_same(client):
    """Outside the region, off the plane, and allowed-with-flag: one rule, the same words."""
    create(client, "g", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    url = "/api/calibrations/1/image-to-robot"
    r = client.post(url, json={"points": [[600, 900], [99999, -5000]]})
    assert r.status_code == 422 and r.json()["field"] == "points[1]"
    assert "px outside the training points' hull" in r.json()["error"]
    r = client.post(url, json={"points": [[600, 900]], "z": 100})
    assert (
        r.status_code == 422
        and r.json()["field"] == "points[0].z"
        and "off the calibration plane" in r.json()["error"]
    )
    r = client.post(
        url, json={"points": [[600, 900], [99999, -5000]], "allow_outside": True, "angles": [30, 0]}
    )
    body = r.json()
    assert r.status_code == 200 and body["inside"] == [True, False] and len(body["rz_deg"]) == 2
    m = cal.map([[600, 900], [99999, -5000]], angle_deg=[30, 0], allow_outside=True)
    assert np.abs(np.array(body["points"]) - m.xyz_mm).max() <= 1e-9
    assert np.abs(np.array(body["sigma_mm"]) - m.sigma_mm).max() <= 1e-12
    lib_words = None
    try:
        cal.map([[99999, -5000]])
    except InputError as exc:
        lib_words = exc.reason
    assert tcp_answer(cal, b"99999,-5000") == f"ERR {lib_words}\n".encode()
    assert tcp_answer(cal, b"600,900,100").startswith(b"ERR z = 100 mm is 67.4 mm off the calibration plane")
    out = tcp_answer(cal, b"99999,-5000,allow").decode().strip().split(",")
    assert out[-1] == "OUTSIDE" and abs(float(out[0]) - m.xyz_mm[1, 0]) <= 1e-9
    rz = float(tcp_answer(cal, b"600,900,a=30").decode().split(",")[3])
    assert rz == pytest.approx(m.rz_deg[0], abs=1e-12)


# ---------------------------------------------------------------------- deployment (issue 11)


def _cal_file(tmp_path, model="homography") -> Path:
    from eyetohand import calibrate
    from eyetohand.core.pairs import pairs_from_records

    cal = calibrate(pairs_from_records(PAIRS), model, "lm", check=pairs_from_records(CHECK), loo=False)
    return cal.save(tmp_path / f"{model}.json")


def _serve_args(**kw):
    import argparse

    d = {
        "port": 0,
        "db_wait": 2.0,
        "token": None,
        "host": "127.0.0.1",
        "tcp": "127.0.0.1:0",
        "calibration": None,
    }
    d.update(kw)
    return argparse.Namespace(**d)


def test_serve_calibration_option_file_id_or_name(tmp_path):
    from eyetohand.server.startup import ServeError, calibration_path, check_options

    f = _cal_file(tmp_path)
    args = _serve_args(calibration=str(f))
    check_options(args)
    assert args.calibration_file.cal.model_name == "homography"
    assert calibration_path("id:3") is None and calibration_path("name:a/b.json") is None
    assert calibration_path("cell 3") is None and calibration_path("file:x") == Path("x")
    bad = tmp_path / "bad.json"
    bad.write_text(f.read_text().replace('"rms_mm": 0.', '"rms_mm": 1.', 1))
    with pytest.raises(ServeError, match=r"^--calibration: .*bad\.json"):
        check_options(_serve_args(calibration=str(bad)))
    with pytest.raises(ServeError, match="no such file|not found|does not exist"):
        check_options(_serve_args(calibration=str(tmp_path / "missing.json")))


def test_tcp_by_path_maps_bit_identically_to_apply(tmp_path, capsys):
    from eyetohand.cli import main
    from eyetohand.positioning import FixedCalibration

    f = _cal_file(tmp_path)
    src = FixedCalibration.from_file(f)
    assert main(["apply", str(f), "--uv", "600.25", "1200.5", "--json"]) == 0
    p = json.loads(capsys.readouterr().out)["points"][0]

    async def run():
        srv = LineServer(src, "127.0.0.1", 0)
        await srv.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"600.25,1200.5\nVERSION\n")
            await writer.drain()
            a = (await reader.readline()).decode().strip()
            b = (await reader.readline()).decode().strip()
            writer.close()
            return a, b
        finally:
            srv.close()

    a, b = asyncio.run(run())
    assert [float(x) for x in a.split(",")] == [p["x"], p["y"], p["z"]]
    import hashlib

    assert b == f"OK {f.resolve()},{hashlib.sha256(f.read_bytes()).hexdigest()}"


def test_import_then_tcp_follows_versions_rollback_and_delete(tmp_path):
    from eyetohand.server.stored import StoredCalibration

    data = tmp_path / "data"
    f_h, f_a = _cal_file(tmp_path, "homography"), _cal_file(tmp_path, "affine")
    with TestClient(create_app(data)) as c:
        body = {"name": "cell", "calibration": json.loads(f_h.read_text())}
        r = c.post("/api/calibrations/import", json=body)
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        store = Store(data)
        src = StoredCalibration(store, cid)

        async def ask(srv, lines):
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"".join(ln + b"\n" for ln in lines))
            await writer.drain()
            out = [(await reader.readline()).decode().strip() for _ in lines]
            writer.close()
            return out

        async def run():
            srv = LineServer(src, "127.0.0.1", 0, poll_s=0.1)
            await srv.start()
            try:
                first = await ask(srv, [b"600,1200", b"VERSION"])
                r = await asyncio.to_thread(
                    c.post,
                    "/api/calibrations/import",
                    json={"name": "cell", "calibration": json.loads(f_a.read_text())},
                )
                assert r.status_code == 200 and r.json()["version"] == 2, r.text
                t0 = asyncio.get_running_loop().time()
                while (await ask(srv, [b"VERSION"]))[0].split(",")[1] != "2":
                    assert asyncio.get_running_loop().time() - t0 < 1.0, "new version not in force in 1 s"
                    await asyncio.sleep(0.05)
                second = await ask(srv, [b"600,1200"])
                await asyncio.to_thread(c.post, f"/api/calibrations/{cid}/rollback", json={"version": 1})
                await asyncio.sleep(0.6)
                third = await ask(srv, [b"600,1200", b"VERSION"])
                await asyncio.to_thread(c.delete, f"/api/calibrations/{cid}")
                await asyncio.sleep(0.6)
                gone = await ask(srv, [b"600,1200", b"VERSION"])
                return first, second, third, gone
            finally:
                srv.close()

        first, second, third, gone = asyncio.run(run())
        store.close()
    assert first[1].startswith("OK cell,1,") and second[0] != first[0]
    assert third[0] == first[0] and third[1].startswith("OK cell,3,")
    assert gone == ["ERR calibration 'cell' was deleted"] * 2


def test_import_refuses_a_tampered_file_naming_why(client, tmp_path):
    d = json.loads(_cal_file(tmp_path).read_text())
    d["model"]["params"][0] *= 1.0001
    r = client.post("/api/calibrations/import", json={"name": "x", "calibration": d})
    assert r.status_code == 422 and "reproduce" in r.json()["error"], r.text
    d = json.loads(_cal_file(tmp_path).read_text())
    d["schema_version"] = 9
    r = client.post("/api/calibrations/import", json={"name": "x", "calibration": d})
    assert r.status_code == 422 and "newer" in r.json()["error"]
    assert client.get("/api/calibrations").json() == []


def test_verify_endpoint_and_history(client, tmp_path):
    d = create(client, "cell", model="homography")
    cid = d["id"]
    fresh = PAIRS[::2]  # inside the calibrated region (the paper's check points lie partly outside)
    shifted = [dict(p, x=p["x"] + 0.5) for p in fresh]
    for pairs, tol in ((fresh, 1.0), (shifted, 0.3)):
        r = client.post(f"/api/calibrations/{cid}/verify", json={"pairs": pairs, "tolerance_mm": tol})
        assert r.status_code == 200, r.text
    last = r.json()
    assert not last["passed"] and last["drift"]["significant"] and "shift" in last["drift"]["named"]
    h = client.get(f"/api/calibrations/{cid}/history").json()
    assert [e["passed"] for e in h["entries"]] == [True, False] and h["entries"][1]["version"] == 1
    assert (
        client.post(
            f"/api/calibrations/{cid}/verify", json={"pairs": fresh[:2], "tolerance_mm": 1}
        ).status_code
        == 422
    )


def _refusal(fn):
    try:
        fn()
    except InputError as exc:
        return exc
    raise AssertionError("not refused")


@pytest.mark.numeric  # the fitted horizon's last bits decide whether w is exactly 0 there
def test_horizon_refused_on_every_interface_even_when_allowed(client, tmp_path, capsys):
    """A pixel on a homography's vanishing line (and one beyond it) maps to no meaningful robot
    point: refused by the library, the CLI (exit 2), HTTP (422 naming the point) and TCP, with
    allow_outside too."""
    create(client, "h", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    H = cal.model.matrix_image_to_robot
    v_line = float(-(H[2, 0] * 600.0 + H[2, 2]) / H[2, 1])
    for v in (v_line, v_line + float(np.sign(v_line)) * 1e5):
        exc = _refusal(lambda v=v: cal.map([[600.0, v]], allow_outside=True))
        assert "maps to no finite robot point" in exc.reason and exc.field_path == "points[0]"
        r = client.post(
            "/api/calibrations/1/image-to-robot", json={"points": [[600, v]], "allow_outside": True}
        )
        assert r.status_code == 422 and r.json()["field"] == "points[0]" and exc.reason in r.json()["error"]
        assert tcp_answer(cal, f"600,{v!r},allow".encode()) == f"ERR {exc.reason}\n".encode()
        path = cal.save(tmp_path / "h.json")
        code = cli_main(["apply", str(path), "--uv", "600", repr(v), "--allow-outside"])
        out, err = capsys.readouterr()
        assert code == 2 and out == "" and err.count("\n") == 1 and "maps to no finite robot point" in err


@pytest.fixture(scope="module")
def two_height_records():
    from eyetohand.sim import Cell
    from eyetohand.sim.simulate import simulate

    sim = simulate(Cell.default(), "grid:4x4", (150.0, 200.0), n_check=0, seed=8)
    return sim.pairs.to_records()


@pytest.mark.parametrize("model", ["dlt3d", "camera"])
def test_multi_height_z_range_on_every_interface(client, tmp_path, capsys, two_height_records, model):
    """A z beyond the calibrated range (150..200 mm, margin 12.5 mm) is refused by the library, the
    CLI, HTTP and TCP with the same words; allowed, it is mapped and flagged inside = false."""
    r = client.post(
        "/api/calibrations",
        json={"name": model, "pairs": two_height_records, "model": model, "optimizer": "lm"},
    )
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    cal = Calibration.from_dict(client.get(f"/api/calibrations/{cid}").json()["calibration"])
    c = cal.region.hull_px.mean(axis=0)
    u, v = float(c[0]), float(c[1])
    exc = _refusal(lambda: cal.map([[u, v]], 260.0))
    assert "outside the calibrated heights: z = 260 mm, calibrated 150..200 mm" in exc.reason
    assert exc.field_path == "points[0].z"
    url = f"/api/calibrations/{cid}/image-to-robot"
    r = client.post(url, json={"points": [[u, v]], "z": 260})
    assert r.status_code == 422 and r.json()["field"] == "points[0].z" and exc.reason in r.json()["error"]
    assert tcp_answer(cal, f"{u!r},{v!r},260".encode()) == f"ERR {exc.reason}\n".encode()
    path = cal.save(tmp_path / "m.json")
    code = cli_main(["apply", str(path), "--uv", repr(u), repr(v), "--z", "260"])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and exc.reason in err
    # allowed: mapped and flagged, the same on every interface
    m = cal.map([[u, v]], 260.0, allow_outside=True)
    assert not m.inside[0] and m.xyz_mm[0, 2] == 260.0
    r = client.post(url, json={"points": [[u, v]], "z": 260, "allow_outside": True})
    assert r.status_code == 200 and r.json()["inside"] == [False]
    assert np.abs(np.array(r.json()["points"]) - m.xyz_mm).max() <= 1e-9
    fields = tcp_answer(cal, f"{u!r},{v!r},260,allow".encode()).decode().strip().split(",")
    assert fields[-1] == "OUTSIDE" and abs(float(fields[0]) - m.xyz_mm[0, 0]) <= 1e-9
    code = cli_main(["apply", str(path), "--uv", repr(u), repr(v), "--z", "260", "--allow-outside", "--json"])
    out, err = capsys.readouterr()
    rec = json.loads(out)["points"][0]
    assert code == 0 and rec["inside"] is False and "warning: 1 point(s) outside" in err
    # inside the range: answered, inside
    assert cal.map([[u, v]], 175.0).inside[0]


def test_apply_json_equals_the_http_mapping(client, tmp_path, capsys):
    create(client, "j", model="homography", optimizer="lm")
    body = client.get("/api/calibrations/1").json()["calibration"]
    path = Calibration.from_dict(body).save(tmp_path / "j.json")
    cal = Calibration.load(path)
    c = cal.region.hull_px.mean(axis=0)
    pts = [[600.0, 900.0], [float(c[0]) + 0.125, float(c[1]) - 3.5], [float(c[0]) - 20.25, float(c[1])]]
    src = tmp_path / "pts.csv"
    rows = [f"{u!r},{v!r},{a}\n" for (u, v), a in zip(pts, (0, 30, -75), strict=True)]
    src.write_text("u,v,angle\n" + "".join(rows))
    code = cli_main(["apply", str(path), str(src), "--json", "--symmetry", "2"])
    out, err = capsys.readouterr()
    assert code == 0, err
    cli = json.loads(out)["points"]
    r = client.post(
        "/api/calibrations/1/image-to-robot", json={"points": pts, "angles": [0, 30, -75], "symmetry": 2}
    )
    api = r.json()
    assert code == 0 and r.status_code == 200
    xyz = np.array([[p["x"], p["y"], p["z"]] for p in cli])
    assert np.abs(xyz - np.array(api["points"])).max() <= 1e-9
    assert np.abs(np.array([p["rz"] for p in cli]) - np.array(api["rz_deg"])).max() <= 1e-9
    assert np.abs(np.array([p["sigma_mm"] for p in cli]) - np.array(api["sigma_mm"])).max() <= 1e-12
    assert [p["inside"] for p in cli] == api["inside"]


# ---------------------------------------------------------------------- calibration from uploaded images

SMALL_CELL = """[camera]
width_px = 816
height_px = 683
pixel_size_um = 10.35
principal_offset_px = [4.0, -3.0]
"""


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """9 images of a grid:3x3 at z = 150 mm, rendered at a third of the default camera's resolution."""
    d = tmp_path_factory.mktemp("rendered")
    (d / "cell.toml").write_text(SMALL_CELL)
    argv = ["simulate", "--config", str(d / "cell.toml"), "--plan", "grid:3x3", "--heights", "150"]
    assert cli_main([*argv, "--check", "4", "--out", str(d / "sim"), "--seed", "2", "--images"]) == 0
    return d / "sim"


def _upload(folder: Path, poses: str = "poses.csv", skip=()) -> dict:
    import base64

    def f(path: Path) -> dict:
        return {"name": path.name, "data_base64": base64.b64encode(path.read_bytes()).decode()}

    names = [r["image"] for r in csv.DictReader((folder / poses).open())]
    return {
        "poses": f(folder / poses),
        "images": [f(folder / n) for n in names if n not in skip],
        "model": "homography",
    }


def _follow_images(client, jid: str) -> dict:
    deadline = time.monotonic() + 120
    while True:
        j = client.get(f"/api/images/jobs/{jid}").json()
        if j["status"] in ("done", "failed", "cancelled"):
            return j
        assert time.monotonic() < deadline, j
        time.sleep(0.05)


def test_images_calibrate_upload_equals_the_cli(client, rendered, capsys):
    """POST /api/images/calibrate with the poses CSV and its images: per-image detections, the fit and
    the saved calibration equal `eyetohand calibrate-images` on the same files; one image missing from
    the upload is left out with the CLI's words."""
    code = cli_main(["calibrate-images", str(rendered / "poses.csv"), "--model", "homography", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    cli = json.loads(out)
    r = client.post("/api/images/calibrate", json=_upload(rendered))
    assert r.status_code == 202 and r.json()["kind"] == "fit"
    j = _follow_images(client, r.json()["id"])
    assert j["status"] == "done", j
    assert j["poses"] == 9 and len(j["detections"]) == 9 and j["left_out"] == [] and j["unused_images"] == []
    assert [d["image"] for d in j["detections"]] == [d["image"] for d in cli["detections"]]
    for a, b in zip(j["detections"], cli["detections"], strict=True):
        assert a["ok"] and abs(a["u"] - b["u"]) < 1e-9 and abs(a["v"] - b["v"]) < 1e-9
    assert j["result"]["model"] == "homography" and j["result"]["n_pairs"] == 9
    assert abs(j["result"]["train"]["rms_mm"] - cli["train"]["rms_mm"]) < 1e-9
    saved = client.post(f"/api/jobs/{j['id']}/save", json={"name": "from images"})
    assert saved.status_code == 201 and saved.json()["request"]["source"] == "images"
    # one image not uploaded: left out, named as the CLI names a missing file
    first = next(csv.DictReader((rendered / "poses.csv").open()))["image"]
    r = client.post("/api/images/calibrate", json=_upload(rendered, skip={first}))
    j = _follow_images(client, r.json()["id"])
    assert j["status"] == "done" and j["left_out"] == [first] and j["result"]["n_pairs"] == 8
    assert "no such file" in j["detections"][0]["reason"]


def test_images_calibrate_refusals_use_the_cli_words(tmp_path, rendered, capsys):
    """A Latin-1 poses CSV fails the job with the CLI's message (no temporary path in it); bad base64
    and a body over the limit are refused at once (422, 413 before parsing)."""
    import base64

    bad = tmp_path / "poses.csv"
    bad.write_bytes((rendered / "poses.csv").read_bytes().replace(b"image,", b"image,\xe9,", 1))
    code = cli_main(["calibrate-images", str(bad), "--images", str(rendered)])
    _, err = capsys.readouterr()
    assert code != 0 and "not UTF-8" in err
    cli_words = err.strip().removeprefix("error: ").replace(str(tmp_path) + "/", "")
    app = create_app(tmp_path / "data", max_body_bytes=8_000_000)
    with TestClient(app) as c:
        body = _upload(rendered)
        body["poses"]["data_base64"] = base64.b64encode(bad.read_bytes()).decode()
        j = _follow_images(c, c.post("/api/images/calibrate", json=body).json()["id"])
        assert j["status"] == "failed" and j["error"]["error"] == cli_words, (j["error"], cli_words)
        assert j["error"]["field"] == "poses" and "eyetohand-images-" not in j["error"]["error"]
        body = _upload(rendered)
        body["images"][0]["data_base64"] = "not base64!"
        r = c.post("/api/images/calibrate", json=body)
        assert r.status_code == 422 and r.json()["field"] == "images[0].data_base64"
        body["images"][0]["name"] = "../up.png"
        r = c.post("/api/images/calibrate", json=body)
        assert r.status_code == 422 and "images" in r.json()["field"]
        big = _upload(rendered)
        big["images"] *= 3  # ~10 MB of base64
        r = c.post(
            "/api/images/calibrate", content=orjson.dumps(big), headers={"content-type": "application/json"}
        )
        assert r.status_code == 413 and "limit" in r.json()["error"]


# ---------------------------------------------------------------------- mapping fast paths (issue 13)

MAP_BODIES = [
    b'{"points": [[1,2]]}',
    b'{"points":[[1.5e3, -2]], "z": 3}',
    b'{"points": [ [1, 2] , [3,4] ]}',
    b'{"points": [\n  [\n    1,\n    2\n  ]\n]}',
    b'{"points": [[1,2,3]]}',
    b'{"points": [[1]]}',
    b'{"points": [[true,2]]}',
    b'{"points": [["1",2]]}',
    b'{"points": [[null,2]]}',
    b'{"points": []}',
    b'{"points": [[1,2]], "z": [1,2]}',
    b'{"points": [[+1,2]]}',
    b'{"points": [[01,2]]}',
    b'{"points": [[1.,2]]}',
    b'{"points": [[1e400,2]]}',
    b'{"points": [[[1,2]]]}',
    b'{"points": [[1,2],[[3,4],[5,6]],[7,8]]}',
    b'{"points": [[1,2]], "\\u0070oints": [[5,6]]}',
    b'{"a": {"points": [[1,2]]}}',
    b'{"points": [[1,2]]',
    b'{"points": [[1,2]],}',
    b'{"points": [[1,2] [3,4]]}',
    b'{"points": [[1 2,3]]}',
    b"[1]",
    b'{"points": [[1,2]], "sigma": 1}',
    b'{"points": [[1,2]], "symmetry": 0}',
    b'{"points": [[1,2],[3,4]], "angles": [1], "allow_outside": true}',
]


def test_fast_points_parse_answers_as_the_schema_does():
    """Every body gets the points, options, status, message and field that MapRequest gives."""
    from pydantic import ValidationError

    from eyetohand.server.errors import ApiError
    from eyetohand.server.responses import api_error_of_validation
    from eyetohand.server.routes import DuplicateKey, mapping, strict_json
    from eyetohand.server.schemas import MapRequest

    taken = 0
    for body in MAP_BODIES:
        taken += mapping.fast_points(body) is not None
        try:
            req, pts = mapping.parse_map_body(body)
            got = ("ok", pts.tolist(), req.model_dump(exclude={"points"}))
        except ApiError as exc:
            got = (exc.status, exc.message, exc.field)
        try:
            ref_req = MapRequest.model_validate_json(body)
            ref = ("ok", [list(p) for p in ref_req.points], ref_req.model_dump(exclude={"points"}))
        except ValidationError as exc:
            e = api_error_of_validation(exc.errors(include_url=False))
            ref = (e.status, e.message, e.field)
        try:  # a key given twice is refused (pydantic alone would keep the last one)
            strict_json(body)
        except DuplicateKey as exc:
            ref = (400, str(exc.detail), exc.field)
        except ValueError:
            pass
        assert got == ref, body
    assert taken >= 8  # the plain spellings do take the fast path
    uv = np.random.default_rng(3).uniform(-5000, 5000, (3001, 2))
    for opt in (0, orjson.OPT_INDENT_2):
        body = orjson.dumps({"points": uv}, option=orjson.OPT_SERIALIZE_NUMPY | opt)
        fast = mapping.fast_points(body)
        assert fast is not None and (fast[0] == uv).all()


JSON_CT = {"Content-Type": "application/json"}


def test_large_mapping_is_chunked_and_streamed_identically(client, monkeypatch):
    """Above INLINE_POINTS the answer streams in pieces, above CHUNK_POINTS it is mapped in chunks:
    the same bytes as one call, and a refusal names the same point."""
    from eyetohand.server.routes import mapping

    create(client, "big", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    monkeypatch.setattr(mapping, "CHUNK_POINTS", 700)
    monkeypatch.setattr(mapping, "CHUNK_BYTES", 5000)
    c = cal.region.hull_px.mean(axis=0)
    rng = np.random.default_rng(5)
    uv = c + rng.uniform(-300, 300, (2500, 2))
    z = cal.model.plane_z_mm if hasattr(cal.model, "plane_z_mm") else None
    body = {"points": uv.tolist(), "angles": rng.uniform(-90, 90, 2500).tolist(), "allow_outside": True}
    if z is not None:
        body["z"] = [z] * 2500
    r = client.post("/api/calibrations/1/image-to-robot", content=orjson.dumps(body), headers=JSON_CT)
    assert r.status_code == 200
    req, pts = mapping.parse_map_body(orjson.dumps(body))
    m = mapping.map_points(
        cal,
        pts,
        req.z,
        angles=req.angles,
        allow_outside=True,
        sigma=True,
        symmetry=1,
        tool_rz_offset_deg=None,
    )
    whole = {
        "id": 1,
        "version": 1,
        "units": "mm",
        "angle_units": "deg",
        "points": m.xyz_mm,
        "rz_deg": m.rz_deg,
    }
    whole.update({"sigma_mm": m.sigma_mm, "inside": m.inside})
    assert r.content == orjson.dumps(whole, option=orjson.OPT_SERIALIZE_NUMPY)
    assert 0 < sum(orjson.loads(r.content)["inside"]) < 2500
    del body["allow_outside"]
    r = client.post("/api/calibrations/1/image-to-robot", content=orjson.dumps(body), headers=JSON_CT)
    first = int(np.flatnonzero(~m.inside)[0])
    assert r.status_code == 422 and r.json()["field"] == f"points[{first}]"


def test_tcp_numbers_only_line_answers_as_the_general_path(client):
    create(client, "t", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    c = cal.region.hull_px.mean(axis=0)
    u, v = float(c[0]), float(c[1])
    plain = tcp_answer(cal, f"{u!r},{v!r}".encode())
    assert (
        plain
        == tcp_answer(cal, f" {u!r} , {v!r} \r".encode())
        == tcp_answer(cal, f"{u!r},{v!r},a=0".encode()).rsplit(b",", 1)[0] + b"\n"
    )
    assert tcp_answer(cal, b"600,nan") == b"ERR v: 'nan' is not a finite number\n"
    assert tcp_answer(cal, b"600,1e999") == b"ERR v: '1e999' is not a finite number\n"
    assert tcp_answer(cal, b"99999,-5000").startswith(b"ERR outside the calibrated region")
    assert tcp_answer(cal, b"1,2,3,4").startswith(b"ERR 4 numbers;")


def test_tcp_takes_the_orientation_words_apply_and_http_take(client):
    """Symmetry and the tool offset answer over TCP as through the library (and HTTP); '6_00' is no number."""
    create(client, "o", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    m = cal.map([[600, 900]], angle_deg=[150.0], symmetry=2, tool_rz_offset_deg=12.5)
    rz = float(tcp_answer(cal, b"600,900,a=150,s=2,t=12.5").decode().split(",")[3])
    assert rz == m.rz_deg[0] and -90 < rz <= 90
    r = client.post(
        "/api/calibrations/1/image-to-robot",
        json={"points": [[600, 900]], "angles": [150.0], "symmetry": 2, "tool_rz_offset_deg": 12.5},
    )
    assert r.json()["rz_deg"][0] == pytest.approx(rz, abs=1e-12)
    assert tcp_answer(cal, b"6_00,900") == b"ERR u: '6_00' is not a number\n"
    assert tcp_answer(cal, b"600,900,a=30,s=2.0") == tcp_answer(cal, b"600,900,a=30,s=2")  # text "2.0" is 2
    assert tcp_answer(cal, b"600,900,a=30,s=1.5") == (
        b"ERR symmetry must be a whole number from 1 to 360 (1: no fold, 2: 180 deg symmetric), got 1.5\n"
    )
    assert tcp_answer(cal, b"600,900,a=30,s=0").startswith(b"ERR symmetry must be a whole number")
    assert tcp_answer(cal, b"600,900,q=1").startswith(b"ERR unknown word 'q=1'")
    # the library's words in ASCII: a controller reads bytes (the library says "2: 180° symmetric")
    with pytest.raises(InputError, match="180° symmetric"):
        cal.map([[600, 900]], angle_deg=[30.0], symmetry=0)
    assert b"(1: no fold, 2: 180 deg symmetric), got 0\n" in tcp_answer(cal, b"600,900,a=30,s=0")


def test_line_protocol_reasons_are_ascii_with_the_symbols_spelt_out():
    from eyetohand.cell import MAX_REASON, ascii_reason

    assert ascii_reason("k1 ± 0.2 — 180° · 3×4 ≤ 5 µm, σ²") == "k1 +/- 0.2 - 180 deg * 3x4 <= 5 um, sigma^2"
    assert ascii_reason("two\nlines  here") == "two lines here"
    assert ascii_reason("中") == "?"
    long = ascii_reason("x" * 500)
    assert len(long) == MAX_REASON and long.endswith("...")
    assert all(ord(c) < 128 for c in ascii_reason("".join(chr(c) for c in range(0x80, 0x3000))))


def test_the_mapping_routes_are_matched_first_and_shadow_no_other_route(tmp_path):
    """Requests are matched against the routes in order; the mapping routes (the robot's hot path)
    come first, which is only harmless because no other route matches their paths."""
    from starlette.routing import Match

    from eyetohand.server.routes import calibrations, collect, images, jobs, mapping, meta, page, pairs

    app = create_app(tmp_path / "data")
    first = app.router.routes[1]  # after /openapi.json: an included router (FastAPI 0.165) or its first route
    tried_first = first.original_router.routes if hasattr(first, "original_router") else [first]
    assert str(getattr(tried_first[0], "path", "")).endswith("/image-to-robot"), first
    for path in ("/api/calibrations/1/image-to-robot", "/api/jobs/abc/image-to-robot"):
        scope = {"type": "http", "path": path, "method": "POST", "root_path": ""}
        assert any(r.matches(scope)[0] == Match.FULL for r in mapping.router.routes)
        for mod in (page, meta, pairs, calibrations, jobs, collect, images):
            for r in mod.router.routes:
                assert r.matches(scope)[0] == Match.NONE, (mod.__name__, r.path)
    app.state.store.close()


def test_the_line_service_on_a_loop_thread_answers_and_stops_cleanly(paper_pairs):
    """``serve`` runs the line service on an event loop of its own (a thread): it answers from there,
    and stopping it cancels its connections, ends the thread and closes the loop, with a client
    still connected."""
    import socket

    from eyetohand import calibrate
    from eyetohand.positioning import LoopThread

    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False)
    t = LoopThread(name="test-tcp")
    srv = LineServer(cal, "127.0.0.1", 0)

    async def start() -> None:
        await t.call(srv.start())

    asyncio.run(start())
    with socket.create_connection(("127.0.0.1", srv.port), timeout=5) as s:
        f = s.makefile("rb")
        s.sendall(b"600,900\n")
        assert f.readline() == tcp_answer(cal, b"600,900")
        assert srv.clients == 1
        t.loop.call_soon_threadsafe(srv.close)
        t.stop()
        assert not t._thread.is_alive() and t.loop.is_closed()
        assert f.readline() == b""  # the connection was closed by the stop
    t.stop()  # a second stop does nothing


@pytest.mark.parametrize(
    "options, argv, field, words",
    [
        ({"seed": -1}, ["--seed", "-1"], "seed", "must be a whole number from 0 to 4294967295, got -1"),
        ({"seed": 2**32}, ["--seed", str(2**32)], "seed", "from 0 to 4294967295, got 4294967296"),
        (
            {"particles": 1},
            ["--particles", "1"],
            "particles",
            "solver option 'n_particles' must be at least 2",
        ),
        (
            {"iterations": 0},
            ["--iterations", "0"],
            "iterations",
            "solver option 'iterations' must be a positive whole number, got 0",
        ),
        (
            {"model": "nope"},
            ["--model", "nope"],
            "model",
            "unknown model 'nope'; choose one of: auto, affine",
        ),
        (
            {"optimizer": "x"},
            ["--optimizer", "x"],
            "optimizer",
            "unknown optimizer 'x'; choose one of: linear",
        ),
        (
            {"objective": "l3"},
            ["--objective", "l3"],
            "objective",
            "unknown objective 'l3'; choose one of: l2",
        ),
    ],
)
def test_fit_options_are_refused_in_the_librarys_words_on_the_cli_and_http(
    client, tmp_path, capsys, options, argv, field, words
):
    """One rule, one set of words: a seed, swarm size or name the library refuses is refused by the
    command line (exit 2, one line) and by the API (422 naming the field) in the library's words, not
    pydantic's ("Input should be ...") and not as an internal error (a negative seed was one)."""
    body = {"name": "t", "pairs": PAIRS, "model": "homography", "optimizer": "hybrid-pso", **options}
    r = client.post("/api/calibrations", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["field"] == field and words in r.json()["error"], r.json()
    assert "Input should" not in r.json()["error"] and "Value error" not in r.json()["error"]
    base = ["calibrate", str(PAPER / "calibration_points.csv"), "--model", "homography"]
    base += ["--optimizer", "hybrid-pso", "-o", str(tmp_path / "c.json")]
    code = cli_main(base + argv)
    err = capsys.readouterr().err.strip()
    assert code == 2 and words in err and "\n" not in err, err
    assert not (tmp_path / "c.json").exists()


def test_server_limits_say_they_are_the_servers(client):
    r = client.post(
        "/api/calibrations", json={"name": "t", "pairs": PAIRS, "optimizer": "pso", "particles": 5000}
    )
    assert r.status_code == 422
    assert r.json() == {
        "error": "particles: 5000 particles is more than this server's limit of 1000",
        "field": "particles",
    }


@pytest.mark.parametrize(
    "argv, body, line, words",
    [
        (
            ["--angle", "1e308"],
            {"angles": [1e308]},
            b"600,900,a=1e308",
            "1e+308 deg is more than 1e+09 deg from 0",
        ),
        (
            ["--tool-rz-offset", "1e12"],
            {"tool_rz_offset_deg": 1e12},
            b"600,900,t=1e12",
            "1e+12 deg is more than 1e+09",
        ),
        (
            ["--angle", "10", "--symmetry", "0"],
            {"angles": [10.0], "symmetry": 0},
            b"600,900,a=10,s=0",
            "symmetry must be a whole number from 1 to 360",
        ),
    ],
)
def test_angles_are_refused_alike_on_apply_http_and_tcp(client, tmp_path, capsys, argv, body, line, words):
    """An angle whose direction is lost to rounding, a tool offset (with or without an angle) and a
    symmetry are refused by the library's rule in its words on every interface; the API names the field."""
    create(client, "a", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    path = cal.save(tmp_path / "a.json")
    assert cli_main(["apply", str(path), "--uv", "600", "900", *argv]) == 2
    assert words in capsys.readouterr().err
    r = client.post("/api/calibrations/1/image-to-robot", json={"points": [[600, 900]], **body})
    assert r.status_code == 422 and words in r.json()["error"], r.json()
    assert r.json()["field"] in ("points[0].angle", "tool_rz_offset_deg", "symmetry"), r.json()
    reply = tcp_answer(cal, line)
    assert reply.startswith(b"ERR ") and words.encode() in reply, reply


def test_image_sizes_are_refused_in_the_librarys_words(client, tmp_path, capsys):
    words = "image size must be two whole numbers of pixels W x H from 1 to 100000"
    for size, text in (((0, 5), "0x5"), ((99999999999, 5), "99999999999x5")):
        code = cli_main(
            [
                "calibrate",
                str(PAPER / "calibration_points.csv"),
                "--image-size",
                text,
                "-o",
                str(tmp_path / "c.json"),
            ]
        )
        assert code == 2 and words in capsys.readouterr().err
        r = client.post("/api/calibrations", json={"name": "i", "pairs": PAIRS, "image_size": list(size)})
        assert r.status_code == 422 and r.json()["field"] == "image_size" and words in r.json()["error"], (
            r.json()
        )


def test_a_swarm_of_too_many_iterations_is_refused():
    from eyetohand.solve.solvers import SWARM_MAX_ITERATIONS, check_optimizer

    check_optimizer("pso", "l2", {"iterations": SWARM_MAX_ITERATIONS})
    with pytest.raises(InputError, match="solver option 'iterations' must be at most 1000000, got 1000001"):
        check_optimizer("pso", "l2", {"iterations": SWARM_MAX_ITERATIONS + 1})


def test_a_word_given_twice_on_a_mapping_line_is_refused(client):
    """'a=10,a=20' took the last angle without a word; which one the robot meant is not guessed."""
    create(client, "w", model="homography", optimizer="lm")
    cal = Calibration.from_dict(client.get("/api/calibrations/1").json()["calibration"])
    assert tcp_answer(cal, b"600,900,a=10,a=20").startswith(b"ERR a given twice; send u,v")
    assert tcp_answer(cal, b"600,900,sigma,allow,sigma").startswith(b"ERR sigma given twice")
    assert tcp_answer(cal, b"600,900,angle_deg=5").startswith(b"ERR unknown word 'angle_deg=5'")
    assert not tcp_answer(cal, b"600,900,a=10,s=2,t=5,sigma,allow").startswith(b"ERR")


def test_token_on_the_command_line_warns_once(tmp_path):
    """--token T: one warning line that the token shows in ps, naming --token-file and EYETOHAND_TOKEN;
    --token-file: none."""
    from helpers import SMALL_CELL_TOML

    from eyetohand.cli.serve import TOKEN_IN_PS

    cell = tmp_path / "cell.toml"
    cell.write_text(SMALL_CELL_TOML)
    camera = ("--camera", f"sim:{cell}")
    srv = ServeProcess(tmp_path / "a", *camera, "--token", "s3cret-token")
    try:
        warned = [ln for ln in srv.out if "visible to every user" in ln]
        assert warned == [TOKEN_IN_PS + "\n"], srv.out
        assert "--token-file FILE" in TOKEN_IN_PS and "EYETOHAND_TOKEN" in TOKEN_IN_PS
    finally:
        srv.stop()
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-token\n")
    srv = ServeProcess(tmp_path / "b", *camera, "--token-file", str(token_file))
    try:
        assert not any("visible to every user" in ln for ln in srv.out), srv.out
    finally:
        srv.stop()
