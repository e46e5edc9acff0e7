"""Failed authentication is not free (eyetohand.core.AuthBackoff): the rule with a fake clock, then a
real ``eyetohand serve`` process hammered with wrong tokens over TCP ``AUTH``, HTTP ``Bearer`` and the
OPC UA user token (asyncua's own client), each attempt made by a real client; the rate of judged
attempts stays bounded, and the right token still works at once from another address (each test
guesses from an address of its own, 127.0.0.x: Linux routes all of 127/8 to loopback)."""

from __future__ import annotations

import asyncio
import logging
import socket
import time

import httpx
import pytest
from helpers import SMALL_CELL_TOML, ServeProcess

from eyetohand.core import AuthBackoff
from eyetohand.core.backoff import BASE_DELAY_S, FREE_FAILURES

TOKEN = "the-right-token-42"


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_the_rule_with_a_fake_clock(caplog):
    clock = Clock()
    b = AuthBackoff(free=3, base_delay_s=1.0, max_delay_s=8.0, forget_s=100.0, max_addresses=4, clock=clock)
    with caplog.at_level(logging.WARNING, logger="eyetohand.auth"):
        for _ in range(3):
            assert b.wait_s("a") == 0
            b.failed("a")
        assert b.wait_s("a") == 0  # three free failures
        b.failed("a")  # the 4th: held back from now on
        waits = []
        for _ in range(6):
            waits.append(b.wait_s("a"))
            clock.t += waits[-1]
            assert b.wait_s("a") == 0
            b.failed("a")
        assert waits == [1.0, 2.0, 4.0, 8.0, 8.0, 8.0]  # doubling, capped
        assert b.wait_s("b") == 0  # another address is not held back
    bursts = [r for r in caplog.records if "failed" in r.getMessage()]
    assert len(bursts) == 1 and "4 failed authentication attempts from a" in bursts[0].getMessage()
    b.succeeded("a")
    assert b.wait_s("a") == 0
    for _ in range(4):
        b.failed("c")
    clock.t += 100.0  # forgotten after forget_s
    assert b.wait_s("c") == 0
    for i in range(50):  # a spray of addresses: memory stays bounded, the latest kept
        b.failed(f"10.0.0.{i}")
    assert b.remembered == 4
    v6 = AuthBackoff(free=1, clock=clock)
    v6.failed("2001:db8:1:2::17")
    v6.failed("2001:db8:1:2:ffff::1")  # the same /64: one host may use any address in it
    assert v6.wait_s("2001:db8:1:2::99") > 0 and v6.wait_s("2001:db8:1:3::17") == 0
    v6.failed("::ffff:10.0.0.7")
    v6.failed("10.0.0.7")  # IPv4-mapped counts as the IPv4 address
    assert v6.wait_s("10.0.0.7") > 0
    with pytest.raises(ValueError, match="base_delay_s"):
        AuthBackoff(base_delay_s=0)


# ---- a real server ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("backoff")
    cell = root / "cell.toml"
    cell.write_text(SMALL_CELL_TOML)
    token_file = root / "token"
    token_file.write_text(TOKEN + "\n")
    srv = ServeProcess(
        root / "data",
        "--camera",
        f"sim:{cell}",
        "--opcua",
        "127.0.0.1:0",
        "--token-file",
        str(token_file),
    )
    srv.opcua_url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]  # type: ignore[attr-defined]
    try:
        yield srv
    finally:
        srv.stop()


def tcp_auth(port: int, token: str, source: str = "127.0.0.1") -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=20, source_address=(source, 0)) as s:
        s.sendall(f"AUTH {token}\n".encode())
        return s.makefile("rb").readline()


def hammer(attempt, seconds: float) -> tuple[int, int]:
    """Wrong attempts for ``seconds`` as fast as one client goes: (attempts, judged ones)."""
    n = judged = 0
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        n += 1
        judged += attempt()
    return n, judged


def max_judged(seconds: float) -> int:
    """The free failures, then one per doubling delay (1, 2, 4 … s) within ``seconds``, plus one."""
    k, t = 0, 0.0
    while t <= seconds:
        t += BASE_DELAY_S * 2**k
        k += 1
    return FREE_FAILURES + 1 + k


def judged_now(attempt) -> None:
    """Wrong attempts until one is judged (a failure counted): the next hold (≥ 2 s after the free
    failures) starts then, so a request sent at once falls in it whatever the machine's load."""
    deadline = time.monotonic() + 70  # the longest hold is 60 s
    while not attempt():
        assert time.monotonic() < deadline, "no attempt judged within the longest hold"
        time.sleep(0.02)


