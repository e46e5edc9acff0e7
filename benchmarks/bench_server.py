"""The positioning service against minimal peers, on loopback only: `python benchmarks/bench_server.py`.

Three servers run as subprocesses on free 127.0.0.1 ports, started in this run: the real
`eyetohand serve` (uvicorn, HTTP and the TCP line service, a fresh data folder), and two peers doing
the same guarded `Calibration.map` call with nothing around it (`benchmarks/peer_http.py`, a minimal
FastAPI app with orjson both ways; `benchmarks/peer_tcp.py`, a minimal asyncio line server). Each
measure alternates between ours and its peer in rounds (same points, same order) and prints the ratio:

1. HTTP, one client: p50 latency of single-point requests (keep-alive; goal ≤ 1.5× the peer).
2. HTTP, 8 clients at once: throughput (goal ≥ 0.6× the peer) and p50.
3. TCP line, one client and 8 clients: p50 (goal ≤ 2× the peer).
4. One request with 1 000 000 points: time (goal ≤ 1.2× the peer) and the server's peak memory above
   its level before (VmHWM; goal ≤ 4× the raw arrays: 10⁶ × (2 in + 3 out + 1 sigma) float64 + 10⁶
   bools); then 1 000 001 points and an 84 MiB body, which must get a clean 413.

The HTTP clients are raw sockets (one small loop per request, threads for 8 clients) and the TCP ones
asyncio streams, in this process: on a small machine they share the cores with the servers, so the
latencies are end to end, client included. `--rounds N` (default 3) sets the repeats.
"""

from __future__ import annotations

import argparse
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

import numpy as np
import orjson

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
PAPER = ROOT / "examples" / "paper"
CLIENTS = 8
ONE_REQUESTS = 300  # per round, one client
MANY_REQUESTS = 150  # per client per round, 8 clients
BIG = 1_000_000
MAP_PATH = "/api/calibrations/1/image-to-robot"


def serve_command(data: Path, ports: dict[str, int]) -> list[str]:
    """``eyetohand serve`` of the seeded calibration "bench" (:func:`seed_database`) on 127.0.0.1:
    the workbench on ``ports["http"]`` and each of the line, Modbus and OPC UA services ``ports`` has
    (keys "tcp", "modbus", "opcua"; other keys are ignored)."""
    cmd = [sys.executable, "-m", "eyetohand.cli", "serve", "--port", str(ports["http"]), "--data", str(data)]
    cmd += ["--calibration", "bench", "--log-level", "warning"]
    for flag in ("tcp", "modbus", "opcua"):
        if flag in ports:
            cmd += [f"--{flag}", f"127.0.0.1:{ports[flag]}"]
    return cmd


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def records(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: (v if k == "id" else float(v)) for k, v in r.items()} for r in csv.DictReader(fh)]


