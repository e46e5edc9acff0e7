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

``VERSION`` answers what is in force: ``OK <name>,<version>,<created_utc>`` for a stored calibration,
``OK <path>,<sha256 of the file>`` for a file. A stored calibration is followed: the service polls
the database every :data:`POLL_S` seconds (off the event loop), so a new version or a rollback takes
effect within a second and a deleted calibration answers ``ERR calibration '<name>' was deleted``.
"""

from __future__ import annotations

import asyncio
import hmac
import math
import threading
from collections.abc import Callable

import numpy as np

from eyetohand.calibration import Calibration
from eyetohand.cell import MAX_REASON, CommandError, ascii_reason, line_count, line_numbers
from eyetohand.core import InputError
from eyetohand.geometry import check_symmetry

MAX_LINE = 256
MAX_CLIENTS = 256
MAX_PER_PEER = 64
IDLE_S = 300.0
AUTH_S = 10.0


USAGE = "send u,v[,z][,a=ANGLE][,s=N][,t=DEG][,allow][,sigma] or VERSION"
POLL_S = 0.25


class FixedCalibration:
    """A calibration that does not change (a file, or one given in code): ``VERSION`` names it."""

    def __init__(self, cal: Calibration, label: str = "calibration", sha256: str = ""):
        self.cal: Calibration | None = cal
        self.error: str | None = None
        self.label = label
        self.sha256 = sha256 or cal.to_dict()["content_sha256"]

    def version_line(self) -> str:
        return f"OK {self.label},{self.sha256}"

    @classmethod
    def from_file(cls, path) -> FixedCalibration:
        import hashlib
        from pathlib import Path

        p = Path(path)
        cal = Calibration.load(p)
        return cls(cal, str(p.resolve()), hashlib.sha256(p.read_bytes()).hexdigest())


class PendingCalibration:
    """Stands in for the served calibration before one exists (``serve --camera`` with a new name):
    every mapping line is one ERR until a collection creates it."""

    def __init__(self, name: str | None):
        self.name = name
        self.cal: Calibration | None = None
        what = f"'{name}' has none yet" if name else "none is served"
        self.error: str | None = (
            f"no calibration to map with: {what}; collect one (CAL BEGIN ... CAL END) "
            "or start serve with --calibration NAME"
        )

    def version_line(self) -> str:
        return f"ERR {self.error}"


class StoredCalibration:
    """The current version of a stored calibration, refreshed by :meth:`poll` (blocking: run it off
    the event loop). A deleted calibration sets ``error``; a database that cannot be read for a moment
    keeps the version in force."""

    def __init__(self, store, cal_id: int):
        self.store = store
        self.cal_id = cal_id
        self.cal: Calibration | None = None
        self.error: str | None = None
        self.name = ""
        self.version = 0
        self.created_utc = ""
        self.poll()
        if self.cal is None:
            raise InputError(self.error or f"no calibration with id {cal_id}")

    def version_line(self) -> str:
        return f"OK {self.name},{self.version},{self.created_utc}"

    def poll(self) -> None:
        from eyetohand.server.storage import NotFound, StorageError

        try:
            now = self.store.current(self.cal_id)
            if now is None:
                self.error = f"calibration '{self.name or self.cal_id}' was deleted"
                self.cal = None
                return
            name, version = now
            self.name = name
            if version == self.version and self.cal is not None:
                return
            ver = self.store.version(self.cal_id, version)
            cal = Calibration.from_dict(ver.calibration, f"calibration {name!r} version {version}")
        except NotFound:
            self.error = f"calibration '{self.name or self.cal_id}' was deleted"
            self.cal = None
            return
        except StorageError:
            return  # keep what is in force; the next poll tries again
        except InputError as exc:
            self.error = f"calibration '{self.name}' version {version} cannot be used: {exc}"[:MAX_REASON]
            self.cal = None
            return
        # one assignment each, read by the event loop between lines (the GIL makes them atomic)
        self.cal, self.version, self.created_utc, self.error = cal, ver.version, ver.created_utc, None


def answer(cal: Calibration, line: bytes) -> bytes:
    """The reply to one request line (without its newline).

    ``u,v[,z]`` → ``x,y,z`` (mm). Optional words after the numbers, as ``apply`` and the HTTP API take
    them: ``a=ANGLE`` (the image angle, deg from +u towards +v) adds ``,rz``; ``s=N`` folds rz for a part
    symmetric under 360/N turns; ``t=DEG`` (the gripper's rz when aligned with the image's +u) makes rz
    the gripper's command; ``sigma`` adds ``,sigma_mm``; ``allow`` maps a point outside the calibrated
    region too, and such an answer ends with ``,OUTSIDE``. Numbers are plain decimals (``6_00`` is not
    one, as in the library's loaders). Refusals: ``ERR <reason>`` (``ERR outside the calibrated region:
    ...`` for a point beyond the margin).
    """
    parts_b = line.split(b",")
    if 2 <= len(parts_b) <= 3 and b"_" not in line:  # the common line, numbers only: as the general path
        try:
            vals = [float(p) for p in parts_b]
        except ValueError:
            pass
        else:
            if all(map(math.isfinite, vals)):
                return _mapped_line(cal, vals, {})
    try:
        text = line.decode("ascii").strip()
    except UnicodeDecodeError:
        return f"ERR not ASCII text; {USAGE}\n".encode()
    if not text:
        return f"ERR empty line; {USAGE}\n".encode()
    parts = [p.strip() for p in text.split(",")]
    nums = [p for p in parts if "=" not in p and p.lower() not in ("allow", "sigma")]
    words = [p.lower() for p in parts[len(nums) :]]
    if parts[: len(nums)] != nums or len(nums) not in (2, 3):
        return f"ERR {len(nums)} numbers; {USAGE}\n".encode()
    vals = []
    for name, p in zip("uvz", nums, strict=False):
        x, err = _number(name, p)
        if err:
            return err
        vals.append(x)
    opts: dict = {}
    for w in words:
        key, _, text_value = w.partition("=")
        option = w if w in ("allow", "sigma") else _WORDS.get(key)
        if option is None:
            return f"ERR unknown word {w[:20]!r}; {USAGE}\n".encode()
        if option in opts:
            return f"ERR {key} given twice; {USAGE}\n".encode()  # which one was meant is not guessed
        if w in ("allow", "sigma"):
            opts[w] = True
            continue
        x, err = _number(key, text_value)
        if err:
            return err
        opts[_WORDS[key]] = x
    return _mapped_line(cal, vals, opts)


_WORDS = {"a": "angle_deg", "s": "symmetry", "t": "tool_rz_offset_deg"}


def _number(name: str, text: str) -> tuple[float, bytes | None]:
    """A finite plain decimal, or the ERR line that refuses it: the rule and words of every line
    protocol's numbers (:func:`eyetohand.cell.line_numbers`)."""
    try:
        return line_numbers([text], (name,), None)[0], None
    except CommandError as exc:
        return 0.0, f"ERR {exc}\n".encode()


