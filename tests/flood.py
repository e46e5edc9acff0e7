"""A flood of idle connections against a real ``eyetohand serve`` run under ``prlimit --nofile=N``
(tests/test_connection_flood.py; also runnable alone: ``PYTHONPATH=src python tests/flood.py``, which
prints what it measured).

The server serves HTTP, the TCP line, Modbus and OPC UA on loopback. :func:`flood` opens idle sockets
spread over the four listeners from other loopback addresses (127.0.0.2 and up: other hosts, as on a
plant network), OPC UA ones sending only ``HEL``; :func:`map_everywhere` then maps one point on every
interface from 127.0.0.1 with independent clients (httpx, a raw socket, pymodbus, asyncua)."""

from __future__ import annotations

import asyncio
import math
import os
import selectors
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from helpers import PAPER, records, src_env

from eyetohand import calibrate
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import registers as R

NOFILE = 1024


def store_calibration(data: Path):
    """A stored calibration ``cell`` (id 1) in ``data``; its region's centre (px)."""
    from eyetohand.server.storage import Store

    cal = calibrate(pairs_from_records(records(PAPER / "calibration_points.csv")), "homography", "lm")
    st = Store(data, create=True)
    try:
        st.create("cell", {"source": "test"}, cal.to_dict(), cal.pairs.to_records(), None, note="test")
    finally:
        st.close()
    c = cal.region.hull_px.mean(axis=0)
    return float(c[0]), float(c[1])


@dataclass
class Served:
    proc: subprocess.Popen
    log: Path
    ports: dict[str, int] = field(default_factory=dict)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)


def start(data: Path, log: Path, nofile: int = NOFILE, timeout_s: float = 60) -> Served:
    """``prlimit --nofile=N eyetohand serve`` with every listener on loopback, any free ports; stdout
    and stderr (every log line) go to ``log``."""
    prlimit = shutil.which("prlimit")
    assert prlimit, "prlimit (util-linux) is needed"
    argv = [prlimit, f"--nofile={nofile}", sys.executable, "-m", "eyetohand.cli", "serve"]
    argv += ["--data", str(data), "--port", "0", "--calibration", "cell", "--tcp", "127.0.0.1:0"]
    argv += ["--modbus", "127.0.0.1:0", "--opcua", "127.0.0.1:0", "--log-level", "info"]
    fh = open(log, "wb")  # noqa: SIM115 - the child writes it for its whole life
    proc = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, env=src_env())
    fh.close()
    srv = Served(proc, log)
    deadline = time.monotonic() + timeout_s
    while len(srv.ports) < 4:
        assert proc.poll() is None, "serve exited: " + log.read_text()
        assert time.monotonic() < deadline, "serve did not start: " + log.read_text()
        time.sleep(0.1)
        for line in log.read_text(errors="replace").splitlines():
            if line.startswith("workbench: http://"):
                srv.ports["http"] = int(line.split("http://127.0.0.1:")[1].split("/")[0])
            elif line.startswith("TCP: 127.0.0.1:"):
                srv.ports["tcp"] = int(line.split(":")[2].split()[0])
            elif line.startswith("Modbus: "):
                srv.ports["modbus"] = int(line.split()[1].rsplit(":", 1)[1])
            elif line.startswith("OPC UA: opc.tcp://"):
                srv.ports["opcua"] = int(line.split()[2].rsplit(":", 1)[1].split("/")[0])
    return srv


def hel(url: str) -> bytes:
    """An OPC UA Hello message (OPC 10000-6 7.1.2.3) for ``url``."""
    body = struct.pack("<IIIII", 0, 65536, 65536, 0, 0) + struct.pack("<i", len(url)) + url.encode()
    return b"HELF" + struct.pack("<I", 8 + len(body)) + body


LISTENERS = ("http", "tcp", "modbus", "opcua")


