"""The HTTP connection's own deadlines (uvicorn's h11 protocol with timers): a client must send a
complete request head within :data:`HEAD_TIMEOUT_S` of connecting (or of its previous answer), and
its body within a time set by its size, or the connection is closed.

uvicorn (0.55) has a keep-alive timeout only between requests, started after an answer: a client
that connects and sends half a request head, a byte at a time or not at all, holds its connection
(and a file descriptor) for ever — 1500 such slowloris connections were held. h11 alone never
times out either. So :class:`GuardedH11Protocol` (``uvicorn.Config(http=GuardedH11Protocol)``)
arms one timer per connection: for the head, then for the body, then none while the app works on
the request (a fit may take minutes; its answer is the app's business).
"""

from __future__ import annotations

import asyncio

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

HEAD_TIMEOUT_S = 10.0
"""A request head (request line and headers) must be complete this long after the connection opened
or the previous answer was sent."""
BODY_MIN_BYTES_PER_S = 64 * 1024
"""A body of N bytes must be complete within HEAD_TIMEOUT_S + N / BODY_MIN_BYTES_PER_S after its
head (a 64 MiB mapping body: 17 min; a chunked body: HEAD_TIMEOUT_S between pieces)."""


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a head deadline and a body deadline (see the module)."""

    head_timeout_s = HEAD_TIMEOUT_S
    body_min_bytes_per_s = BODY_MIN_BYTES_PER_S

    _guard: asyncio.TimerHandle | None = None
    _phase = "head"  # "head": waiting for a complete head; "body": for the body; "app": neither

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._arm("head", self.head_timeout_s)

    def waiting(self) -> bool:
        """Whether the connection waits for its client (a head or a body), not for the app's answer:
        then it may be closed for another connection (positioning/limits.py)."""
        return self._phase != "app"

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._follow()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm("head", self.head_timeout_s)  # the next request's head (keep-alive)
            self._follow()  # a pipelined request may be complete already

    # ------------------------------------------------------------ the timer
    def _follow(self) -> None:
        """Move the deadline with the request's progress (called after the parser saw new bytes)."""
        theirs = self.conn.their_state
        if theirs is h11.SEND_BODY:
            if self._phase == "head":
                length = _content_length(self.headers)
                if length is None:  # chunked: HEAD_TIMEOUT_S between pieces
                    self._arm("body", self.head_timeout_s)
                else:
                    self._arm("body", self.head_timeout_s + length / self.body_min_bytes_per_s)
            elif _content_length(self.headers) is None:
                self._arm("body", self.head_timeout_s)
        elif theirs is not h11.IDLE:  # DONE, MUST_CLOSE, CLOSED, ERROR: the request is in (or over)
            self._disarm()
            self._phase = "app"

    def _arm(self, phase: str, seconds: float) -> None:
        self._disarm()
        self._phase = phase
        self._guard = self.loop.call_later(seconds, self._expired)

    def _disarm(self) -> None:
        if self._guard is not None:
            self._guard.cancel()
            self._guard = None

    def _expired(self) -> None:
        self._guard = None
        if self._phase == "app" or self.transport.is_closing():
            return
        if self.cycle is not None and not self.cycle.response_complete and self._phase == "body":
            self.cycle.disconnected = True  # the app's receive() sees the client gone
        self.transport.close()


def _content_length(headers) -> int | None:
    for k, v in headers or ():
        if k == b"content-length":
            try:
                return int(v)
            except ValueError:
                return None
    return None
