"""The positioning service's line protocol over TCP (asyncio).

A client sends one line per point, ``u,v`` or ``u,v,z`` (pixels, and the object's height in mm),
ended by ``\n``; the server answers ``x,y,z`` (robot mm, full precision) or ``ERR <reason>``, one
line per line, in order. Lines longer than :data:`MAX_LINE` bytes are refused and the connection is
closed (the stream cannot be trusted after that). With a token, the first line must be
``AUTH <token>`` (answered ``OK``; anything else gets ``ERR`` and the connection closes), within
``auth_s`` seconds; without a token an ``AUTH`` line is answered ``OK`` (nothing to check). Idle
connections close after ``idle_s`` seconds; at most ``max_clients`` connections are served at once
and at most ``max_per_peer`` from one address (others get ``ERR busy`` and are closed), shared fairly
(:class:`eyetohand.positioning.limits.Slots`): when all are taken, a connection from an address
holding fewer takes the slot of the longest idle connection of the address holding the most, so idle
sockets from a few addresses cannot lock the robot out. The command pool is shared the same way: with
:data:`MAX_PENDING` commands waiting, one from an address with fewer waiting takes the place of the
newest not yet started of the address with the most (that one is answered ``ERR busy``).
A last line cut off by the end of the stream (no newline) is not answered: it may be incomplete.
Wrong tokens are held back per source address (``auth_backoff``, :class:`eyetohand.core.AuthBackoff`).

``VERSION`` answers what is in force: ``OK <name>,<version>,<created_utc>`` for a stored calibration,
``OK <path>,<sha256 of the file>`` for a file. A stored calibration is followed: the service polls
the database every :data:`POLL_S` seconds (off the event loop), so a new version or a rollback takes
effect within a second and a deleted calibration answers ``ERR calibration '<name>' was deleted``.
"""

from __future__ import annotations

import asyncio
import contextvars
import math
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import cast

import numpy as np

from eyetohand.calibration import Calibration
from eyetohand.cell import (
    PLAIN_REPLIES,
    CommandError,
    ErrorCode,
    LineReplies,
    Refusal,
    ascii_reason,
    line_count,
    line_numbers,
)
from eyetohand.core import (
    MM_DEG,
    Actor,
    AuthBackoff,
    InputError,
    OutputUnits,
    Role,
    TokenTable,
    acting_as,
    current_actor,
)
from eyetohand.geometry import check_symmetry
from eyetohand.positioning.limits import BACKLOG, Limit, Slots
from eyetohand.positioning.locate import NO_CAMERA
from eyetohand.positioning.served import FixedCalibration, Served

MAX_LINE = 256
AUTH_FIRST = "send 'AUTH <token>' first; closing"
"""The refusal of a connection that did not authenticate (code AUTH, -14 in ``ur``)."""
MAX_CLIENTS = 256
MAX_PER_PEER = 64
IDLE_S = 300.0
AUTH_S = 10.0
FIRST_LINE_S = 10.0
"""A connection that has not sent one whole line this long after connecting is closed: idle sockets
(a port scanner, a stuck client) do not hold a slot for :data:`IDLE_S`."""
ROBOT_SLOTS = 8
"""Connections from a ``robot_addresses`` address are served beyond :data:`MAX_CLIENTS` (up to this many),
so no flood from elsewhere locks the robot out."""
MAX_PENDING = 8
"""CAL/BELT commands waiting or running at once (each may grab for a second); one more is answered
``ERR busy`` at once and never delays the others."""
COMMAND_WORKERS = 4
WRITE_HIGH = 16 * 1024
"""Bytes of answers a connection may have waiting to be sent; above it, its lines are not read until
the client reads (a client that never reads stops itself, nobody else)."""
BURST = 8
"""Lines answered for one connection before the event loop serves the others (a client pipelining
thousands of lines in one read must not hold every other client for seconds)."""
MISSING = {  # a command word of a service this server was not started with -> why it is refused
    "CAL": "no camera: start eyetohand serve with --camera URI to use CAL",
    "BELT": "no conveyor: start eyetohand serve with --conveyor FILE to use BELT",
    "LOCATE": NO_CAMERA.reason,  # the words Modbus and OPC UA give too (positioning/locate.py)
}


