"""The positioning service's line protocol over TCP (asyncio).

A client sends one line per point, ``u,v`` or ``u,v,z`` (pixels, and the object's height in mm),
ended by ``\n``; the server answers ``x,y,z`` (robot mm, full precision) or ``ERR <reason>``, one
line per line, in order. Lines longer than :data:`MAX_LINE` bytes are refused and the connection is
closed (the stream cannot be trusted after that). With a token, the first line must be
``AUTH <token>`` (answered ``OK``; anything else gets ``ERR`` and the connection closes), within
``auth_s`` seconds. Idle connections close after ``idle_s`` seconds; at most ``max_clients``
connections are served at once and at most ``max_per_peer`` from one address (others get
``ERR busy`` and are closed), so idle sockets from one local process cannot lock the robot out.
A last line cut off by the end of the stream (no newline) is not answered: it may be incomplete.
"""

from __future__ import annotations

import asyncio
import hmac
import math

import numpy as np

from ..calibration import Calibration
from ..errors import InputError

MAX_LINE = 256
MAX_CLIENTS = 256
MAX_PER_PEER = 64
IDLE_S = 300.0
AUTH_S = 10.0


def answer(cal: Calibration, line: bytes) -> bytes:
    """The reply to one request line (without its newline)."""
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        return b"ERR not ASCII text; send u,v[,z]\n"
    if not text:
        return b"ERR empty line; send u,v[,z]\n"
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (2, 3):
        return f"ERR {len(parts)} fields; send u,v[,z]\n".encode()
    vals = []
    for name, p in zip("uvz", parts, strict=False):
        try:
            x = float(p)
        except ValueError:
            return f"ERR {name}: {p[:20]!r} is not a number\n".encode()
        if not math.isfinite(x):
            return f"ERR {name}: {p[:20]!r} is not a finite number\n".encode()
        vals.append(x)
    z = vals[2] if len(vals) == 3 else None
    try:
        with np.errstate(all="ignore"):
            xyz = cal.image_to_robot(np.array([vals[:2]]), z)[0]
    except InputError as exc:
        return f"ERR {str(exc).splitlines()[0][:200]}\n".encode()
    if not np.isfinite(xyz).all():
        return b"ERR the point maps to no finite robot point\n"
    return f"{float(xyz[0])!r},{float(xyz[1])!r},{float(xyz[2])!r}\n".encode()


class LineServer:
    """Serve ``cal`` on ``host:port``. ``await start()``, then ``await serve_forever()`` or ``close()``."""

    def __init__(self, cal: Calibration, host: str, port: int, *, max_clients: int = MAX_CLIENTS,
                 idle_s: float = IDLE_S, token: str | None = None, max_per_peer: int = MAX_PER_PEER,
                 auth_s: float = AUTH_S):
        self.cal = cal
        self.max_per_peer = max_per_peer
        self.auth_s = auth_s
        self.per_peer: dict[str, int] = {}
        self.token = token.encode() if token else None
        self.host = host
        self.port = port
        self.max_clients = max_clients
        self.idle_s = idle_s
        self.clients = 0
        self.server: asyncio.AbstractServer | None = None

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._client, self.host, self.port, limit=MAX_LINE)
        self.port = self.server.sockets[0].getsockname()[1]

    async def serve_forever(self) -> None:
        assert self.server is not None
        async with self.server:
            await self.server.serve_forever()

    def close(self) -> None:
        if self.server is not None:
            self.server.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        addr = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        if self.clients >= self.max_clients:
            writer.write(b"ERR busy: too many clients, try again later\n")
            await _close(writer)
            return
        if self.per_peer.get(addr, 0) >= self.max_per_peer:
            writer.write(f"ERR busy: {self.max_per_peer} connections from {addr} already\n".encode())
            await _close(writer)
            return
        self.clients += 1
        self.per_peer[addr] = self.per_peer.get(addr, 0) + 1
        try:
            if self.token is not None and not await self._auth(reader, writer):
                return
            while True:
                try:
                    line = await asyncio.wait_for(reader.readuntil(b"\n"), self.idle_s)
                except (asyncio.LimitOverrunError, ValueError):
                    writer.write(f"ERR line longer than {MAX_LINE} bytes; closing\n".encode())
                    break
                except asyncio.IncompleteReadError:
                    break  # end of stream; a last line without its newline may be cut: no answer
                except TimeoutError:
                    writer.write(f"ERR idle for {self.idle_s:g} s; closing\n".encode())
                    break
                writer.write(answer(self.cal, line[:-1]))
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.clients -= 1
            left = self.per_peer.get(addr, 1) - 1
            if left > 0:
                self.per_peer[addr] = left
            else:
                self.per_peer.pop(addr, None)
            await _close(writer)

    async def _auth(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> bool:
        try:
            line = await asyncio.wait_for(reader.readuntil(b"\n"), min(self.auth_s, self.idle_s))
        except (asyncio.LimitOverrunError, ValueError, asyncio.IncompleteReadError, TimeoutError):
            line = b""
        given = line.strip()[5:] if line[:5].upper() == b"AUTH " else b""
        if hmac.compare_digest(given.strip(), self.token):
            writer.write(b"OK\n")
            return True
        writer.write(b"ERR send 'AUTH <token>' first; closing\n")
        return False


async def _close(writer: asyncio.StreamWriter) -> None:
    try:
        await writer.drain()
        writer.close()
        await writer.wait_closed()
    except (ConnectionError, asyncio.CancelledError):
        pass