def seed_database(data: Path, cal_file: Path) -> None:
    from fastapi.testclient import TestClient

    from eyetohand.calibration.file import Calibration
    from eyetohand.server.app import create_app

    app = create_app(data)
    c = TestClient(app)
    r = c.post(
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
    Calibration.from_dict(c.get("/api/calibrations/1").json()["calibration"]).save(cal_file)
    app.state.jobs.shutdown()
    app.state.store.close()


class Http:
    """One keep-alive HTTP/1.1 connection on a raw socket (the least client cost per request)."""

    def __init__(self, port: int):
        self.port = port
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=300)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""

    def post(self, path: str, body: bytes) -> tuple[int, bytes]:
        head = (
            f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{self.port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
        ).encode()
        self.sock.sendall(head + body)
        while b"\r\n\r\n" not in self.buf:
            self._more()
        head_b, _, self.buf = self.buf.partition(b"\r\n\r\n")
        lines = head_b.split(b"\r\n")
        status = int(lines[0].split()[1])
        fields = {k.strip().lower(): v.strip() for k, _, v in (x.partition(b":") for x in lines[1:])}
        if fields.get(b"transfer-encoding", b"").lower() == b"chunked":
            return status, self._chunked()
        length = int(fields[b"content-length"])
        while len(self.buf) < length:
            self._more()
        out, self.buf = self.buf[:length], self.buf[length:]
        return status, out

    def _chunked(self) -> bytes:
        parts = []
        while True:
            while b"\r\n" not in self.buf:
                self._more()
            size_b, _, self.buf = self.buf.partition(b"\r\n")
            size = int(size_b.split(b";")[0], 16)
            while len(self.buf) < size + 2:
                self._more()
            parts.append(self.buf[:size])
            self.buf = self.buf[size + 2 :]
            if size == 0:
                return b"".join(parts)

    def _more(self) -> None:
        chunk = self.sock.recv(1 << 20)
        if not chunk:
            raise ConnectionError("server closed the connection")
        self.buf += chunk

    def close(self) -> None:
        self.sock.close()


def wait_port(port: int, proc: subprocess.Popen, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"server {proc.args} exited with {proc.returncode}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.1)
    raise SystemExit("server did not start")


INSIDE: np.ndarray = np.zeros((0, 2))  # points inside the calibrated region, set in main()


def inside_points(cal_file: Path) -> np.ndarray:
    from eyetohand.calibration.file import Calibration

    cal = Calibration.load(cal_file)
    lo, hi = cal.region.hull_px.min(axis=0), cal.region.hull_px.max(axis=0)
    uv = np.random.default_rng(7).uniform(lo, hi, (20000, 2))
    return uv[cal.map(uv, None, allow_outside=True, with_sigma=False).inside]


def pick(seed: int, n: int) -> np.ndarray:
    return INSIDE[np.random.default_rng(seed).integers(0, len(INSIDE), n)]


def bodies(seed: int, n: int) -> list[bytes]:
    uv = pick(seed, n)
    return [orjson.dumps({"points": [[float(u), float(v)]]}) for u, v in uv]


def check_map(status: int, body: bytes) -> None:
    if status != 200 or len(orjson.loads(body)["points"][0]) != 3:
        raise SystemExit(f"HTTP error: {status} {body[:200]!r}")


def http_one(port: int, reqs: list[bytes]) -> list[float]:
    c = Http(port)
    lat = []
    try:
        for b in reqs[:20]:  # warm-up
            c.post(MAP_PATH, b)
        for b in reqs:
            t0 = time.perf_counter()
            status, out = c.post(MAP_PATH, b)
            lat.append((time.perf_counter() - t0) * 1e3)
            check_map(status, out)
    finally:
        c.close()
    return lat


def http_many(port: int, reqs: list[list[bytes]]) -> tuple[float, list[float]]:
    lat: list[list[float]] = [[] for _ in reqs]
    errors: list[BaseException] = []
    barrier = threading.Barrier(len(reqs) + 1)

    def client(k: int) -> None:
        try:
            c = Http(port)
            c.post(MAP_PATH, reqs[k][0])
            barrier.wait()
            for b in reqs[k]:
                t0 = time.perf_counter()
                status, out = c.post(MAP_PATH, b)
                lat[k].append((time.perf_counter() - t0) * 1e3)
                check_map(status, out)
            c.close()
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=client, args=(k,)) for k in range(len(reqs))]
    for t in threads:
        t.start()
    barrier.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    if errors:
        raise SystemExit(f"HTTP errors: {errors[:3]}")
    return sum(len(x) for x in reqs) / wall, [x for ls in lat for x in ls]


async def tcp_clients(port: int, lines: list[list[bytes]]) -> list[float]:
    async def client(ls: list[bytes]) -> list[float]:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        out = []
        for line in ls:
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

    lat = await asyncio.gather(*(client(ls) for ls in lines))
    return [x for ls in lat for x in ls]