def _mapped_line(cal: Calibration, vals: list[float], opts: dict) -> bytes:
    z = vals[2] if len(vals) == 3 else None
    want_sigma = bool(opts.get("sigma"))
    try:
        symmetry = check_symmetry(line_count(opts.get("symmetry", 1)))  # "2.0" is 2, as on BELT lines
        with np.errstate(all="ignore"):
            m = cal.map(
                np.array([vals[:2]]),
                z,
                angle_deg=opts.get("angle_deg"),
                allow_outside=bool(opts.get("allow")),
                symmetry=symmetry,
                tool_rz_offset_deg=opts.get("tool_rz_offset_deg"),
                with_sigma=want_sigma,
            )
    except InputError as exc:
        reason = exc.reason if exc.index is not None else str(exc)
        return f"ERR {ascii_reason(reason.splitlines()[0])}\n".encode()
    x, y, zz = (float(v) for v in m.xyz_mm[0])
    out = f"{x!r},{y!r},{zz!r}"
    if m.rz_deg is not None:
        out += f",{float(m.rz_deg[0])!r}"
    if want_sigma and m.sigma_mm is not None:
        out += f",{float(m.sigma_mm[0])!r}"
    if not m.inside[0]:
        out += ",OUTSIDE"
    return (out + "\n").encode()


