"""The TCP line service's per-line path (issue 29): a mapping line skips the command-word lookup,
and a connection's idle limit is one timer, not one armed and cancelled per read. Each answer is
:func:`answer`'s, word for word."""

from __future__ import annotations

import asyncio
import time

import pytest
from helpers import PAPER

from eyetohand import calibrate, load_pairs
from eyetohand.cell import LineReplies
from eyetohand.core import output_units
from eyetohand.positioning import LineServer, answer

LINES = [
    b"600,900",
    b"600,900,0",
    b"600.5,900.25",
    b"-600,900",
    b"+600,900",
    b".5,900",
    b"600,900,a=30",
    b"600,900,sigma",
    b"600,900,allow",
    b"5000,5000",
    b"5000,5000,allow",
    b"600,nan",
    b"600,inf",
    b"6_00,900",
    b"600",
    b"600,900,1,2",
    b"600,,900",
    b"600,900,z=1",
    b"-",
    b"1e400,2",
    b"",
    b" 600,900",
    b"600,900 ",
]


@pytest.fixture(scope="module")
def cal():
    return calibrate(load_pairs(PAPER / "calibration_points.csv"), model="homography", optimizer="lm")


async def _ask(srv: LineServer, lines: list[bytes]) -> list[bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
    writer.write(b"".join(line + b"\n" for line in lines))
    out = [await asyncio.wait_for(reader.readline(), 10) for _ in lines]
    writer.close()
    return out


@pytest.mark.parametrize(
    "fmt,units", [("plain", ("mm", "deg")), ("plain", ("m", "rad")), ("ur", ("mm", "deg"))]
)
def test_every_line_gets_answers_words(cal, fmt, units):
    replies = LineReplies(fmt, output_units(*units))

    async def run() -> list[bytes]:
        srv = LineServer(cal, "127.0.0.1", 0, reply_format=fmt, units=output_units(*units))
        await srv.start()
        try:
            return await _ask(srv, LINES)
        finally:
            srv.close()

    got = asyncio.run(run())
    want = [replies.wire(answer(cal, line, replies)) for line in LINES]
    assert got == want
    assert got[0].count(b",") == (2 if fmt == "plain" else 5)


def test_a_command_named_like_a_number_still_gets_its_lines(cal):
    """The word lookup is skipped for lines starting with a digit, sign or point only while no
    command word starts so."""

    async def run() -> list[bytes]:
        srv = LineServer(cal, "127.0.0.1", 0, commands={"1": lambda line: f"OK one {line}"})
        await srv.start()
        try:
            return await _ask(srv, [b"1 x", b"600,900"])
        finally:
            srv.close()

    one, mapped = asyncio.run(run())
    assert one == b"OK one 1 x\n"
    assert mapped == answer(cal, b"600,900")


def test_a_connections_lines_arm_one_timer(cal):
    """``asyncio.timeout`` around each read armed (and cancelled) a timer for every line, ~10 µs of
    a line's ~80 µs round trip; a connection's idle limit is now one timer, moved by each read."""

    async def run() -> int:
        loop = asyncio.get_running_loop()
        armed = []
        call_at = loop.call_at

        def counted(when, callback, *args, **kw):
            armed.append(when)
            return call_at(when, callback, *args, **kw)

        srv = LineServer(cal, "127.0.0.1", 0, idle_s=300.0)
        await srv.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"600,900\n")
            await reader.readline()
            loop.call_at = counted  # type: ignore[method-assign]
            for _ in range(500):
                writer.write(b"600,900\n")
                assert (await reader.readline()).count(b",") == 2
            writer.close()
            return len(armed)
        finally:
            loop.call_at = call_at  # type: ignore[method-assign]
            srv.close()

    assert asyncio.run(run()) <= 5


def test_the_idle_limit_still_closes_and_a_close_still_cancels(cal):
    async def run() -> None:
        srv = LineServer(cal, "127.0.0.1", 0, idle_s=0.3, first_line_s=0.2)
        await srv.start()
        try:
            # silent from the start: the first-line limit; after a line: the idle limit
            for first, want, least_s in (
                (None, b"ERR no line for 0.2 s; closing\n", 0.15),
                (b"600,900\n", b"ERR idle for 0.3 s; closing\n", 0.25),
            ):
                reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
                if first is not None:
                    writer.write(first)
                    assert (await reader.readline()).count(b",") == 2
                t0 = time.monotonic()
                assert await asyncio.wait_for(reader.readline(), 5) == want
                assert least_s < time.monotonic() - t0 < 2.0
                writer.close()
            # a connection waiting on its read is closed, without an ERR line, when its task is cancelled
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"600,900\n")
            await reader.readline()
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            assert all(t.done() for t in tasks)
            assert await asyncio.wait_for(reader.read(), 5) == b""  # closed, no "ERR idle" line
            writer.close()
        finally:
            srv.close()

    asyncio.run(run())
