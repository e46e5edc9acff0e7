"""Following a shared store, on loopback only: `python benchmarks/bench_follow.py [--followers 1,10,50]`.

A throwaway PostgreSQL cluster (tests/pg.py: Debian's server binaries, a temporary folder, a free port
on 127.0.0.1) holds one calibration, "bench". For each count N, N `eyetohand serve --store
postgresql://… --calibration bench --tcp 127.0.0.1:0` processes follow it, and one robot client per
process (in this process, one thread each) sends a mapping line every PACE_S. Each round the "office"
(this process's own connection: another process than the servers) writes a new version, alternating
two calibrations 5 mm apart in x; measured: the time from the write's return to each follower's first
answer with the new version (first follower, median, last follower), median over the rounds.

Then the mapping path, which must not read the database per line: one serve on PostgreSQL and one on
SQLite, one client each, p50 of REQUESTS single-point lines, alternating in rounds; the ratio.

On a small machine the servers, the database and the clients share the cores: the times are end to
end, everything included. `--rounds N` (default 5).
"""

from __future__ import annotations

import argparse
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

PACE_S = 0.02
POINT = "554.166,1283.44"  # a paper calibration point: inside the calibrated region
REQUESTS = 400


def _x(reply: str) -> float:
    return float(reply.split()[-1].split(",")[0])


class Robot(threading.Thread):
    """One robot client: a mapping line every PACE_S; notes when each answer's x first changes."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.file = self.sock.makefile("rw")
        self.x: float | None = None
        self.changed_at: float | None = None
        self.stop = threading.Event()

    def ask(self) -> str:
        self.file.write(POINT + "\n")
        self.file.flush()
        return self.file.readline().strip()

    def run(self) -> None:
        while not self.stop.is_set():
            x = _x(self.ask())
            if self.x is not None and x != self.x and self.changed_at is None:
                self.changed_at = time.monotonic()
            self.x = x
            time.sleep(PACE_S)

    def arm(self) -> None:
        self.changed_at = None


def follow_rounds(url: str, n: int, rounds: int, cals, tmp: Path) -> list[list[float]]:
    from helpers import ServeProcess

    from eyetohand.server import open_store

    servers = []
    robots: list[Robot] = []
    store = open_store(url)
    try:
        for i in range(n):
            servers.append(
                ServeProcess(tmp / f"n{n}-{i}", "--store", url, "--calibration", "bench", timeout_s=120)
            )
        robots = [Robot(s.tcp_port) for s in servers]
        for r in robots:
            r.start()
        time.sleep(1.0)
        cal_id = store.find("bench").id
        out = []
        for k in range(rounds):
            for r in robots:
                r.arm()
            now = store.version(cal_id).calibration
            cal = cals[1] if now == cals[0].to_dict() else cals[0]  # the other one: x moves 5 mm
            store.add_version(cal_id, {"source": "import"}, cal.to_dict(), [], None, f"round {k}")
            t0 = time.monotonic()
            deadline = t0 + 10
            while any(r.changed_at is None for r in robots) and time.monotonic() < deadline:
                time.sleep(0.005)
            late = [r for r in robots if r.changed_at is None]
            if late:
                raise SystemExit(f"{len(late)} of {n} followers did not answer with the new version in 10 s")
            out.append(sorted(max(0.0, r.changed_at - t0) for r in robots if r.changed_at is not None))
            time.sleep(0.5)
        return out
    finally:
        for r in robots:
            r.stop.set()
        for s in servers:
            s.stop()
        store.close()


def mapping_p50(port: int, n: int) -> float:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        f = s.makefile("rw")
        times = []
        for _ in range(n):
            t = time.perf_counter()
            f.write(POINT + "\n")
            f.flush()
            f.readline()
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--followers", default="1,10,50", help="the counts of following serve processes")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    counts = [int(c) for c in args.followers.split(",")]

    from helpers import PAPER, ServeProcess
    from pg import Cluster

    from eyetohand import calibrate, load_pairs
    from eyetohand.core import PointPairs
    from eyetohand.server import open_store

    pairs = load_pairs(PAPER / "calibration_points.csv")
    shifted = PointPairs(pairs.uv_px, pairs.xyz_mm + [5.0, 0.0, 0.0], pairs.ids)
    cals = [calibrate(p, model="homography", optimizer="lm", loo=False) for p in (pairs, shifted)]
    cluster = Cluster()
    try:
        cluster.start()
        url = cluster.new_database()
        with tempfile.TemporaryDirectory(prefix="eyetohand-follow-") as tmp:
            store = open_store(url)
            store.create("bench", {"source": "import"}, cals[0].to_dict(), [], None)
            store.close()
            sqlite_url = f"sqlite:{Path(tmp) / 'cell.db'}"
            s = open_store(sqlite_url, create=True)
            s.create("bench", {"source": "import"}, cals[0].to_dict(), [], None)
            s.close()

            print("office write -> first robot answer with it (TCP lines every 20 ms per follower)")
            print(
                f"{'followers':>9} {'first_s':>8} {'median_s':>9} {'last_s':>7}"
                f"   (median over {args.rounds} rounds)"
            )
            for n in counts:
                rounds = follow_rounds(url, n, args.rounds, cals, Path(tmp))
                first = statistics.median(r[0] for r in rounds)
                med = statistics.median(statistics.median(r) for r in rounds)
                last = statistics.median(r[-1] for r in rounds)
                print(f"{n:>9} {first:>8.3f} {med:>9.3f} {last:>7.3f}", flush=True)

            pg_srv = ServeProcess(Path(tmp) / "map-pg", "--store", url, "--calibration", "bench")
            lite_srv = ServeProcess(Path(tmp) / "map-lite", "--store", sqlite_url, "--calibration", "bench")
            try:
                pg_t, lite_t = [], []
                for _ in range(args.rounds):
                    pg_t.append(mapping_p50(pg_srv.tcp_port, REQUESTS))
                    lite_t.append(mapping_p50(lite_srv.tcp_port, REQUESTS))
            finally:
                pg_srv.stop()
                lite_srv.stop()
            pg_us, lite_us = statistics.median(pg_t) * 1e6, statistics.median(lite_t) * 1e6
            print(
                f"TCP mapping p50, one client, {REQUESTS} lines x {args.rounds} rounds: "
                f"PostgreSQL {pg_us:.0f} us, SQLite {lite_us:.0f} us, ratio {pg_us / lite_us:.2f}"
            )
    finally:
        cluster.remove()


if __name__ == "__main__":
    main()
