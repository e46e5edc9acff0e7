"""Load on the positioning service, on loopback only: `python benchmarks/bench_server.py`.

1. HTTP: 8 concurrent clients × 500 single-point image-to-robot requests (keep-alive), no error
   allowed; p50 / p99 / max latency and throughput.
2. TCP line service: 8 concurrent clients × 500 lines, one at a time; p50 / p99 latency.
3. One request with 1 000 000 points: time and the server's peak memory (VmHWM); then
   1 000 001 points, which must get a clean 413.

The server is a real `eyetohand serve` subprocess (uvicorn) on free 127.0.0.1 ports with a fresh
data folder; clients run in this process (threads for HTTP, asyncio for TCP), so on a small
machine they share the cores with the server: the latencies are end to end, client included.
"""

from __future__ import annotations

import asyncio
import csv
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import orjson

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "examples" / "paper"
CLIENTS = 8
REQUESTS = 500
BIG = 1_000_000


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def records(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: (v if k == "id" else float(v)) for k, v in r.items()} for r in csv.DictReader(fh)]


def seed_database(data: Path) -> None:
    from fastapi.testclient import TestClient

    from eyetohand.server.app import create_app

    app = create_app(data)
    r = TestClient(app).post(
        "/api/calibrations",
        json={
            "name": "bench",
            "pairs": records(PAPER / "calibration_points.csv"),
            "check": records(PAPER / "check_points.csv"),
            "model": "paper",
            "optimizer": "hybrid-pso",
            "seed": 0,
        },
    )
    assert r.status_code == 201, r.text
    app.state.jobs.shutdown()
    app.state.store.close()


def wait_http(url: str, proc: subprocess.Popen, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"server exited with {proc.returncode}")
        try:
            if httpx.get(url + "/api/health", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.1)
    raise SystemExit("server did not start")


def pct(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"p50 {np.percentile(a, 50):.2f} ms  p99 {np.percentile(a, 99):.2f} ms  max {a.max():.2f} ms"


def bench_http(url: str) -> None:
    lat: list[list[float]] = [[] for _ in range(CLIENTS)]
    errors: list[str] = []
    start = threading.Barrier(CLIENTS)

    def client(k: int) -> None:
        rng = np.random.default_rng(k)
        with httpx.Client(base_url=url, timeout=30) as c:
            start.wait()
            for _ in range(REQUESTS):
                body = {"points": [[float(rng.uniform(300, 1300)), float(rng.uniform(300, 1500))]]}
                t0 = time.perf_counter()
                r = c.post("/api/calibrations/1/image-to-robot", json=body)
                lat[k].append((time.perf_counter() - t0) * 1e3)
                if r.status_code != 200 or len(r.json()["points"][0]) != 3:
                    errors.append(f"{r.status_code} {r.text[:100]}")

    t0 = time.perf_counter()
    threads = [threading.Thread(target=client, args=(k,)) for k in range(CLIENTS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    n = CLIENTS * REQUESTS
    print(
        f"HTTP  {CLIENTS} clients x {REQUESTS} single-point requests: {n} ok, {len(errors)} errors, "
        f"{wall:.1f} s, {n / wall:.0f} req/s"
    )
    print(f"      latency {pct([x for ls in lat for x in ls])}")
    if errors:
        raise SystemExit(f"errors: {errors[:3]}")


async def bench_tcp(port: int) -> None:
    async def client(k: int) -> list[float]:
        rng = np.random.default_rng(100 + k)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        out = []
        for _ in range(REQUESTS):
            line = f"{rng.uniform(300, 1300)!r},{rng.uniform(300, 1500)!r}\n".encode()
            t0 = time.perf_counter()
            writer.write(line)
            await writer.drain()
            reply = await reader.readline()
            out.append((time.perf_counter() - t0) * 1e3)
            if reply.startswith(b"ERR") or reply.count(b",") != 2:
                raise SystemExit(f"TCP error: {reply!r}")
        writer.close()
        await writer.wait_closed()
        return out

    t0 = time.perf_counter()
    lat = await asyncio.gather(*(client(k) for k in range(CLIENTS)))
    wall = time.perf_counter() - t0
    n = CLIENTS * REQUESTS
    print(
        f"TCP   {CLIENTS} clients x {REQUESTS} lines: {n} ok, 0 errors, {wall:.1f} s, {n / wall:.0f} lines/s"
    )
    print(f"      latency {pct([x for ls in lat for x in ls])}")


def vm_hwm_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def bench_big(url: str, pid: int) -> None:
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 2000, (BIG, 2))
    body = orjson.dumps({"points": uv}, option=orjson.OPT_SERIALIZE_NUMPY)
    before = vm_hwm_mib(pid)
    t0 = time.perf_counter()
    r = httpx.post(
        url + "/api/calibrations/1/image-to-robot",
        content=body,
        headers={"Content-Type": "application/json"},
        timeout=300,
    )
    wall = time.perf_counter() - t0
    assert r.status_code == 200, r.text[:300]
    n = len(orjson.loads(r.content)["points"])
    print(
        f"BIG   {BIG} points in one request ({len(body) / 2**20:.1f} MiB in, "
        f"{len(r.content) / 2**20:.1f} MiB out): {r.status_code}, {n} points, {wall:.1f} s; "
        f"server peak RSS {before:.0f} -> {vm_hwm_mib(pid):.0f} MiB"
    )
    body = b'{"points": [' + b",".join([b"[1,2]"] * (BIG + 1)) + b"]}"
    r = httpx.post(
        url + "/api/calibrations/1/image-to-robot",
        content=body,
        headers={"Content-Type": "application/json"},
        timeout=300,
    )
    print(f"      {BIG + 1} points: {r.status_code} {r.json()}")
    assert r.status_code == 413
    body = b'{"points": [' + b",".join([b"[1,2]"] * (14 * 2**20)) + b"]}"
    r = httpx.post(
        url + "/api/calibrations/1/image-to-robot",
        content=body,
        headers={"Content-Type": "application/json"},
        timeout=300,
    )
    print(f"      {len(body) / 2**20:.0f} MiB body: {r.status_code} {r.json()}")
    assert r.status_code == 413


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="eyetohand-bench-") as tmp:
        data = Path(tmp) / "data"
        seed_database(data)
        port, tcp_port = free_port(), free_port()
        url = f"http://127.0.0.1:{port}"
        cmd = [
            sys.executable,
            "-m",
            "eyetohand.cli",
            "serve",
            "--port",
            str(port),
            "--data",
            str(data),
            "--tcp",
            f"127.0.0.1:{tcp_port}",
            "--calibration",
            "bench",
            "--log-level",
            "warning",
        ]
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            wait_http(url, proc)
            print(
                f"server pid {proc.pid}: eyetohand serve on 127.0.0.1:{port}, TCP 127.0.0.1:{tcp_port}; "
                f"{os.cpu_count()} cores shared with the clients"
            )
            bench_http(url)
            asyncio.run(bench_tcp(tcp_port))
            bench_big(url, proc.pid)
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
