"""Connection bounds shared by every listener of ``eyetohand serve`` (HTTP, the TCP line, Modbus, OPC
UA): how many connections, from whom, for how long, and how many file handles they may take.

- :class:`Slots`: at most ``total`` connections to one listener and at most ``per_address`` from one
  source address, shared **fairly**: when the listener is full, a connection from an address holding
  fewer than the heaviest address minus one takes the slot of that address's least recently active
  connection (which is closed). So idle sockets from a few addresses cannot lock a new one out — the
  robot gets in without ``--robot-address`` (which stays: a reservation beyond ``total``).
- :class:`Guarded`: an ``asyncio.Protocol`` around a library's protocol (pymodbus's, asyncua's,
  uvicorn's): admits through :class:`Slots`, closes a connection that sends nothing for ``first_s``
  after connecting, or nothing for ``idle_s`` later (a half-open one sends nothing either).
- :func:`file_budget`: at start the soft ``RLIMIT_NOFILE`` is raised toward the hard one, and the
  listeners' totals are scaled so that their sum, their accept backlogs (a burst of accepts holds that
  many handles until they are refused) and a reserve for the rest of the process (the store, logs,
  the camera) stay below it: a flood never leaves the process without file handles.
- :class:`StormLog`: refusals logged once per burst, never one line per connection; and
  :func:`quiet_accept_errors`, the event loop's handler that does the same for ``accept()`` failing
  with EMFILE (asyncio 3.11 logs that once per queued connection per retry: 15 MB of log in 5 s).
"""

from __future__ import annotations

import asyncio
import dataclasses
import errno
import logging
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from eyetohand.cell import ErrorCode, Refusal

LOG = logging.getLogger("eyetohand.connections")
QUIET_S = 10.0
"""A burst of refusals ends after this long without one (the next refusal is logged again)."""
BACKLOG = 64
"""Each listener's least accept backlog: connections the kernel queues before they take a file handle;
asyncio accepts up to this many in one turn before any is refused (counted in :func:`file_budget`). A
burst of connects beyond it waits for the client's SYN retransmit (~1 s), so :func:`file_budget` gives
each listener more where the handles allow (:data:`MAX_BACKLOG`)."""
MAX_BACKLOG = 512
"""The most a listener's backlog is raised to: an eighth of the handles left per listener, between
:data:`BACKLOG` (1024 handles) and this (about 250 under the unit's 8192)."""
RESERVE_FILES = 192
"""File handles kept for everything but the listeners' connections: the store (SQLite and its WAL, one
per thread), log files, the camera, the event loops' own handles."""
WANT_FILES = 8192
"""The soft RLIMIT_NOFILE asked for at start (never above the hard limit): the shipped systemd unit sets
``LimitNOFILE=8192``."""
MIN_TOTAL = 8  # below this a listener is useless: serve refuses to start (raise the limit)
FIRST_S = 10.0
"""A connection that sends nothing this long after connecting is closed (Modbus, OPC UA; the TCP line's
``--tcp-first-line``, HTTP's head deadline are the same rule)."""
IDLE_S = 300.0
"""A Modbus connection that sends nothing this long is closed (the TCP line's idle limit; a PLC that
polls keeps its connection, one that was switched off does not hold it)."""


@dataclass(frozen=True)
class Limit:
    """One listener's bound: at most ``total`` connections, at most ``per_address`` from one address;
    ``backlog``: its listen (and accept-per-turn) backlog."""

    total: int
    per_address: int
    backlog: int = BACKLOG

    def scaled(self, factor: float) -> Limit:
        total = max(MIN_TOTAL, int(self.total * factor))
        return Limit(total, min(self.per_address, total), self.backlog)


#: each listener's bound before :func:`file_budget` fits them to the process's file handles
LIMITS = {
    "http": Limit(256, 256),  # one address may be a proxy, or a script's 80 requests: the fair share only
    "tcp": Limit(256, 64),  # the TCP line's MAX_CLIENTS, MAX_PER_PEER (and ROBOT_SLOTS beyond)
    "modbus": Limit(64, 16),
    "opcua": Limit(64, 16),
}


class Connection(Protocol):
    """What :class:`Slots` needs of a connection: when it last received, whether it may be closed for
    another (not while the server works on its request), and how to close it."""

    last_active: float

    def evictable(self) -> bool: ...

    def evict(self, reason: Refusal) -> None: ...