@pytest.mark.long
def test_tcp_auth_is_held_back_and_the_right_token_works_from_elsewhere(server):
    def attempt() -> int:
        reply = tcp_auth(server.tcp_port, "a-wrong-guess", source="127.0.0.4")
        assert reply.startswith(b"ERR send 'AUTH <token>' first"), reply  # -14 in the ur format
        return b"too many failed attempts" not in reply

    n, judged = hammer(attempt, 3.0)
    assert n > 3 * judged and judged <= max_judged(3.0), (n, judged)
    judged_now(attempt)  # a hold just begun: the hammer may end as the last one runs out
    held = tcp_auth(server.tcp_port, TOKEN, source="127.0.0.4")
    assert b"too many failed attempts from 127.0.0.4" in held  # the right token, unjudged
    assert tcp_auth(server.tcp_port, TOKEN, source="127.0.0.2") == b"OK\n"
    print(f"\nTCP AUTH: {n} wrong attempts in 3 s from one address, {judged} judged")


def test_http_401_is_held_back_and_the_right_token_works_from_elsewhere(server):
    guesser = httpx.HTTPTransport(local_address="127.0.0.5")
    with httpx.Client(base_url=server.url, transport=guesser, timeout=20) as c:

        def attempt() -> int:
            r = c.get("/api/calibrations", headers={"Authorization": "Bearer a-wrong-guess"})
            assert r.status_code in (401, 429) and r.json()["field"] == "Authorization", r.text
            if r.status_code == 429:
                assert 1 <= int(r.headers["Retry-After"]) <= 60
            return r.status_code == 401

        n, judged = hammer(attempt, 3.0)
        assert n > 3 * judged and judged <= max_judged(3.0), (n, judged)
        judged_now(attempt)  # a hold just begun: the hammer may end as the last one runs out
        ok = {"Authorization": f"Bearer {TOKEN}"}
        assert c.get("/api/calibrations", headers=ok).status_code == 429  # held back, unjudged
    other = httpx.HTTPTransport(local_address="127.0.0.2")
    with httpx.Client(base_url=server.url, transport=other, timeout=20) as c:
        assert c.get("/api/calibrations", headers=ok).status_code == 200
    print(f"\nHTTP: {n} wrong tokens in 3 s from one address, {judged} judged (401), the rest 429")


def test_opcua_user_token_is_held_back(server):
    """asyncua's Client, a wrong password again and again: after the free failures the right one is
    refused too (held back, unjudged), and TCP AUTH from the same address is held back as well (one
    count for every interface); another address authenticates on TCP at once."""
    from asyncua import Client
    from asyncua.ua.uaerrors import BadUserAccessDenied

    async def login(password: str) -> bool:
        client = Client(server.opcua_url, timeout=10)
        client.set_user("eyetohand")
        client.set_password(password)
        try:
            await client.connect()
        except BadUserAccessDenied:
            return False
        await client.disconnect()
        return True

    async def run() -> None:
        for _ in range(FREE_FAILURES + 1):
            assert not await login("a-wrong-guess")
        assert not await login(TOKEN)  # held back: not judged

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    asyncio.run(run())
    assert b"too many failed attempts" in tcp_auth(server.tcp_port, TOKEN)
    assert tcp_auth(server.tcp_port, TOKEN, source="127.0.0.3") == b"OK\n"


def test_no_token_tried_is_not_counted(server):
    """A first line that is not AUTH (a robot program without the token) and HTTP requests without a
    token are refused but are no guesses: many of them leave the address free for the right token."""
    for _ in range(3 * FREE_FAILURES):
        with socket.create_connection(
            ("127.0.0.1", server.tcp_port), timeout=20, source_address=("127.0.0.6", 0)
        ) as s:
            s.sendall(b"600,900\n")
            assert s.makefile("rb").readline() == b"ERR send 'AUTH <token>' first; closing\n"
    assert tcp_auth(server.tcp_port, TOKEN, source="127.0.0.6") == b"OK\n"
    with httpx.Client(base_url=server.url, transport=httpx.HTTPTransport(local_address="127.0.0.6")) as c:
        for _ in range(3 * FREE_FAILURES):
            assert c.get("/api/calibrations").status_code == 401
        assert c.get("/api/calibrations", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
