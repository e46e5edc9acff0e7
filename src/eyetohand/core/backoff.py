"""Failed authentication is not free: a per-source-address backoff shared by every interface.

After :attr:`AuthBackoff.free` failed attempts from one address, that address's next attempt is not
judged until a delay has passed since its last failure — :attr:`AuthBackoff.base_delay_s`, doubled
with each further failure, at most :attr:`AuthBackoff.max_delay_s` — and is refused unjudged before
then (the TCP line, HTTP and OPC UA each answer in their own words). So a guesser gets ``free``
guesses and then about one per ``max_delay_s``, however many connections it opens, while any other
address is served as before. An address is forgotten ``forget_s`` after its last failure, or when it
authenticates; at most ``max_addresses`` are remembered (the least recently failed is dropped first),
so memory stays bounded under a spray of source addresses. An IPv6 address counts for its /64 (one
host holds a whole /64 and may pick any address in it); an IPv4-mapped one as the IPv4 address.
``clock`` is injectable for tests. A burst
is logged once, when an address starts to be held back, with its count; the refusals that follow are
not logged one by one.

Thread-safe: the TCP line, the HTTP server and the PLC services run on loops of their own.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

FREE_FAILURES = 5
BASE_DELAY_S = 1.0
MAX_DELAY_S = 60.0
FORGET_S = 900.0
MAX_ADDRESSES = 4096

_log = logging.getLogger("eyetohand.auth")


@dataclass
class _Failures:
    count: int
    last_s: float


class AuthBackoff:
    """Failed authentications per source address (module docstring)."""

    def __init__(
        self,
        *,
        free: int = FREE_FAILURES,
        base_delay_s: float = BASE_DELAY_S,
        max_delay_s: float = MAX_DELAY_S,
        forget_s: float = FORGET_S,
        max_addresses: int = MAX_ADDRESSES,
        clock: Callable[[], float] = time.monotonic,
    ):
        if free < 0 or base_delay_s <= 0 or max_delay_s < base_delay_s or forget_s < max_delay_s:
            raise ValueError("AuthBackoff: expected free >= 0, 0 < base_delay_s <= max_delay_s <= forget_s")
        if max_addresses < 1:
            raise ValueError("AuthBackoff: max_addresses must be at least 1")
        self.free = free
        self.base_delay_s = base_delay_s
        self.max_delay_s = max_delay_s
        self.forget_s = forget_s
        self.max_addresses = max_addresses
        self.clock = clock
        self._failures: OrderedDict[str, _Failures] = OrderedDict()
        self._lock = threading.Lock()

    def _delay_after(self, count: int) -> float:
        over = count - self.free
        if over <= 0:
            return 0.0
        return min(self.max_delay_s, self.base_delay_s * 2.0 ** min(over - 1, 60))

    def wait_s(self, address: str) -> float:
        """Seconds before an attempt from ``address`` is judged (0: judge it now). An attempt made
        while this is positive is to be refused without looking at its token."""
        address = _key(address)
        if address not in self._failures:  # the common case, without the lock (one dict lookup)
            return 0.0
        now = self.clock()
        with self._lock:
            f = self._failures.get(address)
            if f is None:
                return 0.0
            if now - f.last_s >= self.forget_s:
                del self._failures[address]
                return 0.0
            return max(0.0, f.last_s + self._delay_after(f.count) - now)

    def failed(self, address: str, what: str = "authentication") -> None:
        """Count a judged attempt from ``address`` that failed (``what``: for the log line)."""
        address = _key(address)
        now = self.clock()
        with self._lock:
            f = self._failures.pop(address, None)
            if f is None or now - f.last_s >= self.forget_s:
                f = _Failures(0, now)
            f.count += 1
            f.last_s = now
            self._failures[address] = f  # the most recently failed last
            while len(self._failures) > self.max_addresses:
                self._failures.popitem(last=False)
            count = f.count
        if count == self.free + 1:  # once per burst: when the address starts to be held back
            _log.warning(
                "%d failed %s attempts from %s: its next attempts wait %g s, doubling to %g s",
                count,
                what,
                address,
                self._delay_after(count),
                self.max_delay_s,
            )

    def succeeded(self, address: str) -> None:
        """``address`` authenticated: its failures are forgotten."""
        address = _key(address)
        if address not in self._failures:  # the common case, without the lock
            return
        with self._lock:
            self._failures.pop(address, None)

    @property
    def remembered(self) -> int:
        """How many addresses are remembered (bounded by ``max_addresses``)."""
        return len(self._failures)


def _key(address: str) -> str:
    """The address an attempt counts for: an IPv4 address (or a name) as it is, an IPv6 one's /64, an
    IPv4-mapped IPv6 one as its IPv4 address."""
    if ":" not in address:
        return address
    import ipaddress

    try:
        ip = ipaddress.IPv6Address(address.split("%", 1)[0])
    except ValueError:
        return address
    if ip.ipv4_mapped is not None:
        return str(ip.ipv4_mapped)
    return str(ipaddress.IPv6Network(f"{ip}/64", strict=False))