def on_one_core(server_pid: int, port: int, lines: list[list[bytes]]) -> list[float]:
    """``tcp_clients(port, lines)`` with this client and every thread of the server on CPU 0, then all
    back on every CPU. One client's round trip is two wake-ups: across cores on a VM each can cost
    0.1-0.5 ms, and which core a server lands on follows from its threads, not only its code; on one
    core both servers are measured alike (an unpinned and a pinned line are printed)."""
    cpus = os.sched_getaffinity(0)
    if 0 not in cpus:
        return asyncio.run(tcp_clients(port, lines))
    threads = [int(t) for t in os.listdir(f"/proc/{server_pid}/task")]
    try:
        os.sched_setaffinity(0, {0})
        for tid in threads:
            os.sched_setaffinity(tid, {0})
        return asyncio.run(tcp_clients(port, lines))
    finally:
        for tid in threads:
            try:
                os.sched_setaffinity(tid, cpus)
            except ProcessLookupError:  # a pool thread that ended meanwhile
                pass
        os.sched_setaffinity(0, cpus)


def tcp_lines(seed: int, n: int) -> list[bytes]:
    return [f"{u!r},{v!r}\n".encode() for u, v in pick(seed, n).tolist()]


def vm_hwm_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def vm_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def big_once(port: int, pid: int, body: bytes) -> tuple[float, float, int]:
    before = vm_rss_mib(pid)
    c = Http(port)
    t0 = time.perf_counter()
    status, out = c.post(MAP_PATH, body)
    wall = time.perf_counter() - t0
    c.close()
    if status != 200:
        raise SystemExit(f"big request: {status} {out[:300]!r}")
    n = len(orjson.loads(out)["points"])
    assert n == BIG, n
    return wall, vm_hwm_mib(pid) - before, len(out)


def p50(ms: list[float]) -> float:
    return float(np.percentile(ms, 50))


def line(label: str, ours: float, peer: float, unit: str, goal: str) -> None:
    print(
        f"{label:<34} ours {ours:9.3f} {unit:<6} peer {peer:9.3f} {unit:<6} "
        f"ratio {ours / peer:5.2f}  ({goal})"
    )