class StormLog:
    """One warning per burst of refusals on a listener (``what``), with the count of the burst before."""

    def __init__(self, what: str, quiet_s: float = QUIET_S, clock: Callable[[], float] = time.monotonic):
        self.what, self.quiet_s, self.clock = what, quiet_s, clock
        self.last = -1e18
        self.count = 0  # refusals in the current burst
        self.total = 0  # refusals since start

    def refused(self, reason: str) -> None:
        now = self.clock()
        self.total += 1
        if now - self.last > self.quiet_s:
            before = f" ({self.count} in the burst before)" if self.count else ""
            LOG.warning(
                "%s: refusing connections: %s%s; more are counted, not logged, until %g s pass without one",
                self.what,
                reason,
                before,
                self.quiet_s,
            )
            self.count = 0
        self.count += 1
        self.last = now


class Slots:
    """The connections of one listener (module docstring). Not thread-safe: used on its listener's
    event loop only. ``reserved``: addresses served beyond ``total`` (up to ``reserved_slots``
    connections: ``--robot-address``). ``replace_own``: an address at its bound (or a full listener
    no other address can give a slot of) has its own longest idle connection replaced by the new one
    (HTTP: the newest request of a proxy or a script is served, a stale keep-alive or a stalled head
    makes way), else the new one is refused."""

    def __init__(
        self,
        what: str,
        limit: Limit,
        *,
        reserved: frozenset[str] = frozenset(),
        reserved_slots: int = 0,
        replace_own: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.what, self.limit, self.replace_own = what, limit, replace_own
        self.reserved, self.reserved_slots = reserved, reserved_slots
        self.by_address: dict[str, dict[Connection, None]] = {}
        self.count = 0
        self.robots = 0
        self.evicted = 0
        self.log = StormLog(what, clock=clock)

    def admit(self, address: str, conn: Connection) -> Refusal | None:
        """Take a slot for ``conn`` from ``address`` (None), or the refusal of it (logged once a burst)."""
        refused = self._admit(address, conn)
        if refused is not None:
            self.log.refused(refused.reason)
        return refused

    def _admit(self, address: str, conn: Connection) -> Refusal | None:
        if address in self.reserved:
            if self.robots >= self.reserved_slots:
                return _busy(
                    f"busy: {self.reserved_slots} connections from the robot's address {address} already"
                )
            self.robots += 1
            return None
        held = self.by_address.get(address)
        n = len(held) if held else 0
        if n >= self.limit.per_address:
            if not self._evict(address, n - 1, own=True):
                return _busy(f"busy: {self.limit.per_address} connections from {address} already")
        elif self.count >= self.limit.total and not self._evict_for(address, n):
            return _busy("busy: too many clients, try again later")
        if held is None:
            held = self.by_address[address] = {}
        held[conn] = None
        self.count += 1
        return None

    def _evict_for(self, address: str, n: int) -> bool:
        """Free a slot for ``address`` holding ``n``: the longest idle connection of the address holding
        the most, when that is at least ``n + 2`` (after the swap it still holds more); else, with
        ``replace_own``, ``address``'s own longest idle one."""
        for heavy_addr, heavy in sorted(self.by_address.items(), key=lambda kv: -len(kv[1])):
            if len(heavy) < n + 2:
                break  # every address holds about as many: the share is fair already
            if self._evict(heavy_addr, n + 1, own=False):
                return True
        return self._evict(address, n - 1, own=True)

    def _evict(self, address: str, at_least: int, *, own: bool) -> bool:
        """Close the longest idle evictable connection of ``address`` if it holds more than
        ``at_least``; ``own``: for a newer connection from that address (only with ``replace_own``)."""
        held = self.by_address.get(address)
        if not held or len(held) <= at_least or (own and not self.replace_own):
            return False
        whom = "a newer connection from the same address" if own else "another address"
        free = [c for c in held if c.evictable()]
        if not free:
            return False
        victim = min(free, key=lambda c: c.last_active)
        self._drop(address, victim)
        self.evicted += 1
        self.log.refused(f"closed the longest idle of {address}'s connections for {whom}")
        victim.evict(_busy(f"busy: this connection's slot went to {whom} ({self.what}); closing"))
        return True

    def release(self, address: str, conn: Connection) -> None:
        """``conn`` ended (a no-op for one evicted or never admitted)."""
        if address in self.reserved:
            self.robots = max(0, self.robots - 1)
            return
        self._drop(address, conn)

    def _drop(self, address: str, conn: Connection) -> None:
        held = self.by_address.get(address)
        if held is None or conn not in held:
            return
        del held[conn]
        self.count -= 1
        if not held:
            del self.by_address[address]


def _busy(reason: str) -> Refusal:
    return Refusal(ErrorCode.BUSY, reason)


def peer_address(transport: Any) -> str:
    """The source address of a connection (its IP as text; ``?`` when the transport has none)."""
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) and peer else "?"


