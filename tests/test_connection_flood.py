"""1000 idle connections must not take the service down (issue 40).

A real ``eyetohand serve`` with HTTP, ``--tcp``, ``--modbus`` and ``--opcua`` runs under ``prlimit
--nofile=1024`` (systemd's default soft limit, what the shipped unit had); 1000 idle sockets from other
loopback addresses (OPC UA ones sending only HEL) are opened spread over the listeners, then all on one;
meanwhile a point is mapped on every interface by an independent client (httpx, a raw socket,
pymodbus, asyncua) within a deadline, and the log stays small. Before: HTTP took 8.6 s, the log grew
15 MB (226,000 lines of ``Too many open files``) in 5 s. Then the deadlines: a Modbus or OPC UA
connection that sends nothing (or only HEL) is closed, and so is one idle after a request."""

from __future__ import annotations

import asyncio
import errno
import logging
import re
import shutil
import socket
import subprocess
import sys
import time

import pytest
from flood import LISTENERS, NOFILE, flood, hel, map_everywhere, open_fds, start, store_calibration
from helpers import PAPER, records, src_env

from eyetohand import calibrate
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import FixedCalibration, Limit, ModbusService, OpcUaService, quiet_accept_errors
from eyetohand.positioning import registers as R

pytestmark = pytest.mark.serial  # deadlines

DEADLINE_S = 10.0  # each interface's mapping, under the flood (measured 0.001-1.2 s)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("flood")
    uv = store_calibration(tmp / "data")
    srv = start(tmp / "data", tmp / "serve.log")
    yield srv, uv
    srv.stop()


@pytest.mark.parametrize("names", [LISTENERS, ("opcua",), ("modbus",), ("tcp",), ("http",)], ids="+".join)
@pytest.mark.long
def test_1000_idle_sockets_leave_every_interface_mapping(served, names):
    srv, uv = served
    assert srv.ports.keys() == set(LISTENERS)
    first = srv.log.read_text()
    assert f"file handles: limit {NOFILE} (hard {NOFILE})" in first  # the budget line: under prlimit
    size0 = srv.log.stat().st_size
    socks = flood(srv.ports, 1000, names=names)
    try:
        time.sleep(1.0)  # the server has taken (or refused) them
        took = map_everywhere(srv.ports, uv, DEADLINE_S)
        held = open_fds(srv.proc.pid)
    finally:
        for s in socks:
            s.close()
    print(names, {k: round(v, 3) for k, v in took.items()}, f"{held} handles open")
    assert held < NOFILE - 100, held  # the reserve stayed free
    assert srv.proc.poll() is None
    grown = srv.log.stat().st_size - size0
    text = srv.log.read_text()[size0:]
    assert "Too many open files" not in text, text[-3000:]
    assert grown < 4000, text[-3000:]  # a line per listener and burst, and the mapping requests


def _cal():
    return calibrate(pairs_from_records(records(PAPER / "calibration_points.csv")), "homography", "lm")


def _closed_within(sock: socket.socket, seconds: float) -> float:
    """Seconds until the server closed ``sock`` (AssertionError when it did not within ``seconds``)."""
    t = time.monotonic()
    sock.settimeout(seconds)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        raise AssertionError(f"still open after {seconds} s") from None
    except ConnectionError:
        pass
    return time.monotonic() - t


@pytest.mark.long
def test_modbus_closes_silent_and_idle_connections_and_keeps_a_polling_one():
    """Modbus: a socket that never sends is closed after first_s, one idle after a request after
    idle_s (pymodbus alone kept both for ever: still open after 150 s); a client that keeps asking is
    never closed. Per address at most limit.per_address."""
    cal = _cal()
    c = cal.region.hull_px.mean(axis=0)

    async def run() -> None:
        svc = ModbusService(
            lambda: FixedCalibration(cal), "127.0.0.1", 0, limit=Limit(8, 3), first_s=0.5, idle_s=1.0
        )
        await svc.start()
        try:
            loop = asyncio.get_running_loop()
            silent = socket.create_connection(("127.0.0.1", svc.port))
            t = await loop.run_in_executor(None, _closed_within, silent, 5.0)
            assert 0.3 < t < 2.0, t
            from pymodbus.client import AsyncModbusTcpClient

            client = AsyncModbusTcpClient("127.0.0.1", port=svc.port, timeout=2, retries=0, reconnect_delay=0)
            await client.connect()
            req = R.encode_request(R.Request(9, float(c[0]), float(c[1]), None, None, False))
            for _ in range(8):  # 2 s of requests, twice the idle limit: kept
                assert not (await client.write_registers(0, req, device_id=1)).isError()
                await asyncio.sleep(0.25)
            got = await client.read_holding_registers(R.RESULT_ID, count=2, device_id=1)
            assert got.registers[:2] == [9, 0]  # answered, status 0
            assert client.connected
            await asyncio.sleep(2.0)  # then idle: closed
            assert svc.slots.count == 0  # the server closed it (and freed its slot)
            client.close()
            same = [socket.create_connection(("127.0.0.1", svc.port)) for _ in range(4)]
            await asyncio.sleep(0.2)
            assert svc.slots.count == 3  # the fourth from 127.0.0.1 was refused (per address 3)
            for s in same:
                s.close()
        finally:
            await svc.close()

    asyncio.run(asyncio.wait_for(run(), 60))