def stop_all(procs: dict) -> None:
    """Terminate every started process, then reap each (killed after 15 s)."""
    for p in procs.values():
        p.terminate()
    for p in procs.values():
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="repeats of each measure (default 3)")
    args = ap.parse_args(argv)
    rounds = max(1, min(args.rounds, 20))
    with tempfile.TemporaryDirectory(prefix="eyetohand-bench-") as tmp:
        data, cal_file = Path(tmp) / "data", Path(tmp) / "bench.json"
        seed_database(data, cal_file)
        global INSIDE
        INSIDE = inside_points(cal_file)
        port, tcp_port, peer_port, peer_tcp_port = (free_port() for _ in range(4))
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        py = sys.executable
        cmds = {
            "ours": serve_command(data, {"http": port, "tcp": tcp_port}),
            "peer_http": [py, str(HERE / "peer_http.py"), str(cal_file), str(peer_port)],
            "peer_tcp": [py, str(HERE / "peer_tcp.py"), str(cal_file), str(peer_tcp_port)],
        }
        procs = {
            k: subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=env)
            for k, c in cmds.items()
        }
        try:
            for k, p in (("ours", port), ("ours", tcp_port), ("peer_http", peer_port)):
                wait_port(p, procs[k])
            wait_port(peer_tcp_port, procs["peer_tcp"])
            print(
                f"eyetohand serve (pid {procs['ours'].pid}) vs peer_http.py / peer_tcp.py on 127.0.0.1, "
                f"{os.cpu_count()} cores shared with the clients; {rounds} rounds, paper model"
            )
            # the big request first: each server's memory peak is then measured from its level at start
            body = orjson.dumps(
                {"points": np.random.default_rng(0).uniform(0, 2000, (BIG, 2)), "allow_outside": True},
                option=orjson.OPT_SERIALIZE_NUMPY,
            )
            raw_mib = BIG * (2 + 3 + 1) * 8 / 2**20 + BIG / 2**20
            big: dict[str, list[tuple[float, float, int]]] = {"ours": [], "peer": []}
            for _ in range(min(rounds, 2)):
                for who, p, pid in (
                    ("ours", port, procs["ours"].pid),
                    ("peer", peer_port, procs["peer_http"].pid),
                ):
                    big[who].append(big_once(p, pid, body))
            one: dict[str, list[float]] = {"ours": [], "peer": []}
            many: dict[str, list[float]] = {"ours": [], "peer": []}
            many_lat: dict[str, list[float]] = {"ours": [], "peer": []}
            tcp1: dict[str, list[float]] = {"ours": [], "peer": []}
            tcp8: dict[str, list[float]] = {"ours": [], "peer": []}
            tcp1_core: dict[str, list[float]] = {"ours": [], "peer": []}
            pids = {"ours": procs["ours"].pid, "peer": procs["peer_tcp"].pid}
            for r in range(rounds):
                reqs = bodies(r, ONE_REQUESTS)
                reqs8 = [bodies(1000 * r + k, MANY_REQUESTS) for k in range(CLIENTS)]
                lines1 = [tcp_lines(2000 + r, ONE_REQUESTS)]
                lines8 = [tcp_lines(3000 + 100 * r + k, MANY_REQUESTS) for k in range(CLIENTS)]
                order = (("ours", port, tcp_port), ("peer", peer_port, peer_tcp_port))
                for who, hp, tp in order if r % 2 == 0 else order[::-1]:
                    one[who] += http_one(hp, reqs)
                    rate, lat = http_many(hp, reqs8)
                    many[who].append(rate)
                    many_lat[who] += lat
                    tcp1[who] += asyncio.run(tcp_clients(tp, lines1))
                    tcp8[who] += asyncio.run(tcp_clients(tp, lines8))
                    tcp1_core[who] += on_one_core(pids[who], tp, lines1)
            print(
                f"HTTP single point, 1 client: {rounds} x {ONE_REQUESTS} requests each; 8 clients: "
                f"{rounds} x {CLIENTS} x {MANY_REQUESTS}; TCP the same numbers of lines; no error"
            )
            line("HTTP 1 client p50", p50(one["ours"]), p50(one["peer"]), "ms", "goal <= 1.5")
            rate_o, rate_p = float(np.median(many["ours"])), float(np.median(many["peer"]))
            line("HTTP 8 clients throughput", rate_o, rate_p, "req/s", "goal >= 0.6")
            line("HTTP 8 clients p50", p50(many_lat["ours"]), p50(many_lat["peer"]), "ms", "")
            line("TCP 1 client p50", p50(tcp1["ours"]), p50(tcp1["peer"]), "ms", "goal <= 2")
            ours_1c, peer_1c = p50(tcp1_core["ours"]), p50(tcp1_core["peer"])
            line("TCP 1 client p50, one core", ours_1c, peer_1c, "ms", "goal <= 2")
            line("TCP 8 clients p50", p50(tcp8["ours"]), p50(tcp8["peer"]), "ms", "goal <= 2")
            t_o = float(np.median([b[0] for b in big["ours"]]))
            t_p = float(np.median([b[0] for b in big["peer"]]))
            print(
                f"BIG {BIG} points in one request ({len(body) / 2**20:.1f} MiB in, "
                f"{big['ours'][0][2] / 2**20:.1f} MiB out), raw arrays {raw_mib:.0f} MiB"
            )
            line("BIG time", t_o, t_p, "s", "goal <= 1.2")
            mo, mp = big["ours"][0][1], big["peer"][0][1]
            print(
                f"{'BIG peak memory above start':<34} ours {mo:9.0f} MiB    peer {mp:9.0f} MiB    "
                f"ours / raw arrays {mo / raw_mib:5.2f}  (goal <= 4)"
            )
            c = Http(port)
            status, out = c.post(MAP_PATH, b'{"points": [' + b",".join([b"[1,2]"] * (BIG + 1)) + b"]}")
            print(f"      {BIG + 1} points: {status} {orjson.loads(out)}")
            assert status == 413
            c.close()
            c = Http(port)
            big_body = b'{"points": [' + b",".join([b"[1,2]"] * (14 * 2**20)) + b"]}"
            status, out = c.post(MAP_PATH, big_body)
            print(f"      {len(big_body) / 2**20:.0f} MiB body: {status} {orjson.loads(out)}")
            assert status == 413
            c.close()
        finally:
            stop_all(procs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