class Guarded(asyncio.Protocol):
    """A library's protocol ``inner`` behind :class:`Slots` and two deadlines: nothing received for
    ``first_s`` after connecting, or for ``idle_s`` after that (None: no deadline), closes the
    connection. A refused or evicted connection is closed without a word (the protocol's own refusal
    needs its framing: the TCP line does that itself)."""

    def __init__(
        self,
        inner: asyncio.BaseProtocol,
        slots: Slots,
        first_s: float | None,
        idle_s: float | None,
        on_refused: Callable[[], object] | None = None,
        goodbye: bytes = b"",
        waiting: Callable[[Any], bool] | None = None,
    ):
        self.waiting = waiting  # whether ``inner`` waits for its client (None: always): evictable then
        self.inner, self.slots, self.on_refused = inner, slots, on_refused
        self.goodbye = goodbye  # sent to a refused connection before it is closed (HTTP: a 503)
        self.first_s, self.idle_s = first_s, idle_s
        self.transport: Any = None
        self.address = "?"
        self.admitted = False
        self.spoken = False
        self.last_active = 0.0
        self._timer: asyncio.TimerHandle | None = None

    # ---- asyncio.Protocol
    def connection_made(self, transport: Any) -> None:
        self.transport = transport
        self.address = peer_address(transport)
        loop = asyncio.get_running_loop()
        self.last_active = loop.time()
        if self.slots.admit(self.address, self) is not None:
            if self.goodbye:
                transport.write(self.goodbye)
                transport.close()
            else:
                transport.abort()  # no lingering close: the handle is back at once
            if self.on_refused is not None:  # the library forgets the protocol it made
                self.on_refused()
            return
        self.admitted = True
        self.inner.connection_made(transport)
        if self.first_s is not None:
            self._timer = loop.call_at(self.last_active + self.first_s, self._expire)

    def data_received(self, data: bytes) -> None:
        if not self.admitted:
            return
        self.last_active = asyncio.get_running_loop().time()
        if not self.spoken:
            self.spoken = True
            if self._timer is not None:  # from now on the idle deadline
                self._timer.cancel()
                self._timer = None
            if self.idle_s is not None:
                self._timer = asyncio.get_running_loop().call_at(self.last_active + self.idle_s, self._expire)
        self.inner.data_received(data)  # type: ignore[attr-defined]

    def eof_received(self) -> bool | None:
        return self.inner.eof_received() if self.admitted else None  # type: ignore[attr-defined]

    def connection_lost(self, exc: Exception | None) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if not self.admitted:
            return
        self.admitted = False
        self.slots.release(self.address, self)
        self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()

    # ---- deadlines and eviction
    def _expire(self) -> None:
        self._timer = None
        loop = asyncio.get_running_loop()
        wait = self.idle_s if self.spoken else self.first_s
        if wait is None or self.transport is None or self.transport.is_closing():
            return
        due = self.last_active + wait
        if self.spoken and due > loop.time():  # something came meanwhile: wait for the rest
            self._timer = loop.call_at(due, self._expire)
            return
        self.transport.close()

    def evictable(self) -> bool:
        return self.waiting is None or self.waiting(self.inner)

    def evict(self, reason: Refusal) -> None:
        if self.transport is not None:
            self.transport.close()


_BUSY_BODY = b'{"error": "busy: too many connections, try again later"}'
HTTP_BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\nContent-Type: application/json\r\n"
    b"Content-Length: %d\r\nConnection: close\r\n\r\n%s" % (len(_BUSY_BODY), _BUSY_BODY)
)
"""What a refused HTTP connection is sent before it is closed (the API's error body)."""


def guarded_factory(
    factory: Callable[..., Any],
    slots: Slots,
    first_s: float | None,
    idle_s: float | None,
    goodbye: bytes = b"",
    waiting: Callable[[Any], bool] | None = None,
) -> Callable[..., Guarded]:
    """``factory`` (an asyncio protocol factory, called with whatever it is called with) whose
    protocols are :class:`Guarded` (``goodbye``: sent to a refused connection; ``waiting(protocol)``:
    whether it waits for its client, so that it may be closed for another)."""

    def make(*args: Any, **kwargs: Any) -> Guarded:
        return Guarded(factory(*args, **kwargs), slots, first_s, idle_s, goodbye=goodbye, waiting=waiting)

    return make