@pytest.mark.long
def test_opcua_closes_hel_only_and_silent_connections():
    """OPC UA: a socket that sends HEL and nothing more (no session) and one that sends nothing are
    closed after first_s (before: held until max_connections, 1000, took every file handle)."""
    cal = _cal()

    async def run() -> None:
        svc = OpcUaService(lambda: FixedCalibration(cal), "127.0.0.1", 0, first_s=1.0)
        await svc.start()
        try:
            loop = asyncio.get_running_loop()
            silent = socket.create_connection(("127.0.0.1", svc.port))
            helo = socket.create_connection(("127.0.0.1", svc.port))
            helo.sendall(hel(svc.url))
            helo.settimeout(5)
            ack = await loop.run_in_executor(None, helo.recv, 8)  # (the server runs on this loop)
            assert ack[:4] == b"ACKF", ack  # the server answered the HEL
            t_silent, t_hel = await asyncio.gather(
                loop.run_in_executor(None, _closed_within, silent, 8.0),
                loop.run_in_executor(None, _closed_within, helo, 8.0),
            )
            assert t_silent < 3.0 and t_hel < 3.0, (t_silent, t_hel)
            assert svc.slots.count == 0
        finally:
            await svc.close()

    asyncio.run(asyncio.wait_for(run(), 60))


def _serve_under(nofile: str, tmp_path) -> subprocess.CompletedProcess:
    """``prlimit --nofile=SOFT[:HARD] serve`` with every listener, stopped as soon as it printed its
    budget line (or ended)."""
    store_calibration(tmp_path / "data")
    argv = [shutil.which("prlimit") or "prlimit", f"--nofile={nofile}", sys.executable, "-m", "eyetohand.cli"]
    argv += ["serve", "--data", str(tmp_path / "data"), "--port", "0", "--calibration", "cell"]
    argv += ["--tcp", "127.0.0.1:0", "--modbus", "127.0.0.1:0", "--opcua", "127.0.0.1:0"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=src_env())
    out = []
    assert proc.stdout is not None
    for line in proc.stdout:
        out.append(line)
        if line.startswith("connections:"):
            proc.terminate()
            break
    rest, err = proc.communicate(timeout=30)
    return subprocess.CompletedProcess(argv, proc.returncode, "".join(out) + rest, err)


def test_the_soft_limit_is_raised_toward_the_hard_one(tmp_path):
    r = _serve_under("1024:4096", tmp_path)
    line = next(x for x in r.stdout.splitlines() if x.startswith("connections:"))
    assert "file handles: limit 4096 (hard 4096)" in line, line
    found = re.findall(r"(\w+) (\d+) \((\d+)/address, backlog (\d+)\)", line)
    assert [f[:3] for f in found] == [
        ("http", "256", "256"),
        ("tcp", "256", "64"),
        ("modbus", "64", "16"),
        ("opcua", "64", "16"),
    ], line
    # the backlog grows with the handles (a burst of connects is queued, not retried a second later):
    # an eighth of what is left per listener, 64 at 1024 handles, ~120 at 4096
    backlogs = {int(f[3]) for f in found}
    assert len(backlogs) == 1 and 64 < backlogs.pop() <= 512, line


def test_too_few_file_handles_refuse_to_start_with_one_line(tmp_path):
    r = _serve_under("400", tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: too few file handles: limit 400 (hard 400)") and "LimitNOFILE" in line, (
        line
    )


def test_accept_failing_for_want_of_handles_is_logged_once_a_burst(caplog):
    loop = asyncio.new_event_loop()
    try:
        quiet_accept_errors(loop, "TEST")
        listener = socket.socket()
        with caplog.at_level(logging.WARNING, logger="eyetohand.connections"):
            for _ in range(1000):  # asyncio's context for accept() failing (selector_events.py)
                loop.call_exception_handler(
                    {
                        "message": "socket.accept() out of system resource",
                        "exception": OSError(errno.EMFILE, "Too many open files"),
                        "socket": listener,
                    }
                )
        listener.close()
    finally:
        loop.close()
    lines = [r.getMessage() for r in caplog.records if r.name == "eyetohand.connections"]
    assert len(lines) == 1 and lines[0].startswith(
        "TEST: accept(): refusing connections: out of file handles"
    )
