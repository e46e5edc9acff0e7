"""Probe of the TCP line service under abuse (issue 27), through the real ``eyetohand serve`` process.

Each probe starts its own server on loopback (a temporary data folder), does one bad thing to it and
measures what a well-behaved robot sees meanwhile:

- ``stale``: 32 clients keep the collector busy with ``CAL POINT`` (each waits on a grab of the sim:
  camera) while the served calibration is deleted over HTTP: how long mapping lines keep answering
  with the deleted calibration (the docs promise < 1 s);
- ``starve``: 200 idle sockets from 127.0.0.2-.5 and a client that pipelines mapping lines without
  ever reading its answers: the p50/p99/max of another client's mapping lines, before and during
  (target: p99 < 50 ms);
- ``lockout``: 4 x 64 idle sockets from 127.0.0.2-.5, then the robot (``--robot-address
  127.0.0.1`` when the server knows the option) connects: served, or ``ERR busy``?

``python benchmarks/probe_tcp.py [stale|starve|lockout ...]`` prints one line of figures per probe
(all three by default, ~40 s). tests/faults/test_truth_tcp.py runs the same functions with limits.
"""

from __future__ import annotations

import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "tests") not in sys.path:
    sys.path.insert(0, str(ROOT / "tests"))

from helpers import PAPER, ServeProcess, records  # noqa: E402

CELL = """[camera]
width_px = 640
height_px = 512
pixel_size_um = 13.8
principal_offset_px = [3.0, -2.0]
"""
MAP_LINE = b"600,900\n"  # inside the paper calibration's region
IDLE_ADDRS = ("127.0.0.2", "127.0.0.3", "127.0.0.4", "127.0.0.5")


def seed(data: Path, name: str = "cell1") -> None:
    """A stored calibration ``name`` (the paper's pairs, homography) in ``data``."""
    from fastapi.testclient import TestClient

    from eyetohand.server.app import create_app

    app = create_app(data)
    with TestClient(app) as c:
        r = c.post(
            "/api/calibrations",
            json={"name": name, "pairs": records(PAPER / "calibration_points.csv"), "model": "homography"},
        )
        assert r.status_code == 201, r.text
    app.state.store.close()


def connect(port: int, source: str = "127.0.0.1", timeout_s: float = 10.0) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=timeout_s, source_address=(source, 0))
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


class Lines:
    """A blocking line client (LF-ended replies)."""

    def __init__(self, port: int, source: str = "127.0.0.1", timeout_s: float = 10.0):
        self.sock = connect(port, source, timeout_s)
        self.buf = b""

    def send(self, line: bytes | str) -> str:
        self.sock.sendall(line if isinstance(line, bytes) else line.encode() + b"\n")
        return self.read()

    def read(self) -> str:
        while b"\n" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError(f"closed by the server (after {self.buf!r})")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line.decode()

    def close(self) -> None:
        self.sock.close()


def latencies_ms(port: int, n: int, source: str = "127.0.0.1") -> list[float]:
    c = Lines(port, source)
    out = []
    try:
        for _ in range(n):
            t = time.perf_counter()
            reply = c.send(MAP_LINE)
            out.append((time.perf_counter() - t) * 1e3)
            assert reply.count(",") == 2, reply
    finally:
        c.close()
    return out


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def idle_sockets(port: int, per_addr: int) -> list[socket.socket]:
    """``per_addr`` connected sockets from each of 127.0.0.2-.5 that never send anything."""
    out = []
    for addr in IDLE_ADDRS:
        for _ in range(per_addr):
            s = socket.socket()
            s.bind((addr, 0))
            s.settimeout(5)
            try:
                s.connect(("127.0.0.1", port))
            except OSError:
                s.close()
                continue
            out.append(s)
    return out


# ------------------------------------------------------------------ the probes