USAGE = "send u,v[,z][,a=ANGLE][,s=N][,t=DEG][,d=DIAMETER][,allow][,sigma] or VERSION"
TOO_LONG = f"line longer than {MAX_LINE} bytes; closing"
POLL_S = 0.25


class _Poller:
    """Polls the served calibration every ``poll_s`` on a thread of its own (with its own SQLite
    connection: the store keeps one per thread), so the freshness of what the mapping lines use never
    waits behind other work — commands queued for the camera, HTTP requests."""

    def __init__(self, server: LineServer, poll_s: float):
        self.server, self.poll_s = server, poll_s
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name="eyetohand-tcp-poll", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            self._wake.wait(self.poll_s)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self.server.source.poll()
            except Exception:  # noqa: BLE001 - a poll that breaks is tried again, never ends the thread
                pass

    def wake(self) -> None:
        """Poll now rather than at the end of the wait (a change notified by the store)."""
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()


def answer(cal: Calibration, line: bytes, replies: LineReplies = PLAIN_REPLIES) -> bytes:
    """The reply to one request line (without its newline), worded by ``replies`` (the server's reply
    format and units: :mod:`eyetohand.cell.replies`; a given z is in its units).

    ``u,v[,z]`` → ``x,y,z`` (mm). Optional words after the numbers, as ``apply`` and the HTTP API take
    them: ``a=ANGLE`` (the image angle, deg from +u towards +v) adds ``,rz``; ``s=N`` folds rz for a part
    symmetric under 360/N turns; ``t=DEG`` (the gripper's rz when aligned with the image's +u) makes rz
    the gripper's command; ``d=DIAMETER`` (the circular part's diameter, in the line's length unit as z)
    corrects its detected centre for a calibration of circle centres (``Calibration.map``'s
    ``part_diameter_mm``; 0: the pixel is the point's own image); ``sigma`` adds ``,sigma_mm``;
    ``allow`` maps a point outside the calibrated region too, and such an answer ends with
    ``,OUTSIDE``. Numbers are plain decimals (``6_00`` is not one, as in the library's loaders).
    Refusals: ``ERR <reason>`` (``ERR outside the calibrated region: ...`` for a point beyond the
    margin).
    """
    parts_b = line.split(b",")
    if 2 <= len(parts_b) <= 3 and b"_" not in line:  # the common line, numbers only: as the general path
        try:
            vals = [float(p) for p in parts_b]
        except ValueError:
            pass
        else:
            if all(map(math.isfinite, vals)):
                return _mapped_line(cal, vals, {}, replies)
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        return replies.refusal(_usage("not ASCII text"))
    if not text:
        return replies.refusal(_usage("empty line"))
    parts = [p.strip() for p in text.split(",")]
    nums = [p for p in parts if "=" not in p and p.lower() not in ("allow", "sigma")]
    words = [p.lower() for p in parts[len(nums) :]]
    if parts[: len(nums)] != nums or len(nums) not in (2, 3):
        return replies.refusal(
            _usage(f"{len(nums)} numbers; expected 2 or 3 (u,v or u,v,z) before any words")
        )
    vals = []
    for name, p in zip("uvz", nums, strict=False):
        x, err = _number(name, p, replies)
        if err:
            return err
        vals.append(x)
    opts: dict = {}
    for w in words:
        key, _, text_value = w.partition("=")
        option = w if w in ("allow", "sigma") else _WORDS.get(key)
        if option is None:
            return replies.refusal(_usage(f"unknown word {w[:20]!r}"))
        if option in opts:
            return replies.refusal(_usage(f"{key} given twice"))  # which one was meant is not guessed
        if w in ("allow", "sigma"):
            opts[w] = True
            continue
        x, err = _number(key, text_value, replies)
        if err:
            return err
        opts[_WORDS[key]] = x
    return _mapped_line(cal, vals, opts, replies)


_WORDS = {"a": "angle_deg", "s": "symmetry", "t": "tool_rz_offset_deg", "d": "part_diameter_mm"}


def _usage(what: str) -> Refusal:
    """A malformed mapping line's refusal: what is wrong, then how a line goes."""
    return Refusal(ErrorCode.OTHER, f"{what}; {USAGE}")


