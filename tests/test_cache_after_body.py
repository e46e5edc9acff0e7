"""A mapping request is answered with the calibration in force once its body has arrived, not when its
headers did (issue 40: a body sent seconds after its headers was answered 200 with a version deleted or
rolled back meanwhile). A real `eyetohand serve` process, raw sockets: the request's headers carry
``Expect: 100-continue``, so the server's ``100 Continue`` says the app has started and is waiting for
the body (what it took from the cache before is taken by then); the DELETE or the rollback goes through
another connection; then the body is sent.

Both paths: the fast path (the calibration cached: one small request) and the route (the calibration
not cached: the first request after a write; and a large body, which the fast path hands on)."""

from __future__ import annotations

import http.client
import socket

import httpx
import orjson
import pytest
from helpers import ServeProcess

POINT = [554.166, 1283.44]  # inside the paper cell's calibrated region
SHIFT_MM = 5.0


@pytest.fixture(scope="module")
def cal_dicts(paper_pairs):
    """The paper cell's calibration and one fitted on its pairs shifted SHIFT_MM in x (as files' JSON)."""
    from eyetohand import calibrate
    from eyetohand.core import PointPairs

    pairs, _ = paper_pairs
    shifted = PointPairs(pairs.uv_px, pairs.xyz_mm + [SHIFT_MM, 0.0, 0.0], pairs.ids)
    return [calibrate(p, model="homography", optimizer="lm", loo=False).to_dict() for p in (pairs, shifted)]


@pytest.fixture(scope="module")
def server(tmp_path_factory, cal_dicts):
    tmp = tmp_path_factory.mktemp("late-body")
    robot_file = tmp / "robot.json"  # what the TCP line serves (ServeProcess starts one); not used here
    robot_file.write_bytes(orjson.dumps(cal_dicts[0]))
    srv = ServeProcess(tmp / "data", "--calibration", str(robot_file))
    try:
        yield srv
    finally:
        srv.stop()


def _import(srv: ServeProcess, name: str, cal: dict) -> dict:
    r = httpx.post(srv.url + "/api/calibrations/import", json={"name": name, "calibration": cal}, timeout=30)
    assert r.status_code in (200, 201), r.text
    return r.json()


def _map_now(srv: ServeProcess, cal_id: int) -> tuple[int, float]:
    r = httpx.post(f"{srv.url}/api/calibrations/{cal_id}/image-to-robot", json={"points": [POINT]})
    assert r.status_code == 200, r.text
    return r.json()["version"], r.json()["points"][0][0]


def _late_body(srv: ServeProcess, path: str, body: bytes, meanwhile) -> tuple[int, dict]:
    """POST ``path``: the headers, then (once the server asked for the body) ``meanwhile()``, then the
    body. The answer's status and JSON."""
    with socket.create_connection(("127.0.0.1", srv.http_port), timeout=30) as s:
        s.sendall(
            (
                f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{srv.http_port}\r\n"
                f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
                "Expect: 100-continue\r\nConnection: close\r\n\r\n"
            ).encode()
        )
        head = b""
        while not head.endswith(b"\r\n\r\n"):
            got = s.recv(1)
            assert got, f"the server closed the connection before asking for the body: {head!r}"
            head += got
        assert head.startswith(b"HTTP/1.1 100 "), head
        meanwhile()
        s.sendall(body)
        resp = http.client.HTTPResponse(s)
        resp.begin()
        return resp.status, orjson.loads(resp.read())


def _body(points: int) -> bytes:
    return orjson.dumps({"points": [POINT] * points})


# (name, points): one point is the fast path's request; 5000 points (~90 KiB) the route's
SIZES = [("small", 1), ("large", 5000)]


@pytest.mark.parametrize("cached", [True, False], ids=["cached", "not-cached"])
@pytest.mark.parametrize(("size", "points"), SIZES, ids=[s for s, _ in SIZES])
def test_a_calibration_deleted_before_the_body_arrives_is_not_found(server, cal_dicts, cached, size, points):
    name = f"deleted-{size}-{cached}"
    rec = _import(server, name, cal_dicts[0])
    if cached:
        assert _map_now(server, rec["id"])[0] == 1  # now in the server's cache

    def delete() -> None:
        r = httpx.delete(f"{server.url}/api/calibrations/{rec['id']}", headers={"If-Match": rec["etag"]})
        assert r.status_code == 204, r.text

    path = f"/api/calibrations/{rec['id']}/image-to-robot"
    status, answer = _late_body(server, path, _body(points), delete)
    assert status == 404, answer
    assert answer["field"] == "id" and str(rec["id"]) in answer["error"], answer
    # and a version asked for by number is gone with it
    status, answer = _late_body(server, path + "?version=1", _body(points), lambda: None)
    assert status == 404, answer


@pytest.mark.parametrize("cached", [True, False], ids=["cached", "not-cached"])
@pytest.mark.parametrize(("size", "points"), SIZES, ids=[s for s, _ in SIZES])
def test_a_rollback_before_the_body_arrives_answers_the_version_in_force(
    server, cal_dicts, cached, size, points
):
    name = f"rolled-{size}-{cached}"
    _import(server, name, cal_dicts[0])
    rec = _import(server, name, cal_dicts[1])
    assert rec["version"] == 2
    if cached:
        version, _ = _map_now(server, rec["id"])
        assert version == 2

    def rollback() -> None:
        r = httpx.post(
            f"{server.url}/api/calibrations/{rec['id']}/rollback",
            json={"version": 1},
            headers={"If-Match": rec["etag"]},
        )
        assert r.status_code == 200 and r.json()["version"] == 3, r.text

    path = f"/api/calibrations/{rec['id']}/image-to-robot"
    status, answer = _late_body(server, path, _body(points), rollback)
    assert status == 200, answer
    assert answer["version"] == 3, answer
    _, x_v1 = _map_now(server, rec["id"])
    assert {p[0] for p in answer["points"]} == {x_v1}  # version 1's numbers (version 2's are 5 mm apart)
    status, v2 = _late_body(server, path + "?version=2", _body(1), lambda: None)
    assert status == 200 and v2["points"][0][0] == pytest.approx(x_v1 + SHIFT_MM, abs=0.05), v2
