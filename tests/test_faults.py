"""Fault injection on the service (loopback only, each test bounded in time): kill -9 during writes,
a database write lock held by another process, a write that hits a file-size limit, a flood of idle
TCP connections, hostile input at the API, and a delete racing cache fills."""

from __future__ import annotations

import asyncio
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, ServeProcess, records

from eyetohand.positioning import LineServer
from eyetohand.server.app import create_app
from eyetohand.server.storage import DB_NAME, Store

PAIRS = records(PAPER / "calibration_points.csv")


def seed(data: Path, n: int = 1) -> None:
    app = create_app(data)
    with TestClient(app) as c:
        for k in range(n):
            r = c.post("/api/calibrations", json={"name": f"cal {k}", "pairs": PAIRS, "model": "homography"})
            assert r.status_code == 201, r.text
    app.state.store.close()


def start_serve(data: Path, *extra: str, preexec=None) -> ServeProcess:
    """`eyetohand serve` as a subprocess on loopback (HTTP, and TCP with calibration 'cal 0')."""
    return ServeProcess(data, "--calibration", "cal 0", *extra, log_level="error", preexec=preexec)


@pytest.mark.serial  # counts the writes acknowledged in 0.8-1.4 s: runs alone (tests/conftest.py)
@pytest.mark.long
def test_kill_9_during_writes_loses_no_acknowledged_change(tmp_path):
    data = tmp_path / "data"
    seed(data)
    acked: set[int] = set()
    for cycle in range(3):
        srv = start_serve(data)
        stop = threading.Event()

        def writer(srv=srv, stop=stop) -> None:
            with httpx.Client(base_url=srv.url, timeout=10) as c:
                while not stop.is_set():
                    try:
                        r = c.post("/api/calibrations/1/rollback", json={"version": 1})
                    except httpx.HTTPError:
                        return  # the server died under us: that request was never acknowledged
                    if r.status_code == 200:
                        acked.add(r.json()["version"])
                    else:
                        assert r.status_code == 503 and r.headers["Retry-After"], r.text

        threads = [threading.Thread(target=writer) for _ in range(4)]
        for t in threads:
            t.start()
        time.sleep(0.8 + 0.3 * cycle)
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(timeout=10)
        stop.set()
        for t in threads:
            t.join(timeout=15)
    assert len(acked) > 10
    store = Store(data)
    try:
        assert store.integrity_check() == "ok"
        stored = {v.version for v in store.versions(1)}
        assert acked <= stored, sorted(acked - stored)[:5]
        assert stored == set(range(1, max(stored) + 1))  # no hole, no half-written version
    finally:
        store.close()