def flood(
    ports: dict[str, int], n: int, sources: int = 8, names: tuple[str, ...] = LISTENERS
) -> list[socket.socket]:
    """``n`` idle connections spread evenly over the listeners ``names``, from 127.0.0.2 .. 127.0.0.(1
    + ``sources``); OPC UA ones send ``HEL`` and nothing more. Refused or closed ones count too (their
    file handle was taken for a moment)."""
    socks: list[socket.socket] = []
    url = f"opc.tcp://127.0.0.1:{ports['opcua']}/eyetohand/"
    for i in range(n):  # connect without waiting: a full accept queue must not make this take minutes
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.bind((f"127.0.0.{2 + (i // 4) % sources}", 0))
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", ports[names[i % len(names)]]))
        socks.append(s)
    sel = selectors.DefaultSelector()  # epoll: more than FD_SETSIZE sockets
    for i, s in enumerate(socks):
        if names[i % len(names)] == "opcua":
            sel.register(s, selectors.EVENT_WRITE)
    deadline = time.monotonic() + 5
    while sel.get_map() and time.monotonic() < deadline:  # HEL on each OPC UA one once connected
        for key, _ in sel.select(0.5):
            try:
                key.fileobj.send(hel(url))  # type: ignore[union-attr]
            except OSError:
                pass
            sel.unregister(key.fileobj)
    sel.close()
    return socks


def map_everywhere(ports: dict[str, int], uv: tuple[float, float], deadline_s: float) -> dict[str, float]:
    """One point mapped on every interface from 127.0.0.1, each within ``deadline_s``; seconds each
    took. Raises (AssertionError, a client's error) when one fails or is late."""
    import httpx
    from pymodbus.client import ModbusTcpClient

    u, v = uv
    took: dict[str, float] = {}
    t = time.monotonic()
    r = httpx.post(
        f"http://127.0.0.1:{ports['http']}/api/calibrations/1/image-to-robot",
        json={"points": [[u, v]]},
        timeout=deadline_s,
    )
    assert r.status_code == 200, r.text
    took["http"] = time.monotonic() - t

    t = time.monotonic()
    with socket.create_connection(("127.0.0.1", ports["tcp"]), timeout=deadline_s) as s:
        s.sendall(f"{u!r},{v!r}\n".encode())
        line = s.makefile("rb").readline().decode()
    assert len(line.split(",")) == 3 and not line.startswith("ERR"), line
    took["tcp"] = time.monotonic() - t

    t = time.monotonic()
    c = ModbusTcpClient("127.0.0.1", port=ports["modbus"], timeout=deadline_s, retries=0)
    try:
        assert c.connect(), "Modbus: no connection"
        req = R.encode_request(R.Request(777, u, v, None, None, False))
        assert not c.write_registers(1, req[1:], device_id=1).isError()
        assert not c.write_registers(0, [777], device_id=1).isError()
        got = c.read_holding_registers(R.RESULT_ID, count=R.RESULT_END - R.RESULT_ID, device_id=1)
        assert not got.isError(), got
        out = R.decode_result(list(got.registers))
        assert out["request_id"] == 777 and out["status"] == 0, out
    finally:
        c.close()
    took["modbus"] = time.monotonic() - t

    async def opcua() -> list:
        from asyncua import Client

        client = Client(f"opc.tcp://127.0.0.1:{ports['opcua']}/eyetohand/", timeout=deadline_s)
        await client.connect()
        try:
            ns = await client.get_namespace_index("urn:eyetohand")
            cal = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
            return await cal.call_method(f"{ns}:ImageToRobot", u, v, math.nan)
        finally:
            await client.disconnect()

    t = time.monotonic()
    xyz = asyncio.run(asyncio.wait_for(opcua(), deadline_s))
    assert len(xyz) == 4 and all(math.isfinite(x) for x in xyz[:3]), xyz
    took["opcua"] = time.monotonic() - t
    return took


def open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def serve_pid(srv: Served) -> int:
    """The server's pid (prlimit execs it: the same process)."""
    return srv.proc.pid


if __name__ == "__main__":  # measure: PYTHONPATH=src python tests/flood.py [N]
    import tempfile

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        uv = store_calibration(data)
        srv = start(data, Path(tmp) / "serve.log")
        try:
            print("ports", srv.ports, "fds at start", open_fds(srv.proc.pid))
            size0 = srv.log.stat().st_size
            t = time.monotonic()
            socks = flood(srv.ports, n)
            print(f"{n} sockets in {time.monotonic() - t:.1f} s; server fds {open_fds(srv.proc.pid)}")
            for attempt in range(3):
                try:
                    print("mapped", map_everywhere(srv.ports, uv, 10.0))
                    break
                except Exception as exc:  # noqa: BLE001
                    print("FAILED", attempt, repr(exc)[:300])
            time.sleep(5)
            print("server fds", open_fds(srv.proc.pid), "log grew", srv.log.stat().st_size - size0, "bytes")
            for s in socks:
                s.close()
        finally:
            srv.stop()
            tail = srv.log.read_text(errors="replace").splitlines()
            print("log lines", len(tail))
            print("\n".join(tail[-15:]))
