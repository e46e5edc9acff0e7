"""Following the store: what another process changed (another cell, the office) reaches this server's
cache of calibrations, and an unreachable store is noticed, said once, and survived.

The audit trail is the change feed: every change appends an entry in its own transaction, and writes
are serialised (SQLite's write lock; PostgreSQL's advisory lock, :mod:`~eyetohand.server.store_pg`),
so entry ids become visible in increasing order and "every entry after the last one seen" misses
nothing — across a reconnect too (notifications are not durable; the trail is). A thread polls it every
:data:`POLL_S`; on PostgreSQL a second thread LISTENs on the store's channel and wakes the poll at once
(the payload, a calibration id, is only a wake-up: what changed is read from the trail).

While the store cannot be read, the cache keeps the versions in force (immutable, already proven), the
state says why (``/api/health``), and one log line says so — one more when it is back.
"""

from __future__ import annotations

import datetime as _dt
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from eyetohand.server.storage import StorageError, Store

POLL_S = 0.25  # as the TCP line service's poll: every interface follows within the same ~0.25 s
LOG = logging.getLogger("eyetohand.store")


@dataclass(frozen=True)
class StoreState:
    """What ``/api/health`` says of the store: reachable, or since when not and why."""

    where: str
    kind: str
    reachable: bool
    since_utc: str | None = None
    reason: str | None = None
    last_change: int | None = None  # the id of the last audit entry seen

    def to_dict(self) -> dict:
        """For ``/api/health`` (answered without a token: the store's address is left out)."""
        return {
            "kind": self.kind,
            "reachable": self.reachable,
            "since_utc": self.since_utc,
            "reason": self.reason,
            "last_change": self.last_change,
        }


class Follower:
    """Polls ``store``'s audit trail and calls ``on_change(calibration_id)`` for every calibration
    another writer changed (this process's own writes come through it too: harmless, the cache
    compares versions). Start with :meth:`start`, end with :meth:`stop`."""

    def __init__(
        self,
        store: Store,
        on_change: Callable[[int], None],
        poll_s: float = POLL_S,
        beat: Callable[[], None] | None = None,
        beat_s: float = 5.0,
    ):
        """``beat``: called every ``beat_s`` from the polling thread (a serve's heartbeat in the
        store: :mod:`~eyetohand.server.plant`); its failures wait for the next one."""
        self.store = store
        self.on_change = on_change
        self.poll_s = poll_s
        self.beat, self.beat_s = beat, beat_s
        self._next_beat = 0.0
        self._failing = ""  # the last unexpected failure, logged once
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.last: int | None = None
        self.state = StoreState(store.where, store.dialect, True)

    def start(self) -> None:
        """The first poll now (the trail's last entry is where following starts: a change made between
        this and the first request is then seen), then the threads."""
        self._step()
        self._threads.append(threading.Thread(target=self._run, name="eyetohand-follow", daemon=True))
        if self.store.dialect == "postgresql":
            self._threads.append(threading.Thread(target=self._listen, name="eyetohand-listen", daemon=True))
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        for t in self._threads:
            t.join(timeout=5)

    def poll(self) -> None:
        """Read the entries after the last one seen and hand their calibrations to ``on_change``."""
        try:
            last, changed = self.store.changed_since(self.last)
        except StorageError as exc:
            self._down(str(exc))
            return
        if not self.state.reachable:
            LOG.warning("the store %s is reachable again: following its changes", self.store.where)
        self.state = StoreState(self.store.where, self.store.dialect, True, last_change=last)
        self.last = last
        for cal_id in changed:
            try:
                self.on_change(cal_id)
            except StorageError as exc:
                self._down(str(exc))
                return

    def _down(self, reason: str) -> None:
        if self.state.reachable:  # said once, not per poll nor per request
            LOG.warning(
                "the store %s cannot be read (%s): serving the versions in force, refusing changes",
                self.store.where,
                reason,
            )
            now = _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")
            self.state = StoreState(self.store.where, self.store.dialect, False, now, reason, self.last)

    def _step(self) -> None:
        try:
            self.poll()
            self._failing = ""
        except Exception as exc:  # noqa: BLE001 - a bug must not end the following: said once, tried again
            if repr(exc) != self._failing:
                self._failing = repr(exc)
                LOG.exception("following the store %s failed; trying again", self.store.where)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._step()
            if self.beat is not None and time.monotonic() >= self._next_beat and self.state.reachable:
                self._next_beat = time.monotonic() + self.beat_s
                try:
                    self.beat()
                except StorageError:
                    pass  # the poll says when the store cannot be written
            self._wake.wait(self.poll_s)
            self._wake.clear()

    def _listen(self) -> None:
        """LISTEN on the store's channel (its own connection); each notification wakes the poll."""
        import psycopg

        from eyetohand.server.store_pg import CHANNEL, CONNECT_TIMEOUT_S, PgStore

        assert isinstance(self.store, PgStore)  # started for PostgreSQL stores only
        url = self.store.url
        while not self._stop.is_set():
            try:
                with psycopg.connect(url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S) as conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    self._wake.set()  # after a reconnect: catch up at once
                    while not self._stop.is_set():
                        for _ in conn.notifies(timeout=1.0, stop_after=1):
                            self._wake.set()
            except psycopg.Error:
                self._stop.wait(1.0)  # the poll says the store is down; try again
