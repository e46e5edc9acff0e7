"""A fair share per source address (issue 40, "a robot is locked out"): the TCP line's connection
slots and its command pool. Idle sockets from other loopback addresses (127.0.0.x binds: other hosts)
take every slot; a new address still gets one while the others keep theirs, without
``--robot-address``; a new address's command gets a place in a full command pool."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

from helpers import PAPER, ServeProcess, records

from eyetohand import calibrate
from eyetohand.cell import ErrorCode, Refusal
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import LineServer
from eyetohand.positioning.limits import Limit, Slots


class Fake:
    def __init__(self, t: float):
        self.last_active = t
        self.closed: Refusal | None = None

    def evictable(self) -> bool:
        return True

    def evict(self, reason: Refusal) -> None:
        self.closed = reason


def test_slots_share_max_min():
    """Full: a newcomer takes the longest idle slot of the heaviest address, only while that address
    holds two more than the newcomer; per address never more than per_address."""
    slots = Slots("test", Limit(total=6, per_address=4))
    a = [Fake(t) for t in (5.0, 1.0, 3.0, 4.0)]
    for c in a:
        assert slots.admit("10.0.0.1", c) is None
    assert slots.admit("10.0.0.1", Fake(9)).code is ErrorCode.BUSY  # its own cap
    b = [Fake(6.0), Fake(7.0)]
    for c in b:
        assert slots.admit("10.0.0.2", c) is None
    assert slots.count == 6
    new = Fake(8.0)
    assert slots.admit("10.0.0.3", new) is None  # full, but .1 holds 4 >= 0 + 2
    assert a[1].closed is not None and a[1].closed.code is ErrorCode.BUSY  # the longest idle (t=1)
    assert all(c.closed is None for c in (a[0], a[2], a[3], *b))
    assert slots.admit("10.0.0.4", Fake(9.0)) is None  # .1 holds 3 >= 2
    assert sorted(len(v) for v in slots.by_address.values()) == [1, 1, 2, 2]
    assert slots.admit("10.0.0.5", Fake(9.5)) is None  # .1 (first of the two with 2) gives its t=4
    assert slots.admit("10.0.0.6", Fake(9.6)) is None  # .2 gives its t=6
    assert [c.closed is not None for c in (*a, *b)] == [False, True, True, True, True, False]
    assert sorted(len(v) for v in slots.by_address.values()) == [1] * 6
    assert slots.admit("10.0.0.7", Fake(9.9)).reason == "busy: too many clients, try again later"
    assert slots.count == 6 and slots.evicted == 4
    slots.release("10.0.0.1", a[1])  # evicted: releasing it again changes nothing
    assert slots.count == 6


def _fit(tmp):
    from eyetohand.server.storage import Store

    cal = calibrate(pairs_from_records(records(PAPER / "calibration_points.csv")), "homography", "lm")
    st = Store(tmp / "data", create=True)
    try:
        st.create("cell", {"source": "test"}, cal.to_dict(), cal.pairs.to_records(), None, note="t")
    finally:
        st.close()
    c = cal.region.hull_px.mean(axis=0)
    return f"{float(c[0])!r},{float(c[1])!r}"


def test_a_new_address_gets_a_slot_while_idle_sockets_hold_every_other(tmp_path):
    """4 x 64 idle sockets from 127.0.0.2-.5 hold all 256 slots of a real ``serve`` (no
    --robot-address); the robot from 127.0.0.1, then a client from 127.0.0.6, each get a mapping answer;
    one idle socket per newcomer was closed (with ERR busy), every other one is still open."""
    line = _fit(tmp_path)
    srv = ServeProcess(tmp_path / "data", "--calibration", "cell", log_level="warning")
    socks: list[socket.socket] = []
    try:
        for i in range(256):
            s = socket.socket()
            s.bind((f"127.0.0.{2 + i % 4}", 0))
            s.settimeout(5)
            s.connect(("127.0.0.1", srv.tcp_port))
            socks.append(s)
        time.sleep(0.5)  # the server accepted every one (none is refused: 64 per address)
        answers, newcomers = [], []
        for source in ("127.0.0.1", "127.0.0.6"):  # both stay connected: two slots taken
            r = socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=5, source_address=(source, 0))
            newcomers.append(r)
            r.sendall(line.encode() + b"\n")
            answers.append(r.makefile("rb").readline().decode().strip())
        for r in newcomers:
            r.close()
        assert all(a.count(",") == 2 and not a.startswith("ERR") for a in answers), answers
        closed = []
        for s in socks:
            s.setblocking(False)
            try:
                got = s.recv(200)
            except BlockingIOError:
                continue  # still open, nothing said
            closed.append(got)
        assert len(closed) == 2, closed  # one slot freed per newcomer, from the longest idle
        assert all(c.startswith(b"ERR busy: this connection's slot went to another address") for c in closed)
    finally:
        for s in socks:
            s.close()
        srv.stop()
    log = "".join(srv.out)
    assert log.count("refusing connections") <= 2, log[-2000:]  # logged once a burst, not per socket


def test_a_new_address_gets_a_place_in_a_full_command_pool(paper_pairs):
    """127.0.0.2 fills the command pool (8: 4 running, 4 waiting) with slow commands; a command from
    127.0.0.3 takes the place of .2's newest waiting one (answered ERR busy) and is answered itself;
    one more from .2 is refused at once (it holds the most)."""
    cal = calibrate(paper_pairs[0], model="homography", optimizer="lm", loo=False)
    go = threading.Event()

    def slow(line: str) -> str:
        go.wait(10)
        return "OK " + line.split()[1]

    async def run() -> None:
        srv = LineServer(cal, "127.0.0.1", 0, commands={"SLOW": slow})
        await srv.start()
        try:
            conns = []
            for i in range(8):
                r, w = await asyncio.open_connection("127.0.0.1", srv.port, local_addr=("127.0.0.2", 0))
                w.write(f"SLOW a{i}\n".encode())
                conns.append((r, w))
            for _ in range(100):
                if srv.pending == 8:
                    break
                await asyncio.sleep(0.02)
            assert srv.pending == 8
            r9, w9 = await asyncio.open_connection("127.0.0.1", srv.port, local_addr=("127.0.0.2", 0))
            w9.write(b"SLOW a8\n")
            assert (await asyncio.wait_for(r9.readline(), 5)).startswith(b"ERR busy: 8 commands")
            rb, wb = await asyncio.open_connection("127.0.0.1", srv.port, local_addr=("127.0.0.3", 0))
            wb.write(b"SLOW b0\n")
            await asyncio.sleep(0.2)
            go.set()
            assert await asyncio.wait_for(rb.readline(), 5) == b"OK b0\n"
            got = [await asyncio.wait_for(r.readline(), 5) for r, _ in conns]
            busy = [g for g in got if g.startswith(b"ERR busy: this command's place went to another")]
            assert len(busy) == 1 and sum(g.startswith(b"OK a") for g in got) == 7, got
            for _, w in (*conns, (r9, w9), (rb, wb)):
                w.close()
        finally:
            go.set()
            srv.close()

    asyncio.run(asyncio.wait_for(run(), 30))


def test_replace_own_serves_the_newest_and_spares_requests_at_work():
    """HTTP's rule: an address at its bound has its own longest idle connection replaced by the new
    one; a connection whose request the server works on is never closed for another."""

    class Working(Fake):
        def evictable(self) -> bool:
            return False

    slots = Slots("test", Limit(total=4, per_address=2), replace_own=True)
    old, busy = Fake(1.0), Working(0.5)
    assert slots.admit("10.0.0.1", busy) is None and slots.admit("10.0.0.1", old) is None
    new = Fake(2.0)
    assert slots.admit("10.0.0.1", new) is None  # at its bound: replaces its longest idle evictable one
    assert old.closed is not None and "a newer connection from the same address" in old.closed.reason
    assert busy.closed is None
    assert slots.admit("10.0.0.1", Fake(3.0)) is None and new.closed is not None
    strict = Slots("test", Limit(total=4, per_address=1))  # the TCP line: refused, nothing closed
    first = Fake(1.0)
    assert strict.admit("10.0.0.1", first) is None
    assert strict.admit("10.0.0.1", Fake(2.0)).code is ErrorCode.BUSY and first.closed is None
    only_busy = Slots("test", Limit(total=1, per_address=1), replace_own=True)
    assert only_busy.admit("10.0.0.1", Working(1.0)) is None
    assert only_busy.admit("10.0.0.1", Fake(2.0)).code is ErrorCode.BUSY
