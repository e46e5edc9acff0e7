"""The TCP line's round trip, before and after a change, in one run: ``eyetohand serve --tcp --modbus
--opcua`` from this tree and from another tree's ``src/`` (``--baseline-src``, e.g. a copy of main's),
and peer_tcp.py, the three alternating round by round over the same points (bench_paths.py's row 3
with more rounds and the baseline beside it). Prints each one's p50 and its ratio to the peer.

``python benchmarks/tcp_ab.py --baseline-src DIR [--rounds 8] [--lines 300]`` (~1 min).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_server as srv  # noqa: E402

SRC = HERE.parent / "src"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-src", required=True, metavar="DIR", help="the other tree's src/")
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--lines", type=int, default=300, help="lines per round and server")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="eyetohand-tcp-ab-") as tmp:
        data, cal_file = Path(tmp) / "data", Path(tmp) / "bench.json"
        srv.seed_database(data, cal_file)
        srv.INSIDE = srv.inside_points(cal_file)
        py = sys.executable
        ports: dict[str, dict[str, int]] = {}
        cmds, envs = {}, {}
        for name, src in (("baseline", args.baseline_src), ("this tree", str(SRC))):
            p = {k: srv.free_port() for k in ("http", "tcp", "modbus", "opcua")}
            ports[name] = p
            cmds[name], envs[name] = (
                srv.serve_command(data, p),
                {**os.environ, "PYTHONPATH": src, "PYTHONUNBUFFERED": "1"},
            )
        peer_port = srv.free_port()
        ports["peer"] = {"tcp": peer_port}
        cmds["peer"] = [py, str(HERE / "peer_tcp.py"), str(cal_file), str(peer_port)]
        envs["peer"] = {**os.environ, "PYTHONPATH": str(SRC)}
        procs = {
            k: subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=envs[k])
            for k, c in cmds.items()
        }
        try:
            for k, p in ports.items():  # every port: OPC UA fills its address space after TCP opens
                for port in p.values():
                    srv.wait_port(port, procs[k])
            lat: dict[str, list[float]] = {k: [] for k in cmds}
            for r in range(-1, args.rounds):  # round -1 warms up
                pts = srv.pick(r + 30, args.lines).round(3).tolist()
                lines = [f"{u!r},{v!r}\n".encode() for u, v in pts]
                for k in list(cmds) if r % 2 == 0 else list(cmds)[::-1]:
                    got = asyncio.run(srv.tcp_clients(ports[k]["tcp"], [lines]))
                    if r >= 0:
                        lat[k] += got
        finally:
            srv.stop_all(procs)
    p50 = {k: float(np.percentile(v, 50)) for k, v in lat.items()}
    for k, v in p50.items():
        print(f"{k:10s} TCP line p50 {v * 1e3:7.1f} µs  {v / p50['peer']:.2f}× the peer")


if __name__ == "__main__":
    main()