def probe_stale(tmp: Path, clients: int = 32, cap_s: float = 30.0, extra: tuple[str, ...] = ()) -> dict:
    """Seconds from the HTTP delete's answer until mapping lines refuse, and how many mapped answers
    came in that time, while ``clients`` clients keep sending CAL POINT."""
    import httpx

    data = tmp / "data"
    seed(data)
    cell = tmp / "cell.toml"
    cell.write_text(CELL)
    srv = ServeProcess(
        data, "--camera", f"sim:{cell}?seed=5", "--calibration", "cell1", *extra, log_level="error"
    )
    stop = threading.Event()
    replies: list[str] = []
    try:
        assert srv.tcp_port is not None
        first = Lines(srv.tcp_port)
        assert first.send("CAL BEGIN cell1") == "OK", "CAL BEGIN refused"
        first.close()

        def hammer(k: int) -> None:
            try:
                c = Lines(srv.tcp_port, timeout_s=cap_s + 30)
                j = 0
                while not stop.is_set():
                    j += 1
                    replies.append(c.send(f"CAL POINT {100 + k + j * 0.37:.3f},{50 + j * 0.11:.3f},150"))
                c.close()
            except OSError:
                pass

        threads = [threading.Thread(target=hammer, args=(k,), daemon=True) for k in range(clients)]
        for t in threads:
            t.start()
        time.sleep(2.0)  # the collector's queue fills
        robot = Lines(srv.tcp_port)
        assert robot.send(MAP_LINE).count(",") == 2
        r = httpx.delete(srv.url + "/api/calibrations/1", timeout=30)
        assert r.status_code == 204, r.text
        t0 = time.monotonic()
        stale = 0
        refused_s = None
        while time.monotonic() - t0 < cap_s:
            reply = robot.send(MAP_LINE)
            if reply.startswith("ERR"):
                refused_s = time.monotonic() - t0
                break
            stale += 1
            time.sleep(0.005)
        robot.close()
        return {
            "refused_after_s": refused_s,
            "stale_answers": stale,
            "cal_replies": len(replies),
            "busy": sum(r.startswith("ERR busy") for r in replies),
        }
    finally:
        stop.set()
        srv.stop()


def _pipeliner(port: int, stop: threading.Event, sent: list[int]) -> None:
    """Pipelines mapping lines and never reads an answer (until ``stop``)."""
    s = connect(port)
    s.settimeout(0.2)
    block = MAP_LINE * 4096
    try:
        while not stop.is_set():
            try:
                sent[0] += s.send(block)
            except TimeoutError:
                pass
            except OSError:
                break
    finally:
        s.close()


def probe_starve(tmp: Path, idle: int = 200, lines: int = 300, extra: tuple[str, ...] = ()) -> dict:
    """A good client's mapping-line latencies (ms) alone, then with ``idle`` idle sockets and a
    pipelining client that does not read."""
    data = tmp / "data"
    seed(data)
    srv = ServeProcess(data, "--calibration", "cell1", *extra, log_level="error")
    stop = threading.Event()
    socks: list[socket.socket] = []
    try:
        assert srv.tcp_port is not None
        latencies_ms(srv.tcp_port, 50)  # warm up
        alone = latencies_ms(srv.tcp_port, lines)
        socks = idle_sockets(srv.tcp_port, idle // len(IDLE_ADDRS))
        sent = [0]
        bad = threading.Thread(target=_pipeliner, args=(srv.tcp_port, stop, sent), daemon=True)
        bad.start()
        time.sleep(1.0)  # the bad client's answers fill every buffer between it and the server
        loaded = latencies_ms(srv.tcp_port, lines)
        return {
            "alone_p50_ms": statistics.median(alone),
            "alone_p99_ms": pct(alone, 0.99),
            "p50_ms": statistics.median(loaded),
            "p99_ms": pct(loaded, 0.99),
            "max_ms": max(loaded),
            "idle_sockets": len(socks),
            "bad_client_sent_kb": sent[0] / 1024,
        }
    finally:
        stop.set()
        for s in socks:
            s.close()
        srv.stop()


def probe_lockout(tmp: Path, per_addr: int = 64, extra: tuple[str, ...] = ()) -> dict:
    """4 x ``per_addr`` idle sockets from 127.0.0.2-.5, then the robot from 127.0.0.1: its first
    reply (a mapping answer, or ERR busy)."""
    data = tmp / "data"
    seed(data)
    srv = ServeProcess(data, "--calibration", "cell1", *extra, log_level="error")
    socks: list[socket.socket] = []
    try:
        assert srv.tcp_port is not None
        socks = idle_sockets(srv.tcp_port, per_addr)
        time.sleep(0.5)
        robot = Lines(srv.tcp_port)
        try:
            reply = robot.send(MAP_LINE)
        except ConnectionError as exc:
            reply = str(exc)
        robot.close()
        return {"idle_sockets": len(socks), "robot_reply": reply}
    finally:
        for s in socks:
            s.close()
        srv.stop()


PROBES = {"stale": probe_stale, "starve": probe_starve, "lockout": probe_lockout}


def main(argv: list[str]) -> None:
    for name in argv or list(PROBES):
        with tempfile.TemporaryDirectory() as tmp:
            t = time.monotonic()
            out = PROBES[name](Path(tmp))
            figures = ", ".join(
                f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in out.items()
            )
            print(f"{name}: {figures} ({time.monotonic() - t:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