class LineServer:
    """Serve ``cal`` on ``host:port``. ``await start()``, then ``await serve_forever()`` or ``close()``."""

    def __init__(
        self,
        cal: Calibration | FixedCalibration | StoredCalibration | PendingCalibration,
        host: str,
        port: int,
        *,
        max_clients: int = MAX_CLIENTS,
        idle_s: float = IDLE_S,
        token: str | None = None,
        max_per_peer: int = MAX_PER_PEER,
        auth_s: float = AUTH_S,
        poll_s: float = POLL_S,
        commands: dict[str, Callable[[str], str]] | None = None,
    ):
        self.source: FixedCalibration | StoredCalibration | PendingCalibration = (
            FixedCalibration(cal) if isinstance(cal, Calibration) else cal
        )
        self.poll_s = poll_s
        self._poller: asyncio.Task | None = None
        # first word (upper case) -> handler(line) -> reply without line end, run off the event loop
        # (a command may grab and detect for a second); e.g. {"CAL": collector.handle}
        self.commands = {k.upper(): f for k, f in (commands or {}).items()}
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
        if isinstance(self.source, StoredCalibration):
            self._poller = asyncio.get_running_loop().create_task(self._follow(self.source))

    def follow(self, source: StoredCalibration, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Serve (and follow) ``source`` from now on: after a collection created the calibration.
        Callable from any thread; ``loop`` is the server's (needed from another thread)."""
        self.source = source

        def restart() -> None:
            if self._poller is not None:
                self._poller.cancel()
            self._poller = asyncio.get_running_loop().create_task(self._follow(source))

        if loop is not None:
            loop.call_soon_threadsafe(restart)
        else:
            restart()

    @property
    def cal(self) -> Calibration | None:
        """The calibration in force (None while a followed one is deleted)."""
        return self.source.cal

    async def _follow(self, src: StoredCalibration) -> None:
        while True:
            await asyncio.sleep(self.poll_s)
            await asyncio.to_thread(src.poll)

    def reply(self, line: bytes) -> bytes:
        """The answer to one line with the calibration in force (``VERSION`` names it)."""
        src = self.source
        if line.strip().upper() == b"VERSION":
            text = src.version_line() if src.error is None else f"ERR {ascii_reason(src.error)}"
            return text.encode("ascii", "replace") + b"\n"
        cal = src.cal
        if cal is None or src.error is not None:
            return f"ERR {ascii_reason(str(src.error))}\n".encode()
        return answer(cal, line)

    async def serve_forever(self) -> None:
        assert self.server is not None
        async with self.server:
            await self.server.serve_forever()

    def close(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
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
                    # asyncio.timeout, not wait_for: wait_for runs the read as a task of its own, two
                    # more turns of the event loop for every line
                    async with asyncio.timeout(self.idle_s):
                        line = await reader.readuntil(b"\n")
                except (asyncio.LimitOverrunError, ValueError):
                    writer.write(f"ERR line longer than {MAX_LINE} bytes; closing\n".encode())
                    break
                except asyncio.IncompleteReadError:
                    break  # end of stream; a last line without its newline may be cut: no answer
                except TimeoutError:
                    writer.write(f"ERR idle for {self.idle_s:g} s; closing\n".encode())
                    break
                word = line.split(None, 1)[0].upper().decode("ascii", "replace") if line.strip() else ""
                if word in self.commands:
                    reply = await asyncio.to_thread(self.commands[word], line[:-1].decode("ascii", "replace"))
                    writer.write(reply.encode("ascii", "replace") + b"\n")
                else:
                    writer.write(self.reply(line[:-1]))
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
        assert self.token is not None  # _auth runs only with a token
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
