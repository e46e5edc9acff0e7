"""Issue 27, the TCP side: each promise of the line service tested through a real ``eyetohand serve``
process on loopback (real sockets), each bounded in time. The probes themselves are
benchmarks/probe_tcp.py (``python benchmarks/probe_tcp.py`` prints their figures)."""

from __future__ import annotations

import json
import os
import resource
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from helpers import ROOT, ServeProcess

sys.path.insert(0, str(ROOT / "benchmarks"))
from probe_tcp import (  # noqa: E402
    CELL,
    MAP_LINE,
    Lines,
    connect,
    probe_lockout,
    probe_stale,
    probe_starve,
    seed,
)

Z = 150.0


def serve(tmp: Path, *extra: str, preexec=None) -> ServeProcess:
    return ServeProcess(tmp / "data", *extra, log_level="error", preexec=preexec)


def until(fn, timeout_s: float, step_s: float = 0.01):
    """(seconds, value) at the first truthy ``fn()``, or (None, last value) after ``timeout_s``."""
    t0 = time.monotonic()
    got = fn()
    while not got and time.monotonic() - t0 < timeout_s:
        time.sleep(step_s)
        got = fn()
    return (time.monotonic() - t0 if got else None), got


# ------------------------------------------------------------------ 1. fresh however busy the collector


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_a_deleted_calibration_is_refused_within_1_s_while_32_clients_keep_the_camera_busy(tmp_path):
    """32 clients send CAL POINT back to back (each a grab of the sim: camera); the calibration is
    deleted over HTTP: mapping lines refuse within 1 s (before: up to the whole command queue's time,
    25 s measured). A client over the command queue's bound gets ERR busy at once."""
    out = probe_stale(tmp_path, clients=32, cap_s=5.0)
    print(out)
    assert out["refused_after_s"] is not None and out["refused_after_s"] < 1.0, out
    assert out["busy"] > 0  # the queue is bounded: the surplus is refused, not queued


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_a_new_version_is_in_force_within_1_s_while_the_collector_is_busy(tmp_path):
    data = tmp_path / "data"
    seed(data)
    cell = tmp_path / "cell.toml"
    cell.write_text(CELL)
    srv = ServeProcess(data, "--camera", f"sim:{cell}?seed=5", "--calibration", "cell1", log_level="error")
    stop = threading.Event()
    try:
        assert Lines(srv.tcp_port).send("CAL BEGIN cell1") == "OK"

        def hammer(k: int) -> None:
            try:
                c = Lines(srv.tcp_port, timeout_s=60)
                j = 0
                while not stop.is_set():
                    j += 1
                    c.send(f"CAL POINT {100 + k + j * 0.37:.3f},{50 + j * 0.11:.3f},150")
                c.close()
            except OSError:
                pass  # the server stopped under it

        for k in range(32):
            threading.Thread(target=hammer, args=(k,), daemon=True).start()
        time.sleep(1.5)
        robot = Lines(srv.tcp_port)
        assert robot.send("VERSION").startswith("OK cell1,1,")
        r = httpx.post(srv.url + "/api/calibrations/1/rollback", json={"version": 1}, timeout=30)
        assert r.status_code == 200 and r.json()["version"] == 2, r.text
        took, _ = until(lambda: robot.send("VERSION").startswith("OK cell1,2,"), 5.0)
        assert took is not None and took < 1.0, took
        robot.close()
    finally:
        stop.set()
        srv.stop()


# ------------------------------------------------------------------ 5. the database file is the truth


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_tcp_refuses_while_the_database_file_is_deleted_or_replaced(tmp_path):
    data = tmp_path / "data"
    seed(data)
    srv = serve(tmp_path, "--calibration", "cell1")
    db, aside = data / "calibrations.db", tmp_path / "aside.db"
    try:
        robot = Lines(srv.tcp_port)
        good = robot.send(MAP_LINE)
        assert good.count(",") == 2
        os.rename(db, aside)  # deleted under the running server
        took, reply = until(lambda: robot.send(MAP_LINE).startswith("ERR database replaced or missing"), 2.0)
        assert took is not None and took < 1.0, reply
        assert robot.send("VERSION").startswith("ERR database replaced or missing")
        os.rename(aside, db)  # the same file is back: sane again
        took, _ = until(lambda: robot.send(MAP_LINE) == good, 2.0)
        assert took is not None and took < 1.0
        copy = data / "copy.db"
        copy.write_bytes(db.read_bytes())
        os.replace(copy, db)  # replaced by another file (a restore, a copy): refused
        took, _ = until(lambda: robot.send(MAP_LINE).startswith("ERR database replaced or missing"), 2.0)
        assert took is not None and took < 1.0
        robot.close()
    finally:
        srv.stop()


# ------------------------------------------------------------------ 6. acknowledged means stored