def _number(name: str, text: str, replies: LineReplies) -> tuple[float, bytes | None]:
    """A finite plain decimal, or the reply that refuses it: the rule and words of every line
    protocol's numbers (:func:`eyetohand.cell.line_numbers`)."""
    try:
        return line_numbers([text], (name,), None)[0], None
    except CommandError as exc:
        return 0.0, replies.refusal(Refusal(exc.code, str(exc)))


def _mapped_line(cal: Calibration, vals: list[float], opts: dict, replies: LineReplies) -> bytes:
    z = replies.z_in(vals[2]) if len(vals) == 3 else None
    want_sigma = bool(opts.get("sigma"))
    try:
        # "2.0" is 2, as on BELT lines; none given is 1, which needs no check
        symmetry = check_symmetry(line_count(opts["symmetry"])) if "symmetry" in opts else 1
        with np.errstate(all="ignore"):
            m = cal.map(
                np.array([vals[:2]]),
                z,
                angle_deg=opts.get("angle_deg"),
                allow_outside=bool(opts.get("allow")),
                symmetry=symmetry,
                tool_rz_offset_deg=opts.get("tool_rz_offset_deg"),
                with_sigma=want_sigma,
                part_diameter_mm=replies.z_in(opts.get("part_diameter_mm")),  # the line's length unit
            )
    except InputError as exc:
        return replies.refused(exc)
    return replies.mapped(
        m.xyz_mm[0].tolist(),  # Python floats (not a NumPy scalar per coordinate)
        None if m.rz_deg is None else m.rz_deg[0],
        m.sigma_mm[0] if want_sigma and m.sigma_mm is not None else None,
        bool(m.inside[0]),
    )


def _busy(reason: str) -> Refusal:
    return Refusal(ErrorCode.BUSY, reason)


class _Lines:
    """Splits a byte stream into lines: CR, LF and CR LF each end one line (a KAREL robot may send CR
    only), CR LF also when the CR ends one read and the LF starts the next."""

    def __init__(self) -> None:
        self.buf = b""
        self.skip_lf = False  # the last line ended with a CR at the end of a read: a LF next is its end

    def feed(self, data: bytes) -> None:
        if self.skip_lf and data:
            self.skip_lf = False
            if data[:1] == b"\n":
                data = data[1:]
        self.buf += data

    def next(self) -> bytes | None:
        """The next whole line without its end, or None until more comes."""
        buf = self.buf
        cr, lf = buf.find(b"\r"), buf.find(b"\n")
        if cr < 0 and lf < 0:
            return None
        i = lf if cr < 0 or 0 <= lf < cr else cr
        line, rest = buf[:i], buf[i + 1 :]
        if buf[i : i + 1] == b"\r":
            if rest[:1] == b"\n":
                rest = rest[1:]
            elif not rest:
                self.skip_lf = True
        self.buf = rest
        return line


