"""PLC round trips beside the TCP line's, on loopback: `python benchmarks/bench_plc.py [--rounds N]`.

One real `eyetohand serve --calibration FILE --tcp … --modbus … --opcua …` runs as a subprocess (free
127.0.0.1 ports, a calibration fitted to the paper's pairs in this run); this process is the client of
all three, one request at a time, and the protocols alternate in rounds over the same points:

- TCP line: ``u,v\\n`` → ``x,y,z\\n`` (a raw socket);
- Modbus, the PLC's handshake: one write of registers 0..9 (inputs and a new request id, the write
  that maps) and one read of 100..130 (the result with the echoed id), with pymodbus's synchronous
  client and with pyModbusTCP's (its client is lighter: the gap is client cost);
- OPC UA: one ``Calibration.ImageToRobot(u, v, NaN)`` call (asyncua's client; a session kept open).

Prints p50 and p99 (ms, end to end, client included: on a small machine the clients share the cores
with the server) and each one's ratio to the TCP line's p50 measured in the same run; and the Modbus
and OPC UA rounds to the minimal servers of peer_plc.py (pymodbus, asyncua: the same register map and
method, the same mapping call, nothing else), each ratio ours / its peer: what the service adds.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from helpers import PAPER, free_port, records, src_env  # noqa: E402

from eyetohand.positioning import registers as R  # noqa: E402

REQUESTS = 300  # per protocol per round


def fit(folder: Path) -> Path:
    from eyetohand import calibrate
    from eyetohand.core.pairs import pairs_from_records

    pairs = pairs_from_records(records(PAPER / "calibration_points.csv"))
    return calibrate(pairs, "homography", "lm", loo=False).save(folder / "cell.json")


def inside_points(cal_file: Path, n: int, seed: int) -> list[tuple[float, float]]:
    from eyetohand.calibration import Calibration

    cal = Calibration.load(cal_file)
    hull = cal.region.hull_px
    c = hull.mean(axis=0)
    rng = np.random.default_rng(seed)
    pts = c + (rng.random((n, 2)) - 0.5) * (hull.max(axis=0) - hull.min(axis=0)) * 0.3
    return [(round(float(u), 3), round(float(v), 3)) for u, v in pts]


def start(cal_file: Path, data: Path, ports: dict[str, int]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "eyetohand.cli", "serve", "--port", "0", "--data", str(data)]
    cmd += ["--calibration", str(cal_file), "--log-level", "warning"]
    for flag in ("tcp", "modbus", "opcua"):
        cmd += [f"--{flag}", f"127.0.0.1:{ports[flag]}"]
    proc = subprocess.Popen(cmd, env=src_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("workbench:"):
            return proc
    raise SystemExit("serve did not start: " + (proc.stdout.read() if proc.stdout else ""))


def start_peer(cal_file: Path, ports: dict[str, int]) -> subprocess.Popen:
    """peer_plc.py on ``ports["peer_modbus"]`` and ``ports["peer_opcua"]``, returned once both accept."""
    cmd = [sys.executable, str(ROOT / "benchmarks" / "peer_plc.py"), str(cal_file)]
    proc = subprocess.Popen(cmd + [str(ports["peer_modbus"]), str(ports["peer_opcua"])], env=src_env())
    deadline = time.monotonic() + 60
    for key in ("peer_modbus", "peer_opcua"):
        while True:
            try:
                socket.create_connection(("127.0.0.1", ports[key]), timeout=1).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit("peer_plc.py did not start") from None
                time.sleep(0.1)
    return proc


def tcp_round(port: int, pts) -> list[float]:
    out = []
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        f = s.makefile("rb")
        for u, v in pts:
            t = time.perf_counter()
            s.sendall(f"{u!r},{v!r}\n".encode())
            reply = f.readline()
            out.append((time.perf_counter() - t) * 1e3)
            assert not reply.startswith(b"ERR"), reply
    return out


class Ids:
    n = 0

    @classmethod
    def next(cls) -> int:
        cls.n = cls.n % 65535 + 1
        return cls.n


def modbus_round(write, read, pts) -> list[float]:
    out = []
    for u, v in pts:
        rid = Ids.next()
        regs = R.encode_request(R.Request(rid, u, v, None, None, False))
        t = time.perf_counter()
        write(regs)
        res = R.decode_result(read())
        out.append((time.perf_counter() - t) * 1e3)
        assert res["request_id"] == rid and res["status"] == 0, res
    return out


async def opcua_round(url: str, pts) -> list[float]:
    from asyncua import Client

    out = []
    client = Client(url)
    client.session_timeout = 600_000  # what the server grants (else the client warns on stderr)
    async with client:
        ns = await client.get_namespace_index("urn:eyetohand")
        cal = await client.nodes.objects.get_child([f"{ns}:Calibration"])
        method = await cal.get_child(f"{ns}:ImageToRobot")
        for u, v in pts:
            t = time.perf_counter()
            await cal.call_method(method, u, v, math.nan)
            out.append((time.perf_counter() - t) * 1e3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--requests", type=int, default=REQUESTS)
    args = ap.parse_args(argv)
    from pymodbus.client import ModbusTcpClient
    from pyModbusTCP.client import ModbusClient

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cal_file = fit(folder)
        ports = {k: free_port() for k in ("tcp", "modbus", "opcua", "peer_modbus", "peer_opcua")}
        proc = start(cal_file, folder / "data", ports)
        peer = start_peer(cal_file, ports)
        url = f"opc.tcp://127.0.0.1:{ports['opcua']}/eyetohand/"
        peer_url = f"opc.tcp://127.0.0.1:{ports['peer_opcua']}/eyetohand/"
        pm = ModbusTcpClient("127.0.0.1", port=ports["modbus"])
        assert pm.connect()
        pp = ModbusTcpClient("127.0.0.1", port=ports["peer_modbus"])
        assert pp.connect()
        mt = ModbusClient(host="127.0.0.1", port=ports["modbus"], auto_open=True)
        span = R.RESULT_END - R.RESULT_ID
        clients = {
            "TCP line": lambda pts: tcp_round(ports["tcp"], pts),
            "Modbus (pymodbus client)": lambda pts: modbus_round(
                lambda regs: pm.write_registers(0, regs),
                lambda: pm.read_holding_registers(R.RESULT_ID, count=span).registers,
                pts,
            ),
            "Modbus (pyModbusTCP client)": lambda pts: modbus_round(
                lambda regs: mt.write_multiple_registers(0, regs),
                lambda: mt.read_holding_registers(R.RESULT_ID, span),
                pts,
            ),
            "OPC UA (asyncua client)": lambda pts: asyncio.run(opcua_round(url, pts)),
            "Modbus peer (pymodbus client)": lambda pts: modbus_round(
                lambda regs: pp.write_registers(0, regs),
                lambda: pp.read_holding_registers(R.RESULT_ID, count=span).registers,
                pts,
            ),
            "OPC UA peer (asyncua client)": lambda pts: asyncio.run(opcua_round(peer_url, pts)),
        }
        times: dict[str, list[float]] = {k: [] for k in clients}
        try:
            for k in clients:  # warm-up: imports, connections, first calls
                clients[k](inside_points(cal_file, 20, 99))
            for r in range(args.rounds):
                pts = inside_points(cal_file, args.requests, r)
                for k, run in clients.items():
                    times[k] += run(pts)
        finally:
            pm.close()
            pp.close()
            mt.close()
            for p in (proc, peer):
                p.terminate()
                p.wait(20)
    ref = float(np.percentile(times["TCP line"], 50))
    print(f"loopback round trips, {args.rounds} rounds x {args.requests} requests, {os.cpu_count()} cores")
    print(f"{'':30s} {'p50 ms':>8s} {'p99 ms':>8s} {'p50 / TCP line':>15s}")
    for k, ms in times.items():
        p50, p99 = np.percentile(ms, [50, 99])
        print(f"{k:30s} {p50:8.3f} {p99:8.3f} {p50 / ref:15.2f}")
    p50 = {k: float(np.percentile(ms, 50)) for k, ms in times.items()}
    for ours, peer_key in (
        ("Modbus (pymodbus client)", "Modbus peer (pymodbus client)"),
        ("OPC UA (asyncua client)", "OPC UA peer (asyncua client)"),
    ):
        print(f"{ours.split(' (')[0]}: ours / minimal peer (peer_plc.py) {p50[ours] / p50[peer_key]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
