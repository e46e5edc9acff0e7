"""The guarded default path against its peers, in one run (issue 29): `python benchmarks/bench_guard.py`.

1. ``Calibration.image_to_robot`` of 10⁶ points inside the region (the default guard) against
   ``cv2.perspectiveTransform`` of the same points with the same matrix (goal ≤ 1.5×);
2. the same, one point, against a NumPy 3×3 product and divide (goal ≤ 3×);
3. the TCP line ``u,v`` round trip, p50, of ``positioning.tcp.LineServer`` (a calibration file, as
   ``eyetohand serve --calibration FILE.json`` serves it) against ``benchmarks/peer_tcp.py`` (goal ≤ 1.5×),
   each in a process of its own, one blocking client, both pinned to one CPU when it can (one round trip
   is two wake-ups: across cores on a VM each costs 0.1–0.5 ms whichever server it is).

The paper's pairs, homography. Every measure alternates ours and the peer in rounds and prints medians
and their ratio. ``--quick``: fewer rounds.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from eyetohand import calibrate, load_pairs
from eyetohand.calibration import Calibration

HERE = Path(__file__).resolve().parent
PAPER = HERE.parent / "examples" / "paper"
N_BIG = 1_000_000

SERVE = """
import asyncio, sys
from eyetohand.calibration import Calibration
from eyetohand.positioning import FixedCalibration, LineServer

async def main():
    server = LineServer(FixedCalibration.from_file(sys.argv[1]), "127.0.0.1", int(sys.argv[2]))
    await server.start()
    await server.serve_forever()

asyncio.run(main())
"""


def inside_points(cal: Calibration, n: int, seed: int = 0) -> np.ndarray:
    """``n`` pixels inside the training points' hull (not its margin), uniformly over its bounding box."""
    rng = np.random.default_rng(seed)
    hull = cal.region.hull_px  # type: ignore[union-attr]
    lo, hi = hull.min(axis=0), hull.max(axis=0)
    out = np.empty((0, 2))
    while len(out) < n:
        q = lo + rng.random((2 * n, 2)) * (hi - lo)
        out = np.vstack([out, q[cal.region.outside_px(q) == 0]])  # type: ignore[union-attr]
    return np.ascontiguousarray(out[:n])


def timed(f, repeat: int) -> float:
    best = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        best.append(time.perf_counter() - t0)
    return min(best)


def rounds(pairs: dict, n_rounds: int, repeat: int) -> dict[str, float]:
    """Median over ``n_rounds`` of each callable's best of ``repeat``, the callables alternated."""
    got: dict[str, list[float]] = {k: [] for k in pairs}
    for f in pairs.values():
        f()  # warm-up
    for _ in range(n_rounds):
        for k, f in pairs.items():
            got[k].append(timed(f, repeat))
    return {k: statistics.median(v) for k, v in got.items()}


def per_call(f, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        f()
    return (time.perf_counter() - t0) / n


def report(label: str, ours: float, peer: float, unit: str, scale: float, goal: str) -> None:
    print(
        f"{label:<40} ours {ours * scale:9.3f} {unit:<3} peer {peer * scale:9.3f} {unit:<3} "
        f"ratio {ours / peer:6.2f}  (goal {goal})"
    )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def connect(port: int, proc: subprocess.Popen) -> socket.socket:
    for _ in range(300):
        if proc.poll() is not None:
            raise SystemExit(f"server exited with {proc.returncode}")
        try:
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
        except OSError:
            time.sleep(0.05)
            continue
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return s
    raise SystemExit(f"no server on port {port}")


def round_trips(sock: socket.socket, lines: list[bytes]) -> list[float]:
    out = []
    for line in lines:
        t0 = time.perf_counter()
        sock.sendall(line)
        reply = b""
        while not reply.endswith(b"\n"):
            reply += sock.recv(4096)
        out.append(time.perf_counter() - t0)
        if reply.startswith(b"ERR") or reply.count(b",") != 2:
            raise SystemExit(f"TCP error: {reply!r}")
    return out


def pin(pids: list[int]) -> None:
    """This process and every thread of ``pids`` on CPU 0, when this process may use it."""
    if 0 not in os.sched_getaffinity(0):
        return
    os.sched_setaffinity(0, {0})
    for pid in pids:
        for tid in os.listdir(f"/proc/{pid}/task"):
            os.sched_setaffinity(int(tid), {0})


def tcp(cal: Calibration, n_rounds: int, per_round: int) -> None:
    with tempfile.TemporaryDirectory(prefix="eyetohand-bench-guard-") as tmp:
        f = Path(tmp) / "cal.json"
        cal.save(f)
        ports = {"ours": free_port(), "peer": free_port()}
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        procs = {
            "ours": subprocess.Popen([sys.executable, "-c", SERVE, str(f), str(ports["ours"])], env=env),
            "peer": subprocess.Popen(
                [sys.executable, str(HERE / "peer_tcp.py"), str(f), str(ports["peer"])], env=env
            ),
        }
        try:
            socks = {k: connect(ports[k], procs[k]) for k in procs}
            pin([p.pid for p in procs.values()])
            pts = inside_points(cal, n_rounds * per_round, seed=3).tolist()
            lines = [f"{u!r},{v!r}\n".encode() for u, v in pts]
            lat: dict[str, list[float]] = {"ours": [], "peer": []}
            for k in socks:
                round_trips(socks[k], lines[:200])  # warm-up
            for r in range(n_rounds):
                block = lines[r * per_round : (r + 1) * per_round]
                for k in ("ours", "peer") if r % 2 == 0 else ("peer", "ours"):
                    lat[k] += round_trips(socks[k], block)
            for s in socks.values():
                s.close()
            med = {k: statistics.median(v) for k, v in lat.items()}
            report("TCP line u,v round trip, p50", med["ours"], med["peer"], "us", 1e6, "<= 1.5")
        finally:
            for p in procs.values():
                p.terminate()
                p.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer rounds")
    ap.add_argument("--no-tcp", action="store_true", help="leave out the TCP round trip")
    args = ap.parse_args(argv)
    n_rounds = 5 if args.quick else 11
    cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm", loo=False)
    H = cal.model.matrix_image_to_robot  # type: ignore[attr-defined]
    uv = inside_points(cal, N_BIG)
    src = uv.reshape(-1, 1, 2)
    big = rounds(
        {"ours": lambda: cal.image_to_robot(uv), "peer": lambda: cv2.perspectiveTransform(src, H)},
        n_rounds,
        3,
    )
    report("image_to_robot, 10^6 inside points", big["ours"], big["peer"], "ms", 1e3, "<= 1.5")

    one = uv[0].copy()
    u, v = one.tolist()
    ones = np.array([u, v, 1.0])

    def peer_one():
        p = H @ ones
        return p[:2] / p[2]

    n_calls = 2000 if args.quick else 10000
    per_call(lambda: cal.image_to_robot(one), n_calls)  # warm-up
    got: dict[str, list[float]] = {"ours": [], "peer": []}
    for _ in range(n_rounds):
        got["ours"].append(per_call(lambda: cal.image_to_robot(one), n_calls))
        got["peer"].append(per_call(peer_one, n_calls))
    report(
        "image_to_robot, one point",
        statistics.median(got["ours"]),
        statistics.median(got["peer"]),
        "us",
        1e6,
        "<= 3",
    )
    if not args.no_tcp:
        tcp(cal, n_rounds, 400 if args.quick else 1000)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