class LineServer:
    """Serve ``cal`` on ``host:port``. ``await start()``, then ``await serve_forever()`` or ``close()``.

    ``commands``: first word (upper case) -> handler(line) -> reply without line end, run on a pool of
    :data:`COMMAND_WORKERS` threads of its own (a command may grab and detect for a second), at most
    ``max_pending`` at once (more: ``busy_replies[word](reason)``, else ``ERR busy: …``).
    ``robot_addresses``: addresses served beyond ``max_clients`` (up to :data:`ROBOT_SLOTS`
    connections). ``first_line_s``: a connection without a whole line this long after connecting is
    closed."""

    def __init__(
        self,
        cal: Calibration | Served,
        host: str,
        port: int,
        *,
        max_clients: int = MAX_CLIENTS,
        backlog: int = BACKLOG,
        idle_s: float = IDLE_S,
        token: str | TokenTable | None = None,
        command_roles: dict[str, Role] | None = None,
        max_per_peer: int = MAX_PER_PEER,
        auth_s: float = AUTH_S,
        poll_s: float = POLL_S,
        commands: dict[str, Callable[[str], str]] | None = None,
        busy_replies: dict[str, Callable[[str], str]] | None = None,
        max_pending: int = MAX_PENDING,
        robot_addresses: tuple[str, ...] | list[str] = (),
        first_line_s: float = FIRST_LINE_S,
        reply_format: str = "plain",
        units: OutputUnits = MM_DEG,
        auth_backoff: AuthBackoff | None = None,
    ):
        self.replies = LineReplies(reply_format, units)  # how every reply is worded (cell/replies.py)
        # failed AUTH per address (serve shares one with HTTP and OPC UA)
        self.auth_backoff = AuthBackoff() if auth_backoff is None else auth_backoff
        self.source: Served = FixedCalibration(cal) if isinstance(cal, Calibration) else cal
        self.poll_s = poll_s
        self._poller: _Poller | None = None
        self.commands = {k.upper(): f for k, f in (commands or {}).items()}
        self._numeric_words = any(
            k[:1] in _NUMBER_START.decode() for k in (*self.commands, *MISSING)
        )  # ('' is in any string: a command named '' takes the empty line, as before)
        self.busy_replies = {k.upper(): f for k, f in (busy_replies or {}).items()}
        self.max_pending = max_pending
        self._queued: dict[Future, str] = {}  # the commands waiting or running -> their address
        self._pool: ThreadPoolExecutor | None = None
        self.auth_s = auth_s
        # every named token (AUTH with any; the connection then acts as its holder: the audit names it)
        self.tokens = TokenTable.of(token)
        self.command_roles = {k.upper(): r for k, r in (command_roles or {}).items()}
        self.host = host
        self.port = port
        self.idle_s = idle_s
        self.first_line_s = first_line_s
        self.robot_addresses = frozenset(robot_addresses)
        self.backlog = backlog
        self.slots = Slots(
            f"TCP {host}:{port}",
            Limit(max_clients, max_per_peer, backlog),
            reserved=self.robot_addresses,
            reserved_slots=ROBOT_SLOTS,
        )
        self.server: asyncio.AbstractServer | None = None

    @property
    def max_per_peer(self) -> int:
        return self.slots.limit.per_address

    @property
    def clients(self) -> int:
        """Connections served now (beside the robot's reserved ones)."""
        return self.slots.count

    @property
    def robots(self) -> int:
        return self.slots.robots

    @property
    def per_peer(self) -> dict[str, int]:
        """Connections served now per source address."""
        return {a: len(c) for a, c in self.slots.by_address.items()}

    @property
    def pending(self) -> int:
        """Commands waiting for a worker or running."""
        return len(self._queued)

    async def start(self) -> None:
        self.server = await asyncio.start_server(
            self._client, self.host, self.port, limit=MAX_LINE, backlog=self.backlog
        )
        self.port = self.server.sockets[0].getsockname()[1]
        self.slots.what = self.slots.log.what = f"TCP {self.host}:{self.port}"
        self._poller = _Poller(self, self.poll_s)

    def wake(self) -> None:
        """Poll the served calibration now (callable from any thread): the store said something
        changed (``serve`` wires its follower's notifications here); the timed poll stays, as the
        fallback."""
        if self._poller is not None:
            self._poller.wake()

    def follow(self, source: Served, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Serve (and follow) ``source`` from now on: after a collection created the calibration.
        Callable from any thread (``loop`` is not needed any more: the poller reads :attr:`source`)."""
        self.source = source

    @property
    def cal(self) -> Calibration | None:
        """The calibration in force (None while a followed one is deleted)."""
        return self.source.cal

    def reply(self, line: bytes) -> bytes:
        """The answer to one line with the calibration in force (``VERSION`` names it)."""
        src = self.source
        problem = src.problem()
        cal = src.cal
        if problem is None and cal is None:  # a Served that says nothing is wrong but has nothing
            problem = Refusal(ErrorCode.NO_CALIBRATION, "no calibration to map with")
        if problem is not None:
            return self.replies.refusal(Refusal(problem.code, ascii_reason(problem.reason)))
        if line.strip().upper() == b"VERSION":
            return src.version_line().encode("ascii", "replace") + b"\n"
        assert cal is not None
        return answer(cal, line, self.replies)

    async def serve_forever(self) -> None:
        assert self.server is not None
        async with self.server:
            await self.server.serve_forever()

    def close(self) -> None:
        if self._poller is not None:
            self._poller.stop()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
        if self.server is not None:
            self.server.close()

    async def _command(self, word: str, line: bytes, addr: str) -> bytes:
        """A CAL/BELT command's reply, run on the command pool; refused at once when it is full and
        no address holds two more places than ``addr`` (:meth:`_take_place`)."""
        handler = self.commands[word]
        if len(self._queued) >= self.max_pending and not self._take_place(addr):
            return self._busy_reply(
                word, f"busy: {self.pending} commands are waiting for the camera or conveyor; try again later"
            )
        if self._pool is None:
            self._pool = ThreadPoolExecutor(COMMAND_WORKERS, thread_name_prefix="eyetohand-cmd")
        ctx = contextvars.copy_context()  # the command acts as the connection's token holder
        fut = self._pool.submit(ctx.run, handler, line.decode("ascii", "replace"))
        self._queued[fut] = addr
        try:
            reply = await asyncio.wrap_future(fut)
        except asyncio.CancelledError:
            task = asyncio.current_task()
            if not fut.cancelled() or (task is not None and task.cancelling()):
                raise  # the server is closing
            return self._busy_reply(
                word, "busy: this command's place went to another address's; try again later"
            )
        finally:
            self._queued.pop(fut, None)
        return reply.encode("ascii", "replace") + b"\n"

    def _take_place(self, addr: str) -> bool:
        """Free a place in the full command pool for ``addr``: cancel the newest command not yet
        started of the address with the most waiting, when that is at least two more than ``addr``'s
        (its own task answers it ``ERR busy``)."""
        held: dict[str, list[Future]] = {}
        for f, a in self._queued.items():
            held.setdefault(a, []).append(f)
        mine = len(held.get(addr, ()))
        for futs in sorted(held.values(), key=len, reverse=True):
            if len(futs) < mine + 2:
                return False
            for f in reversed(futs):
                if f.cancel():  # not started yet
                    del self._queued[f]
                    return True
        return False

    def _busy_reply(self, word: str, reason: str) -> bytes:
        busy = self.busy_replies.get(word)
        reply = busy(reason) if busy is not None else self.replies.refusal_line(_busy(reason), word)
        return reply.encode("ascii", "replace") + b"\n"

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.replies.ur:  # every line this connection is sent goes through the ur format
            writer = cast(asyncio.StreamWriter, _Worded(writer, self.replies))
        peer = writer.get_extra_info("peername")
        addr = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        client = _Client(self, writer)
        refused = self.slots.admit(addr, client)
        if refused is not None:
            writer.write(self.replies.refusal(refused))
            await _close(writer)
            return
        writer.transport.set_write_buffer_limits(high=WRITE_HIGH)
        lines = _Lines()
        try:
            actor = await self._auth(reader, writer, lines, addr) if self.tokens else current_actor()
            if actor is None:
                return
            with acting_as(actor):
                await self._serve_lines(reader, writer, lines, client, addr)
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.slots.release(addr, client)
            await _close(writer)

    async def _serve_lines(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, lines, client: _Client, addr: str
    ) -> None:
        spoken = bool(self.tokens)  # AUTH was the first line
        burst = 0
        idle = _IdleLimit(client)
        # a mapping line (a digit, sign or point first) names no command: its word is not looked up
        worded = isinstance(writer, _Worded) or self._numeric_words
        try:
            while True:
                line = lines.next()
                if line is None:
                    if len(lines.buf) > MAX_LINE:
                        writer.write(self._refusal(writer, ErrorCode.LINE_TOO_LONG, TOO_LONG))
                        return
                    wait_s = self.idle_s if spoken else min(self.idle_s, self.first_line_s)
                    data = await idle.read(reader, wait_s)
                    if data is None:
                        what = "idle" if spoken else "no line"
                        writer.write(
                            self._refusal(writer, ErrorCode.IDLE, f"{what} for {wait_s:g} s; closing")
                        )
                        return
                    if not data:
                        return  # end of stream; a last line without its end may be cut: no answer
                    lines.feed(data)
                    continue
                spoken = True
                if len(line) > MAX_LINE:
                    writer.write(self._refusal(writer, ErrorCode.LINE_TOO_LONG, TOO_LONG))
                    return
                if not worded and line[:1] in _NUMBER_START:
                    writer.write(self.reply(line))
                else:
                    word = line.split(None, 1)[0].upper().decode("ascii", "replace") if line.strip() else ""
                    if isinstance(writer, _Worded):
                        writer.kind = word  # the ur count of this line's replies (CAL's 4, others' 6)
                    if (
                        word == "AUTH"
                    ):  # a program that always sends its token: checked again (OK without one)
                        if not self._token_ok(line):
                            writer.write(self._refusal(writer, ErrorCode.AUTH, AUTH_FIRST))
                            return
                        writer.write(b"OK\n")
                    elif word in self.commands and (why := self._role_refusal(word)) is not None:
                        writer.write(self._refusal(writer, ErrorCode.AUTH, why))
                    elif word in self.commands:
                        writer.write(await self._command(word, line, addr))
                    elif word in MISSING:
                        writer.write(self._refusal(writer, ErrorCode.NOT_SERVED, MISSING[word]))
                    else:
                        writer.write(self.reply(line))
                # returns at once unless this client's unsent answers are over WRITE_HIGH: then only this
                # client waits (its lines are not read meanwhile), nobody else
                await writer.drain()
                burst += 1
                if burst >= BURST:  # let the other clients in between a pipelining client's lines
                    burst = 0
                    await asyncio.sleep(0)
        finally:
            idle.close()

    def _refusal(self, writer, code: ErrorCode, reason: str) -> bytes:
        """One of the service's own refusals, worded for ``writer``'s connection (in ``ur``, in the count
        of its last command word)."""
        kind = writer.kind if isinstance(writer, _Worded) else ""
        return self.replies.refusal(Refusal(code, reason), kind)

    async def _auth(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, lines: _Lines, addr: str
    ) -> Actor | None:
        """The holder of the token of the connection's first line ``AUTH <token>``, or None (refused)."""
        line = b""
        try:
            async with asyncio.timeout(min(self.auth_s, self.idle_s)):
                while (got := lines.next()) is None and len(lines.buf) <= MAX_LINE:
                    data = await reader.read(4096)
                    if not data:
                        break
                    lines.feed(data)
                line = got or b""
        except TimeoutError:
            pass
        if line[:5].upper() != b"AUTH ":
            writer.write(self.replies.refusal(Refusal(ErrorCode.AUTH, AUTH_FIRST)))
            return None  # no token tried (nothing said, or another line first): not counted
        wait_s = self.auth_backoff.wait_s(addr)
        if wait_s > 0:  # too many failures from this address: refused without looking at the token
            why = (
                f"send 'AUTH <token>' first: too many failed attempts from {addr}, the next is "
                f"judged in {math.ceil(wait_s)} s; closing"
            )
            writer.write(self.replies.refusal(Refusal(ErrorCode.AUTH, why)))
            return None
        actor = self._holder(line)
        if actor is not None:
            self.auth_backoff.succeeded(addr)
            writer.write(b"OK\n")
            return actor
        self.auth_backoff.failed(addr, "TCP AUTH")
        writer.write(self.replies.refusal(Refusal(ErrorCode.AUTH, AUTH_FIRST)))
        return None

    def _token_ok(self, line: bytes) -> bool:
        """``AUTH <token>`` with one of this server's tokens (any ``AUTH`` line when it has none: a robot
        program that always authenticates talks to a loopback server without a token too); a later
        ``AUTH`` with another holder's token is refused (a connection acts for one holder)."""
        if not self.tokens:
            return True
        return self._holder(line) == current_actor()

    def _holder(self, line: bytes) -> Actor | None:
        """The holder of the token in ``AUTH <token>`` (None: no such token)."""
        given = line.strip()[5:] if line[:5].upper() == b"AUTH " else b""
        return self.tokens.match(given.strip())

    def _role_refusal(self, word: str) -> str | None:
        """Why this connection's holder may not send command ``word`` (``command_roles``), or None."""
        needed = self.command_roles.get(word)
        return None if needed is None else current_actor().refusal(needed, word)


_NUMBER_START = b"0123456789+-."
"""What a mapping line may start with (its u): no command word does (:attr:`LineServer._numeric_words`).
(``line[:1] in _NUMBER_START`` holds for an empty line too, which is answered as before: no word.)"""


class _IdleLimit:
    """A connection's read deadline (``idle_s``, or ``first_line_s`` before its first line) with one
    timer for the connection instead of one per read: ``asyncio.timeout`` around each read armed a
    timer and cancelled it for every line (~10 µs of a line's ~80 µs round trip on the 2-core test
    machine; tests/test_tcp_per_line.py counts the timers). Here a read only moves the
    deadline; the timer, when it fires early, re-arms itself for the deadline, and at the deadline
    cancels the reading task — as ``asyncio.timeout`` does: a cancellation from elsewhere (the server
    closing) stays a cancellation."""

    def __init__(self, client: _Client) -> None:
        self.client = client  # its last_active moves with every read (the fair share's "longest idle")
        self.loop = asyncio.get_running_loop()
        self.task = asyncio.current_task()
        self.deadline = 0.0
        self.reading = False
        self.expired = False
        self.timer: asyncio.TimerHandle | None = None

    def _fire(self) -> None:
        self.timer = None
        if not self.reading:
            return  # the next read arms it again
        if self.loop.time() < self.deadline:
            self.timer = self.loop.call_at(self.deadline, self._fire)
            return
        self.expired = True
        assert self.task is not None
        self.task.cancel()

    async def read(self, reader: asyncio.StreamReader, wait_s: float) -> bytes | None:
        """Up to 4096 bytes (b"" at the end of the stream), or None when none came within ``wait_s``."""
        now = self.loop.time()
        self.client.last_active = now
        self.deadline = now + wait_s
        if self.timer is None:
            self.timer = self.loop.call_at(self.deadline, self._fire)
        elif self.timer.when() > self.deadline:  # a shorter wait than the armed one
            self.timer.cancel()
            self.timer = self.loop.call_at(self.deadline, self._fire)
        self.reading = True
        try:
            return await reader.read(4096)
        except asyncio.CancelledError:
            assert self.task is not None
            if self.expired and self.task.uncancel() == 0:
                return None
            raise
        finally:
            self.reading = False

    def close(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None


class _Client:
    """A connection as :class:`~eyetohand.positioning.limits.Slots` sees it: when it last read, and
    how it is closed when its slot goes to another address (``ERR busy: …``, then closed)."""

    __slots__ = ("server", "writer", "last_active")

    def __init__(self, server: LineServer, writer: asyncio.StreamWriter):
        self.server, self.writer = server, writer
        self.last_active = asyncio.get_running_loop().time()

    def evictable(self) -> bool:
        return True  # (a command running goes on in its worker; its answer finds the line closed)

    def evict(self, reason: Refusal) -> None:
        self.writer.write(self.server._refusal(self.writer, reason.code, reason.reason))
        self.writer.transport.close()  # the reading task sees the end of the stream and ends


class _Worded:
    """A connection's writer that sends every reply through the server's
    :meth:`~eyetohand.cell.LineReplies.wire` (``ur``: no line stays text), in the count of the
    connection's last command word (:attr:`kind`); everything else is the writer's."""

    def __init__(self, writer: asyncio.StreamWriter, replies: LineReplies):
        self._writer, self._replies, self.kind = writer, replies, ""

    def write(self, data: bytes) -> None:
        self._writer.write(self._replies.wire(data, self.kind))

    def __getattr__(self, name: str):
        return getattr(self._writer, name)


async def _close(writer: asyncio.StreamWriter) -> None:
    try:
        await writer.drain()
        writer.close()
        await writer.wait_closed()
    except (ConnectionError, asyncio.CancelledError):
        pass


class LoopThread:
    """An event loop of its own, run by a daemon thread: ``eyetohand serve`` puts the line service on
    one, so that the robot's lines never wait behind the workbench's HTTP work (or its server's
    periodic wake-ups) on the main loop. :meth:`call` runs a coroutine there and awaits it from
    another loop; :meth:`stop` (from any thread but its own) cancels what still runs there, then ends
    the thread."""

    def __init__(self, name: str = "eyetohand-tcp"):
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self._thread.start()

    async def call(self, coro):
        """Await ``coro`` run on this loop (from a coroutine on another loop)."""
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    def stop(self, timeout_s: float = 5.0) -> None:
        async def cancel_rest() -> None:
            rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in rest:
                t.cancel()
            await asyncio.gather(*rest, return_exceptions=True)

        if self.loop.is_closed():
            return
        try:
            asyncio.run_coroutine_threadsafe(cancel_rest(), self.loop).result(timeout_s)
        except (TimeoutError, RuntimeError):
            pass
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self.loop.close()
