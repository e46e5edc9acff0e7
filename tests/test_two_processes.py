"""Two real `eyetohand serve` processes on one data folder (the default SQLite store), and on one
PostgreSQL database: whatever one writes, every interface of the other maps with the version in force
in the store (issue 40: A's HTTP answered the old version indefinitely, 500 mm away from its TCP line;
after a delete, A's mapping still answered 200 with the deleted version).

A serves HTTP (the fast path: one point; the route: 2500 points, a body the fast path hands on), the TCP
line, Modbus (pymodbus's client) and OPC UA (asyncua's client) with ``--calibration cell``; B, on the
same store, posts a version 500 mm away in x, then rolls back, then deletes. After each write every
interface of A is polled until it answers with the new state, under a deadline (no fixed sleeps); the
delays measured are printed (``-s``)."""

from __future__ import annotations

import asyncio
import math
import socket
import threading
import time

import httpx
import orjson
import pytest
from helpers import PAPER, ServeProcess, records
from pymodbus.client import ModbusTcpClient

from eyetohand import calibrate
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import Status
from eyetohand.positioning import registers as R
from eyetohand.server import open_store
from eyetohand.server.routes.mapping import INLINE_BYTES

SHIFT_MM = 500.0
# the deadline: the HTTP cache's follower and the line service poll every 0.25 s (measured: 0.1-0.6 s);
# the rest is room for a loaded machine (2 cores shared by the suite)
FOLLOW_S = 2.5
MANY = 2500  # points of the route's request (~90 KiB: over the fast path's 64 KiB)


@pytest.fixture(scope="module")
def cal_dicts():
    """The paper cell's calibration and one fitted on its pairs SHIFT_MM away in x."""
    pairs = pairs_from_records(records(PAPER / "calibration_points.csv"))
    shifted = pairs_from_records(
        [{**r, "x": r["x"] + SHIFT_MM} for r in records(PAPER / "calibration_points.csv")]
    )
    return [calibrate(p, model="homography", optimizer="lm", loo=False).to_dict() for p in (pairs, shifted)]


def _port(srv: ServeProcess, prefix: str) -> int:
    line = next(x for x in srv.out if x.startswith(prefix))
    return int(line.split()[1].rsplit(":", 1)[1].split("/")[0])


class LoopThread:
    """An asyncio loop in a thread (asyncua's client lives there); :meth:`run` waits for a coroutine."""

    def __init__(self):
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro, timeout_s: float = 15):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


class Interfaces:
    """A's interfaces, each asked the same image point: what calibration answers it (version, x mm),
    or the refusal's words."""

    def __init__(self, srv: ServeProcess, uv: tuple[float, float], cal_id: int):
        from asyncua import Client

        self.srv, self.uv, self.cal_id = srv, uv, cal_id
        self.http = httpx.Client(base_url=srv.url, timeout=30, headers={"Content-Type": "application/json"})
        self.tcp = socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=10)
        self.tcp_in = self.tcp.makefile("rb")
        self.modbus = ModbusTcpClient("127.0.0.1", port=_port(srv, "Modbus:"), timeout=5)
        assert self.modbus.connect()
        self._req_id = 0
        self.ua_loop = LoopThread()
        url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]
        self.ua = Client(url, timeout=10)
        self.ua_loop.run(self.ua.connect())
        self.ns = self.ua_loop.run(self.ua.get_namespace_index("urn:eyetohand"))
        self.ua_cal = self.ua_loop.run(self.ua.nodes.root.get_child(["0:Objects", f"{self.ns}:Calibration"]))

    def close(self) -> None:
        self.ua_loop.run(self.ua.disconnect())
        self.ua_loop.close()
        self.modbus.close()
        self.tcp.close()
        self.http.close()

    def _http(self, n: int) -> tuple[int, float] | str:
        body = orjson.dumps({"points": [list(self.uv)] * n})
        assert (len(body) > INLINE_BYTES) == (n == MANY)  # the fast path hands the large one on
        r = self.http.post(f"/api/calibrations/{self.cal_id}/image-to-robot", content=body)
        if r.status_code != 200:
            return f"{r.status_code} {r.json()['error']}"
        answer = r.json()
        assert len({p[0] for p in answer["points"]}) == 1  # one calibration for the whole request
        return answer["version"], answer["points"][0][0]

    def http_fast(self):
        return self._http(1)

    def http_route(self):
        return self._http(MANY)

    def tcp_line(self):
        u, v = self.uv
        self.tcp.sendall(f"VERSION\n{u!r},{v!r}\n".encode())
        version, mapped = (self.tcp_in.readline().decode().strip() for _ in range(2))
        if mapped.startswith("ERR"):
            return mapped
        assert version.startswith("OK "), version
        return int(version.split(",")[1]), float(mapped.split()[-1].split(",")[0])

    def modbus_registers(self):
        self._req_id += 1
        regs = R.encode_request(R.Request(self._req_id, *self.uv, None, None, False), "big")
        assert not self.modbus.write_registers(1, regs[1:], device_id=1).isError()
        assert not self.modbus.write_registers(0, [self._req_id], device_id=1).isError()
        deadline = time.monotonic() + 5
        while True:
            got = self.modbus.read_holding_registers(
                R.RESULT_ID, count=R.RESULT_END - R.RESULT_ID, device_id=1
            )
            assert not got.isError(), got
            out = R.decode_result(list(got.registers), "big")
            if out["request_id"] == self._req_id:
                break
            assert time.monotonic() < deadline, f"Modbus request {self._req_id} never answered: {out}"
        if out["status"] != Status.OK:
            return f"status {out['status']}"
        return out["version"], out["x"]

    def opcua(self):
        from asyncua import ua

        async def ask():
            version = await (await self.ua_cal.get_child(f"{self.ns}:Version")).read_value()
            try:
                x = (await self.ua_cal.call_method(f"{self.ns}:ImageToRobot", *self.uv, math.nan))[0]
            except ua.UaStatusCodeError as exc:
                return f"{type(exc).__name__}"
            return version, x

        return self.ua_loop.run(ask())

    def every(self) -> dict:
        return {
            "http fast path": self.http_fast,
            "http route": self.http_route,
            "tcp": self.tcp_line,
            "modbus": self.modbus_registers,
            "opcua": self.opcua,
        }