def _view_rect(cell: Path, z: float = Z):
    from helpers import view_square_mm

    from eyetohand.sim.camera_sim import CellCamera
    from eyetohand.sim.cell import load_cell

    cx, cy, half = view_square_mm(CellCamera(load_cell(cell)).camera, z, margin_px=40)
    return cx, cy, half


def _ignore_sigxfsz() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG


def test_a_point_refused_on_a_full_disk_is_never_stored(tmp_path):
    """The journal cannot grow (the server's file size limit lowered to its size: a full disk for that
    write): CAL POINT answers ERR; after space comes back, the next POINT is point 6 and the journal
    holds exactly the 6 acknowledged points (before: the refused record was still buffered and
    flushed with the next one, 7 on disk)."""
    cell = tmp_path / "cell.toml"
    cell.write_text(CELL)
    cx, cy, half = _view_rect(cell)
    srv = serve(tmp_path, "--camera", f"sim:{cell}?seed=5", "--calibration", "cell1", preexec=_ignore_sigxfsz)
    journal = tmp_path / "data" / "collect" / "collect.jsonl"
    soft, hard = resource.prlimit(srv.proc.pid, resource.RLIMIT_FSIZE)
    try:
        link = Lines(srv.tcp_port, timeout_s=60)
        assert link.send("CAL BEGIN cell1") == "OK"
        poses = [(cx + 0.5 * half * (k % 3 - 1), cy + 0.5 * half * (k // 3 - 1), Z) for k in range(9)]
        acked = []
        for k in range(5):
            reply = link.send("CAL POINT {:.3f},{:.3f},{:.3f}".format(*poses[k]))
            assert reply.startswith(f"OK {k + 1},"), reply
            acked.append(k)
        resource.prlimit(srv.proc.pid, resource.RLIMIT_FSIZE, (journal.stat().st_size, hard))
        refused = link.send("CAL POINT {:.3f},{:.3f},{:.3f}".format(*poses[5]))
        assert refused.startswith("ERR journal write failed"), refused
        resource.prlimit(srv.proc.pid, resource.RLIMIT_FSIZE, (soft, hard))  # space is back
        reply = link.send("CAL POINT {:.3f},{:.3f},{:.3f}".format(*poses[6]))
        assert reply.startswith("OK 6,"), reply
        assert link.send("CAL STATUS") == "OK cell1,6,collecting"
        link.close()
    finally:
        srv.stop()
    points = [json.loads(x) for x in journal.read_text().splitlines() if '"op":"point"' in x]
    assert [p["n"] for p in points] == [1, 2, 3, 4, 5, 6]
    assert [round(p["xyz_mm"][0], 3) for p in points] == [round(poses[k][0], 3) for k in (0, 1, 2, 3, 4, 6)]


# ------------------------------------------------------------------ 7. one calibration for mapping and CHECK


def test_collection_and_check_use_the_calibration_the_mapping_lines_serve(tmp_path):
    data = tmp_path / "data"
    seed(data)
    cell = tmp_path / "cell.toml"
    cell.write_text(CELL)
    z_cal = 167.417  # the plane of the seeded (paper) calibration
    cx, cy, _ = _view_rect(cell, z_cal)
    srv = serve(tmp_path, "--camera", f"sim:{cell}?seed=5", "--calibration", "cell1")
    try:
        link = Lines(srv.tcp_port, timeout_s=60)
        refused = link.send("CAL BEGIN cell2")
        assert refused.startswith("ERR CAL BEGIN cell2: mapping lines and CAL CHECK use calibration 'cell1'")
        assert "--calibration cell2" in refused
        assert link.send("CAL STATUS") == "OK -,0,none"
        assert link.send("VERSION").startswith("OK cell1,1,")
        check = link.send(f"CAL CHECK {cx:.3f},{cy:.3f},{z_cal}")
        # cell1 (the paper's pixels) checked: the sim's target is outside its region; no other was used
        assert check.startswith("ERR points[0]: outside the calibrated region"), check
        assert link.send("CAL BEGIN cell1") == "OK"
        link.close()
    finally:
        srv.stop()


# ------------------------------------------------------------------ 8. no client starves another


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_a_pipelining_client_that_never_reads_does_not_delay_another(tmp_path):
    """200 idle sockets from 127.0.0.2-.5 and a client pipelining mapping lines without reading its
    answers: another client's mapping lines keep p99 < 50 ms (the target; alone 1.7 ms, before the fix a
    line waited up to 4.8 s). On a shared, loaded machine the bound is relative to the same client's
    lines measured alone in the same run (printed)."""
    out = probe_starve(tmp_path, idle=200, lines=300)
    print(out)
    # target p99 < 50 ms (1.7-16 ms measured by the probe alone); 250 ms bounds it on a machine at load 15
    assert out["p99_ms"] < 250, out
    assert out["max_ms"] < 1000, out  # before: 4755 ms, one burst of the pipeliner's lines


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_the_robot_address_is_served_whatever_idles_elsewhere(tmp_path):
    out = probe_lockout(tmp_path, per_addr=64, extra=("--robot-address", "127.0.0.1"))
    assert out["idle_sockets"] == 256
    assert out["robot_reply"].count(",") == 2, out


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_sockets_that_never_send_a_line_are_closed_after_the_grace(tmp_path):
    seed(tmp_path / "data")
    srv = serve(tmp_path, "--calibration", "cell1", "--tcp-first-line", "1")
    socks = []
    try:
        for k in range(8):
            s = socket.socket()
            s.bind((f"127.0.0.{2 + k % 4}", 0))
            s.settimeout(5)
            s.connect(("127.0.0.1", srv.tcp_port))
            socks.append(s)
        t0 = time.monotonic()
        for s in socks:
            got = b""
            while chunk := s.recv(256):
                got += chunk
            assert got == b"ERR no line for 1 s; closing\n"
        assert time.monotonic() - t0 < 4
    finally:
        for s in socks:
            s.close()
        srv.stop()


# ------------------------------------------------------------------ 10. small ones


def test_cr_lf_and_crlf_each_end_one_line_also_split_across_reads(tmp_path):
    seed(tmp_path / "data")
    srv = serve(tmp_path, "--calibration", "cell1")
    try:
        s = connect(srv.tcp_port)
        robot = Lines.__new__(Lines)
        robot.sock, robot.buf = s, b""
        s.sendall(b"600,900\r")  # CR only (a KAREL robot): answered, not left hanging
        assert robot.read().count(",") == 2
        s.sendall(b"600,901\r")
        assert robot.read().count(",") == 2
        time.sleep(0.2)
        s.sendall(b"\n600,902\r\n")  # the LF ending the CR LF above arrived in the next read
        assert robot.read().count(",") == 2
        s.sendall(b"VERSION\n")
        assert robot.read().startswith("OK cell1,1,")  # nothing answered in between: no empty line
        s.settimeout(0.3)
        with pytest.raises(TimeoutError):
            s.recv(100)
        s.close()
    finally:
        srv.stop()


def test_cal_and_belt_on_a_server_without_camera_or_conveyor_say_what_is_missing(tmp_path):
    seed(tmp_path / "data")
    srv = serve(tmp_path, "--calibration", "cell1")
    try:
        link = Lines(srv.tcp_port)
        assert link.send("CAL BEGIN x") == "ERR no camera: start eyetohand serve with --camera URI to use CAL"
        assert link.send("belt 1,2,3,4") == (
            "ERR no conveyor: start eyetohand serve with --conveyor FILE to use BELT"
        )
        assert link.send("600") == (
            "ERR 1 numbers; expected 2 or 3 (u,v or u,v,z) before any words; "
            "send u,v[,z][,a=ANGLE][,s=N][,t=DEG][,d=DIAMETER][,allow][,sigma] or VERSION"
        )
        link.close()
    finally:
        srv.stop()


@pytest.mark.serial  # asserts a latency or deadline: runs alone (tests/conftest.py)
def test_a_corrupt_image_in_a_folder_camera_is_a_decode_error_not_a_timeout(tmp_path):
    shots = tmp_path / "shots"
    shots.mkdir()
    srv = serve(tmp_path, "--camera", f"folder:{shots}?timeout=3")
    try:
        link = Lines(srv.tcp_port, timeout_s=20)
        assert link.send("CAL BEGIN c1") == "OK"

        def drop() -> None:
            time.sleep(0.5)
            (shots / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50 + b"IEND\xaeB`\x82")

        threading.Thread(target=drop, daemon=True).start()
        t0 = time.monotonic()
        reply = link.send("CAL POINT 1,2,150")
        assert reply.startswith("ERR image decode failed: bad.png"), reply
        assert time.monotonic() - t0 < 2.5  # at once, not after the 3 s timeout
        assert link.send("CAL STATUS") == "OK c1,0,collecting"
        link.close()
    finally:
        srv.stop()


def test_belt_touch_of_a_part_never_sighted_is_refused(tmp_path):
    from eyetohand.cell import BeltProtocol

    belt = BeltProtocol(None, source=None, store_dir=tmp_path)
    assert belt.handle("BELT BEGIN b1") == "OK"
    assert belt.handle("BELT TOUCH p1,1,2,3,100") == (
        "ERR BELT TOUCH: part 'p1' was never sighted; send BELT SIGHT p1 first "
        "(a touch pairs with the camera's sighting of the same part)"
    )
    assert belt.handle("BELT STATUS") == "OK b1,0,0,collecting"