HOLD_LOCK = """
import sqlite3, sys, time
db = sqlite3.connect(sys.argv[1], isolation_level=None)
db.execute("BEGIN IMMEDIATE")
db.execute("UPDATE calibrations SET updated_utc = updated_utc")
print("locked", flush=True)
time.sleep(float(sys.argv[2]))
db.execute("COMMIT")
"""


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
@pytest.mark.long
def test_a_foreign_write_lock_gives_503_while_mapping_keeps_answering(tmp_path):
    data = tmp_path / "data"
    seed(data)
    srv = start_serve(data, "--db-wait", "1")
    try:
        with httpx.Client(base_url=srv.url, timeout=10) as c:  # warm the cache of calibration 1
            r = c.post("/api/calibrations/1/image-to-robot", json={"points": [[600, 900]]})
            assert r.status_code == 200
        holder = subprocess.Popen(
            [sys.executable, "-c", HOLD_LOCK, str(data / DB_NAME), "4.5"], stdout=subprocess.PIPE, text=True
        )
        assert holder.stdout.readline().strip() == "locked"
        t_lock = time.monotonic()
        write: dict = {}

        def do_write() -> None:
            t0 = time.monotonic()
            r = httpx.post(srv.url + "/api/calibrations/1/rollback", json={"version": 1}, timeout=30)
            write.update(
                status=r.status_code,
                body=r.json(),
                retry=r.headers.get("Retry-After"),
                seconds=time.monotonic() - t0,
                ctype=r.headers["content-type"],
            )

        wt = threading.Thread(target=do_write)
        wt.start()
        http_ms, tcp_ms = [], []
        with (
            httpx.Client(base_url=srv.url, timeout=10) as c,
            socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=10) as s,
        ):
            f = s.makefile("rb")
            while time.monotonic() - t_lock < 3.5:  # the lock is held 4.5 s (the write waits 1 s of it)
                t0 = time.perf_counter()
                r = c.post("/api/calibrations/1/image-to-robot", json={"points": [[600, 900]]})
                http_ms.append((time.perf_counter() - t0) * 1e3)
                assert r.status_code == 200
                t0 = time.perf_counter()
                s.sendall(b"600,900\n")
                assert f.readline().count(b",") == 2
                tcp_ms.append((time.perf_counter() - t0) * 1e3)
        wt.join(timeout=30)
        holder.wait(timeout=10)
        print(
            f"under a foreign write lock: HTTP mapping p99 {np.percentile(http_ms, 99):.1f} ms "
            f"(n={len(http_ms)}), TCP p99 {np.percentile(tcp_ms, 99):.1f} ms; write {write}"
        )
        assert write["status"] == 503 and write["ctype"] == "application/json", write
        assert write["retry"] and int(write["retry"]) >= 1 and "busy" in write["body"]["error"]
        assert write["seconds"] < 3.0  # the bounded wait (1 s here), not the lock's 4.5 s
        assert np.percentile(http_ms, 99) < 50 and np.percentile(tcp_ms, 99) < 50
        r = httpx.post(srv.url + "/api/calibrations/1/rollback", json={"version": 1}, timeout=10)
        assert r.status_code == 200  # the lock is gone: writes work again
    finally:
        srv.stop()


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
@pytest.mark.long
def test_a_huge_body_is_refused_while_the_robot_keeps_being_served(tmp_path):
    """A 63 MiB body of pairs is refused before it is parsed (413 JSON), and TCP answers meanwhile."""
    data = tmp_path / "data"
    seed(data)
    srv = start_serve(data)
    try:
        body = b'{"pairs": [' + b",".join([b'{"u": 1.5, "v": 2.5, "x": 3.5, "y": 4.5}'] * 1_620_000) + b"]}"
        assert len(body) > 63 * 2**20
        result: dict = {}

        def post() -> None:
            t0 = time.monotonic()
            try:
                r = httpx.post(
                    srv.url + "/api/calibrations",
                    content=body,
                    timeout=60,
                    headers={"Content-Type": "application/json"},
                )
                result.update(status=r.status_code, ctype=r.headers.get("content-type", ""))
            except httpx.HTTPError as exc:  # the server may close the connection after its 413
                result.update(status=None, error=str(exc))
            result["seconds"] = time.monotonic() - t0

        t = threading.Thread(target=post)
        tcp_ms = []
        with socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=10) as s:
            f = s.makefile("rb")
            t.start()
            t_end = time.monotonic() + 2.0
            while t.is_alive() or time.monotonic() < t_end:
                t0 = time.perf_counter()
                s.sendall(b"600,900\n")
                assert f.readline().count(b",") == 2
                tcp_ms.append((time.perf_counter() - t0) * 1e3)
                if time.monotonic() > t_end + 30:
                    break
        t.join(timeout=60)
        print(f"63 MiB body: {result}; TCP p99 {np.percentile(tcp_ms, 99):.1f} ms (n={len(tcp_ms)})")
        assert result.get("status") in (413, None), result
        if result.get("status") == 413:
            assert result["ctype"].startswith("application/json")
        assert np.percentile(tcp_ms, 99) < 50
    finally:
        srv.stop()


def _limit_file_size(limit: int):
    def pre() -> None:
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return pre


def test_a_write_past_the_file_size_limit_fails_cleanly(tmp_path):
    data = tmp_path / "data"
    seed(data, 2)
    before = Store(data)
    want = [(r.name, r.current_version) for r, _ in before.list()]
    before.close()
    size = (data / DB_NAME).stat().st_size
    srv = start_serve(data, preexec=_limit_file_size(size + 4096))
    try:  # ~100 KB to store (pairs, and the calibration's copy of them): more than the 4 KiB left
        big = [
            {**p, "id": f"{k}-{p['id']}-{'x' * 40}", "u": p["u"] + 0.37 * k, "x": p["x"] + 0.05 * k}
            for k in range(20)
            for p in PAIRS
        ]
        body = {"name": "big", "pairs": big, "model": "homography"}
        r = httpx.post(srv.url + "/api/calibrations", json=body, timeout=60)
        assert r.status_code in (503, 507), r.text
        assert r.headers["content-type"] == "application/json"
        assert "nothing was changed" in r.json()["error"]
        ok = httpx.post(
            srv.url + "/api/calibrations/1/image-to-robot", json={"points": [[600, 900]]}, timeout=10
        )
        assert ok.status_code == 200  # the service is still up and serving
    finally:
        srv.stop()
    after = Store(data)
    try:
        assert after.integrity_check() == "ok"
        assert [(r.name, r.current_version) for r, _ in after.list()] == want
    finally:
        after.close()


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_idle_connections_from_another_address_do_not_lock_the_robot_out(paper_pairs):
    from eyetohand import calibrate

    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False)

    async def run() -> None:
        srv = LineServer(cal, "127.0.0.1", 0)
        await srv.start()
        flood = []
        try:
            for _ in range(300):
                s = socket.socket()
                s.setblocking(False)
                s.bind(("127.0.0.2", 0))
                try:
                    s.connect(("127.0.0.1", srv.port))
                except BlockingIOError:
                    pass
                flood.append(s)
            await asyncio.sleep(0.5)  # let the server accept (or refuse) them all
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            for i in range(20):
                writer.write(f"{500 + i},900\n".encode())
                reply = await asyncio.wait_for(reader.readline(), 5)
                assert reply.count(b",") == 2, reply
            writer.close()
            assert srv.per_peer.get("127.0.0.2", 0) <= srv.max_per_peer
        finally:
            for s in flood:
                s.close()
            srv.close()

    asyncio.run(asyncio.wait_for(run(), 30))
