"""The one-point HTTP mapping call's short way (``routes.mapping.FastMap``, issue 29) answers exactly
what the FastAPI route answers — status, headers and bytes — for what it takes, and hands everything
else to the route: options, errors, versions, unknown ids, a body too large, an uncached calibration."""

from __future__ import annotations

import csv

import orjson
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER

from eyetohand.server.app import create_app
from eyetohand.server.routes import mapping


def _records(name: str) -> list[dict]:
    with open(PAPER / name, newline="") as fh:
        return [{k: (v if k == "id" else float(v)) for k, v in r.items()} for r in csv.DictReader(fh)]


def _app(data, fast: bool):
    app = create_app(data)
    if not fast:  # the same app without the short way (the stack is built on the first request)
        app.user_middleware = [m for m in app.user_middleware if m.cls is not mapping.FastMap]
    return app


@pytest.fixture(scope="module")
def clients(tmp_path_factory):
    data = tmp_path_factory.mktemp("fastmap")
    seed = TestClient(create_app(data))
    body = {
        "name": "c",
        "pairs": _records("calibration_points.csv"),
        "model": "homography",
        "optimizer": "lm",
    }
    assert seed.post("/api/calibrations", json=body).status_code == 201
    seed.app.state.jobs.shutdown()
    seed.app.state.store.close()
    fast, slow = _app(data, True), _app(data, False)
    with TestClient(fast) as f, TestClient(slow) as s:
        yield f, s
    for app in (fast, slow):
        app.state.jobs.shutdown()
        app.state.store.close()


INSIDE = [715.1, 757.0]
BODIES = [
    {"points": [INSIDE]},  # the short way
    {"points": [INSIDE, [700.0, 760.0]]},
    {"points": [[715, 757]]},
    {"points": [INSIDE], "sigma": False},
    {"points": [INSIDE], "z": 0.0},
    {"points": [INSIDE], "angles": [30.0], "symmetry": 2},
    {"points": [INSIDE], "units": "m", "angle_units": "rad"},
    {"points": [[5000.0, 5000.0]]},  # outside: 422
    {"points": [[5000.0, 5000.0]], "allow_outside": True},
    {"points": [[0.0, None]]},
    {"points": [INSIDE], "sigma": "yes"},
    {"points": [INSIDE], "unknown": 1},
    {"points": []},
    {"points": [[1.0]]},
    {"pionts": [INSIDE]},
]


@pytest.mark.parametrize("i", range(len(BODIES)))
@pytest.mark.parametrize(
    "path", ["/api/calibrations/1/image-to-robot", "/api/calibrations/1/image-to-robot?version=1"]
)
def test_the_short_way_answers_what_the_route_answers(clients, i, path):
    fast, slow = clients
    body = orjson.dumps(BODIES[i])
    headers = {"content-type": "application/json"}
    for _ in range(2):  # the first call caches the calibration, the second takes the short way
        a, b = fast.post(path, content=body, headers=headers), slow.post(path, content=body, headers=headers)
        assert (a.status_code, a.content) == (b.status_code, b.content)
        assert sorted(a.headers.items()) == sorted(b.headers.items())


@pytest.mark.parametrize(
    "raw",
    [
        b'{"points": [[715.1, 757.0]], "points": [[1, 2]]}',  # a key twice: 400
        b'{"points": [[715.1, 757.0]]',  # not JSON
        b'{"points": [[1e400, 0]]}',
        b'{"points": [[NaN, 0]]}',
    ],
)
def test_malformed_bodies_get_the_routes_words(clients, raw):
    fast, slow = clients
    path = "/api/calibrations/1/image-to-robot"
    headers = {"content-type": "application/json"}
    fast.post(path, content=b'{"points": [[715.1, 757.0]]}', headers=headers)
    a, b = fast.post(path, content=raw, headers=headers), slow.post(path, content=raw, headers=headers)
    assert a.status_code >= 400 and (a.status_code, a.content) == (b.status_code, b.content)


@pytest.mark.parametrize("cal", ["2", "01", "0", "-1", str(2**62 + 1), "x"])
def test_other_ids_are_the_routes(clients, cal):
    fast, slow = clients
    path = f"/api/calibrations/{cal}/image-to-robot"
    body = orjson.dumps({"points": [INSIDE]})
    headers = {"content-type": "application/json"}
    a, b = fast.post(path, content=body, headers=headers), slow.post(path, content=body, headers=headers)
    assert (a.status_code, a.content) == (b.status_code, b.content)
    assert a.status_code == (200 if cal == "01" else 404 if cal == "2" else 422)


def test_the_short_way_is_taken(clients, monkeypatch):
    """A cached calibration's one-point call does not reach the route (whose handler would count)."""
    fast, _ = clients
    path = "/api/calibrations/1/image-to-robot"
    body = orjson.dumps({"points": [INSIDE]})
    headers = {"content-type": "application/json"}
    assert fast.post(path, content=body, headers=headers).status_code == 200
    calls = []
    real = mapping.parsed  # the route's parse of the body it read

    async def counted(body):
        calls.append(1)
        return await real(body)

    monkeypatch.setattr(mapping, "parsed", counted)
    assert fast.post(path, content=body, headers=headers).status_code == 200
    assert calls == []
    bad = orjson.dumps({"points": [[5000.0, 5000.0]]})
    assert fast.post(path, content=bad, headers=headers).status_code == 422
    assert calls == [1]  # a refusal is the route's
