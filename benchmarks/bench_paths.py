"""The paths users call, each against its peer in the same run (issue 29's table): `python
benchmarks/bench_paths.py [--quick]`.

1. ``Calibration.image_to_robot(uv)`` with its default guard, 10⁶ points inside the region, against
   ``cv2.perspectiveTransform`` with the model's matrix (goal ≤ 1.5×); the model alone beside it.
2. The same, one point, against NumPy's ``H @ [u, v, 1]`` and divide (goal ≤ 3×).
3. The TCP line ``u,v`` round trip, p50, against a minimal asyncio echo-and-map server
   (peer_tcp.py; goal ≤ 1.5×); beside it the same with each server and its client pinned to one core
   (bench_server.on_one_core): a round trip is two wake-ups, which across a VM's cores cost 0.1-0.5 ms
   each and move the unpinned ratio 1-3× between runs; on one core both servers are measured alike.
4. HTTP one point, p50, against a minimal FastAPI app (peer_http.py; goal ≤ 1.2×).
5. ``eyetohand apply CAL --uv U V`` start against ``python -c "import numpy"`` (goal ≤ 1.5×, wall and
   CPU medians of interleaved fresh processes).
6. Modbus and OPC UA round trips (p50) beside the TCP line's, to the same ``eyetohand serve``, and
   against minimal servers of their own protocol (peer_plc.py: pymodbus, asyncua).

Rows 1-2 run in this process on a homography calibration of the paper's pairs (bench_startup.py's);
rows 3-4 and 6 use one ``eyetohand serve --tcp --modbus --opcua`` and the three peers as subprocesses on
127.0.0.1, the calibration seeded as bench_server.py does, ours and the peer alternating round by
round over the same points; row 5 is bench_startup.py's measure. The pieces are those benchmarks'
own (imported). Each row prints its ratio and "goal met" or "NOT met". ~2 min (``--quick`` ~1 min).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_plc  # noqa: E402  (adds tests/ to sys.path: helpers)
import bench_server as srv  # noqa: E402
import bench_startup  # noqa: E402
from bench_map import _best_us, _ms  # noqa: E402

from eyetohand.calibration import Calibration  # noqa: E402

ROWS: list[tuple[str, str, float, float, float, str]] = []  # label, unit, ours, peer, goal, peer name


def row(label: str, ours: float, peer: float, unit: str, peer_name: str, goal: float | None) -> None:
    ratio = ours / peer
    verdict = "" if goal is None else ("goal met" if ratio <= goal else "NOT met")
    goal_s = "" if goal is None else f"goal ≤ {goal:g}"
    print(
        f"{label:<44} {ours:10.4g} {unit:<3} {peer_name:<34} {peer:10.4g} {unit:<3} "
        f"{ratio:7.2f}×  {goal_s:<9} {verdict}",
        flush=True,
    )


def inside(cal: Calibration, n: int, seed: int = 0) -> np.ndarray:
    """``n`` pixels inside the calibrated region (uniform in its hull's box, the outside ones dropped)."""
    hull = cal.region.hull_px
    lo, hi = hull.min(axis=0), hull.max(axis=0)
    rng = np.random.default_rng(seed)
    out = np.zeros((0, 2))
    while len(out) < n:
        uv = rng.uniform(lo, hi, (2 * n, 2))
        out = np.vstack([out, uv[cal.map(uv, None, allow_outside=True, with_sigma=False).inside]])
    return out[:n]


def in_process(rep: int, n1: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cal = Calibration.load(bench_plc.fit(Path(tmp)))
    H = cal.model.matrix_image_to_robot
    big = inside(cal, 10**6)
    big_cv = big.reshape(-1, 1, 2)
    check = cv2.perspectiveTransform(big_cv[:1000], H)[:, 0]
    assert np.allclose(cal.image_to_robot(big[:1000])[:, :2], check)
    guarded = _ms(lambda: cal.image_to_robot(big), rep)
    model = _ms(lambda: cal.model.image_to_robot(big), rep)
    peer = _ms(lambda: cv2.perspectiveTransform(big_cv, H), rep)
    row("image_to_robot, 10⁶ points inside, guarded", guarded, peer, "ms", "cv2.perspectiveTransform", 1.5)
    row("   (the model alone, no guard)", model, peer, "ms", "cv2.perspectiveTransform", None)
    uv1 = big[0].copy()

    def numpy_one():
        p = H @ np.array([uv1[0], uv1[1], 1.0])
        return p[:2] / p[2]

    one = _best_us(lambda: cal.image_to_robot(uv1), n1, rep)
    floor = _best_us(numpy_one, n1, rep)
    row("image_to_robot, one point, guarded", one, floor, "µs", "NumPy H @ [u, v, 1], divide", 3.0)


def servers(rounds: int, requests: int) -> None:
    with tempfile.TemporaryDirectory(prefix="eyetohand-bench-") as tmp:
        data, cal_file = Path(tmp) / "data", Path(tmp) / "bench.json"
        srv.seed_database(data, cal_file)
        srv.INSIDE = srv.inside_points(cal_file)
        keys = ("http", "tcp", "modbus", "opcua", "peer_http", "peer_tcp", "peer_modbus", "peer_opcua")
        ports = {k: srv.free_port() for k in keys}
        py = sys.executable
        cmds = {
            "ours": srv.serve_command(data, ports),
            "peer_http": [py, str(HERE / "peer_http.py"), str(cal_file), str(ports["peer_http"])],
            "peer_tcp": [py, str(HERE / "peer_tcp.py"), str(cal_file), str(ports["peer_tcp"])],
            "peer_plc": [py, str(HERE / "peer_plc.py"), str(cal_file)]
            + [str(ports["peer_modbus"]), str(ports["peer_opcua"])],
        }
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        procs = {
            k: subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=env)
            for k, c in cmds.items()
        }
        try:
            for k, p in (("ours", "http"), ("ours", "tcp"), ("ours", "modbus"), ("ours", "opcua")):
                srv.wait_port(ports[p], procs[k])
            srv.wait_port(ports["peer_http"], procs["peer_http"])
            srv.wait_port(ports["peer_tcp"], procs["peer_tcp"])
            srv.wait_port(ports["peer_modbus"], procs["peer_plc"])
            srv.wait_port(ports["peer_opcua"], procs["peer_plc"])
            pids = {"tcp": procs["ours"].pid, "peer_tcp": procs["peer_tcp"].pid}
            _measure_servers(ports, rounds, requests, pids)
        finally:
            srv.stop_all(procs)


def _clients(ports: dict[str, int], pms: dict, reqs: list[bytes], pts: list[tuple[float, float]]):
    """One round's client of each server: name → a call returning its latencies (ms)."""
    R = bench_plc.R
    lines = [f"{u!r},{v!r}\n".encode() for u, v in pts]

    def modbus(pm):
        return lambda: bench_plc.modbus_round(
            lambda regs: pm.write_registers(0, regs),
            lambda: pm.read_holding_registers(R.RESULT_ID, count=R.RESULT_END - R.RESULT_ID).registers,
            pts,
        )

    def opcua(key: str):
        url = f"opc.tcp://127.0.0.1:{ports[key]}/eyetohand/"
        return lambda: asyncio.run(bench_plc.opcua_round(url, pts))

    return {
        "http": lambda: srv.http_one(ports["http"], reqs),
        "peer_http": lambda: srv.http_one(ports["peer_http"], reqs),
        "tcp": lambda: asyncio.run(srv.tcp_clients(ports["tcp"], [lines])),
        "peer_tcp": lambda: asyncio.run(srv.tcp_clients(ports["peer_tcp"], [lines])),
        "modbus": modbus(pms["modbus"]),
        "peer_modbus": modbus(pms["peer_modbus"]),
        "opcua": opcua("opcua"),
        "peer_opcua": opcua("peer_opcua"),
    }


def _measure_servers(ports: dict[str, int], rounds: int, requests: int, pids: dict[str, int]) -> None:
    from pymodbus.client import ModbusTcpClient

    pms = {k: ModbusTcpClient("127.0.0.1", port=ports[k]) for k in ("modbus", "peer_modbus")}
    assert all(pm.connect() for pm in pms.values())
    lat: dict[str, list[float]] = {}
    try:
        for r in range(-1, rounds):  # round -1: warm-up (connections, first calls), not counted
            reqs = srv.bodies(r + 10, 20 if r < 0 else requests)
            pts = [(u, v) for u, v in srv.pick(r + 30, len(reqs)).round(3).tolist()]
            runs = _clients(ports, pms, reqs, pts)
            for k in list(runs) if r % 2 == 0 else list(runs)[::-1]:  # ours and peer, alternating first
                got = runs[k]()
                if r >= 0:
                    lat.setdefault(k, []).extend(got)
            lines = [f"{u!r},{v!r}\n".encode() for u, v in pts]
            for k in ("tcp", "peer_tcp") if r % 2 == 0 else ("peer_tcp", "tcp"):  # both on one core
                got = srv.on_one_core(pids[k], ports[k], [lines])
                if r >= 0:
                    lat.setdefault(k + " one core", []).extend(got)
    finally:
        for pm in pms.values():
            pm.close()
    p50 = {k: float(np.percentile(v, 50)) for k, v in lat.items()}
    row("TCP line u,v round trip, p50", p50["tcp"], p50["peer_tcp"], "ms", "asyncio echo-and-map", 1.5)
    row(
        "   (each server and its client on one core)",
        p50["tcp one core"],
        p50["peer_tcp one core"],
        "ms",
        "asyncio echo-and-map",
        None,
    )
    row("HTTP one point, p50", p50["http"], p50["peer_http"], "ms", "minimal FastAPI (peer_http)", 1.2)
    row("Modbus write+read handshake, p50", p50["modbus"], p50["tcp"], "ms", "our TCP line, p50", None)
    row("OPC UA ImageToRobot call, p50", p50["opcua"], p50["tcp"], "ms", "our TCP line, p50", None)
    row("Modbus handshake, p50", p50["modbus"], p50["peer_modbus"], "ms", "minimal pymodbus (peer_plc)", None)
    row("OPC UA call, p50", p50["opcua"], p50["peer_opcua"], "ms", "minimal asyncua (peer_plc)", None)


def startup(rounds: int) -> None:
    wall, cpu = bench_startup.measure(rounds)
    peer, apply = bench_startup.PEER, bench_startup.APPLY
    row(f"{apply} start, wall", wall[apply] * 1e3, wall[peer] * 1e3, "ms", peer, 1.5)
    row(f"{apply} start, CPU", cpu[apply] * 1e3, cpu[peer] * 1e3, "ms", peer, 1.5)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats, rounds and requests")
    args = ap.parse_args(argv)
    q = args.quick
    print(
        f"The paths users call against peers in the same run ({os.cpu_count()} cores; medians; "
        f"ratio = ours / peer)",
        flush=True,
    )
    t0 = time.perf_counter()
    in_process(rep=3 if q else 5, n1=1000 if q else 3000)
    servers(rounds=2 if q else 4, requests=150 if q else 300)
    startup(rounds=9 if q else 15)
    print(f"({time.perf_counter() - t0:.0f} s; `make test` wall time: see docs/performance.md)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