def _follow(a: Interfaces, want, what: str) -> dict[str, float]:
    """Poll every interface of A until ``want(answer)`` holds for each; the seconds each took."""
    t0 = time.monotonic()
    pending = a.every()
    took: dict[str, float] = {}
    last: dict[str, object] = {}
    while pending:
        for name, ask in list(pending.items()):
            last[name] = got = ask()
            if want(got):
                took[name] = time.monotonic() - t0
                del pending[name]
        assert time.monotonic() - t0 < FOLLOW_S, f"{what}: not followed in {FOLLOW_S} s by {last}"
    print(f"{what}: " + ", ".join(f"{k} {v:.3f} s" for k, v in took.items()))
    return took


@pytest.mark.parametrize("kind", ["data folder", "postgresql"])
@pytest.mark.long
def test_every_interface_of_a_follows_what_b_writes(tmp_path, cal_dicts, kind, request):
    """On one ``--data`` folder (the default SQLite store), and on one PostgreSQL database (``--store``:
    the plant's shared store; each process has its own data folder there)."""
    data = tmp_path / "data"
    where = ["--store", request.getfixturevalue("pg_url")] if kind == "postgresql" else []
    store = open_store(where[1] if where else data, create=True)
    try:
        pairs = pairs_from_records(records(PAPER / "calibration_points.csv")).to_records()
        cid = store.create("cell", {"source": "import"}, cal_dicts[0], pairs, None).id
    finally:
        store.close()
    serving = [*where, "--calibration", "cell"]
    a = ServeProcess(data, *serving, "--modbus", "127.0.0.1:0", "--opcua", "127.0.0.1:0")
    b = ServeProcess(data if not where else tmp_path / "data-b", *serving)
    probe = None
    try:
        from eyetohand.calibration import Calibration

        uv = tuple(float(c) for c in Calibration.from_dict(cal_dicts[0]).region.hull_px.mean(axis=0))
        probe = Interfaces(a, uv, cid)
        first = {name: ask() for name, ask in probe.every().items()}
        versions = {v[0] for v in first.values() if isinstance(v, tuple)}
        xs = [v[1] for v in first.values() if isinstance(v, tuple)]
        assert versions == {1} and len(xs) == 5, first
        x1 = xs[0]
        assert max(xs) - min(xs) < 0.001, first  # every interface maps alike (Modbus: to 1 µm)

        with httpx.Client(base_url=b.url, timeout=30) as office:
            r = office.post("/api/calibrations/import", json={"name": "cell", "calibration": cal_dicts[1]})
            assert r.status_code == 200 and r.json()["version"] == 2, r.text
            _follow(
                probe,
                lambda got: isinstance(got, tuple) and got[0] == 2 and abs(got[1] - x1 - SHIFT_MM) < 0.5,
                "new version",
            )
            r = office.post(
                f"/api/calibrations/{cid}/rollback",
                json={"version": 1},
                headers={"If-Match": r.json()["etag"]},
            )
            assert r.status_code == 200 and r.json()["version"] == 3, r.text
            _follow(
                probe,
                lambda got: isinstance(got, tuple) and got[0] == 3 and abs(got[1] - x1) < 0.001,
                "rollback",
            )
            r = office.delete(f"/api/calibrations/{cid}", headers={"If-Match": r.json()["etag"]})
            assert r.status_code == 204, r.text
            took = _follow(probe, lambda got: isinstance(got, str), "delete")
            gone = {name: ask() for name, ask in probe.every().items()}
        assert gone["http fast path"] == gone["http route"], gone
        assert gone["http fast path"].startswith("404 ") and str(cid) in gone["http fast path"], gone
        assert gone["tcp"] == "ERR calibration 'cell' was deleted", gone
        assert gone["modbus"] == f"status {Status.NO_CALIBRATION}", gone
        assert gone["opcua"] == "BadInvalidState", gone
        assert set(took) == set(probe.every())
    finally:
        if probe is not None:
            probe.close()
        b.stop()
        a.stop()