# ---------------------------------------------------------------- file handles
@dataclass(frozen=True)
class FileBudget:
    """The process's file handles as ``serve`` set them: the soft and hard limits (after raising the
    soft one), the handles open at start, and each listener's :class:`Limit` within them."""

    soft: int
    hard: int
    open_at_start: int
    limits: Mapping[str, Limit]

    def line(self) -> str:
        """The start-up line that says it."""
        each = ", ".join(
            f"{k} {v.total} ({v.per_address}/address, backlog {v.backlog})" for k, v in self.limits.items()
        )
        return (
            f"connections: {each}; file handles: limit {self.soft} (hard {self.hard}), "
            f"{self.open_at_start} open at start, {RESERVE_FILES} reserved"
        )


class FileBudgetError(Exception):
    """The file handle limit is too low for the listeners asked for (the message says how to raise it)."""


def file_budget(
    wanted: Mapping[str, Limit], *, want_files: int = WANT_FILES, raise_limit: bool = True
) -> FileBudget:
    """Raise the soft RLIMIT_NOFILE toward ``want_files`` (never above the hard limit) and fit the
    ``wanted`` listeners into it: their totals are scaled down (never up) so that their sum, a
    :data:`BACKLOG` each and :data:`RESERVE_FILES` stay below the soft limit, counting the handles
    open now. Raises :class:`FileBudgetError` when even :data:`MIN_TOTAL` each does not fit."""
    try:
        import resource
    except ImportError:  # Windows: no RLIMIT_NOFILE (its handle limit is far above these)
        return FileBudget(-1, -1, 0, dict(wanted))
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if raise_limit:
        target = want_files if hard == resource.RLIM_INFINITY else min(want_files, hard)
        if soft != resource.RLIM_INFINITY and soft < target:
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
                soft = target
            except (ValueError, OSError):
                pass
    open_now = _open_files()
    limit = soft if soft != resource.RLIM_INFINITY else 1 << 20
    n = max(1, len(wanted))
    backlog = max(BACKLOG, min(MAX_BACKLOG, (limit - open_now - RESERVE_FILES) // (8 * n)))
    room = limit - open_now - RESERVE_FILES - backlog * len(wanted)
    asked = sum(w.total for w in wanted.values())
    if room < MIN_TOTAL * len(wanted):
        raise FileBudgetError(
            f"too few file handles: limit {soft} (hard {hard}), {open_now} open, {RESERVE_FILES} reserved "
            f"and {backlog} per listener leave {room} for {len(wanted)} listeners; raise it "
            f"(systemd: LimitNOFILE=8192; a shell: ulimit -n 8192)"
        )
    factor = min(1.0, room / asked) if asked else 1.0
    limits = {
        k: dataclasses.replace(w if factor >= 1.0 else w.scaled(factor), backlog=backlog)
        for k, w in wanted.items()
    }
    return FileBudget(int(soft), int(hard), open_now, limits)


def _open_files() -> int:
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:  # no /proc (macOS): a guess on the safe side
        return 64


# ---------------------------------------------------------------- accept() without handles
_RESOURCE_ERRNOS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


def quiet_accept_errors(loop: asyncio.AbstractEventLoop, what: str) -> StormLog:
    """Make ``loop`` log ``accept()`` failing for want of file handles once per burst (asyncio retries
    the listener after 1 s itself: ``selector_events._accept_connection``; in 3.11 it calls the
    exception handler once per queued connection, each with a traceback). Every other error goes to
    the handler there was."""
    storm = StormLog(f"{what}: accept()")
    previous = loop.get_exception_handler()

    def handler(lp: asyncio.AbstractEventLoop, context: dict) -> None:
        exc = context.get("exception")
        # asyncio's accept() failure is the context with a listening "socket" and an OSError
        if isinstance(exc, OSError) and exc.errno in _RESOURCE_ERRNOS and context.get("socket") is not None:
            storm.refused(f"out of file handles ({exc.strerror})")
            return
        if previous is not None:
            previous(lp, context)
        else:
            lp.default_exception_handler(context)

    loop.set_exception_handler(handler)
    return storm
