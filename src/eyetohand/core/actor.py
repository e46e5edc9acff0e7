"""Who is acting now: the name and role of the token a request or a robot connection authenticated
with, for the audit trail and for what that role may do. One context variable, set per HTTP request
(the token guard) or per TCP connection (its ``AUTH`` line), so concurrent requests never see each
other's actor; a thread started for the work runs the context it was given (``contextvars``).

Roles, each allowed what the one before is, and more (docs/server.md "Tokens, roles and signing"):

- ``viewer``: read (every GET) and map (image to robot, evaluate), nothing stored;
- ``operator``: also fit, collect, import, verify, roll back, rename, delete (what a token without a
  role may do, as before roles existed);
- ``signer``: also sign a stored version with the server's key (``--sign-key``): the act that lets
  ``--require-signed`` serve it.
"""

from __future__ import annotations

import contextvars
import enum
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass


class Role(enum.IntEnum):
    """What a token may do; a higher role may do everything a lower one may."""

    VIEWER = 1
    OPERATOR = 2
    SIGNER = 3

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, text: str) -> Role:
        """The role named ``text`` (``viewer``, ``operator``, ``signer``); ValueError listing them."""
        try:
            return cls[text.strip().upper()]
        except KeyError:
            raise ValueError(f"role {text!r}: expected one of {', '.join(ROLE_NAMES)}") from None


ROLE_NAMES = tuple(r.label for r in Role)

DEFAULT_TOKEN_NAME = "default"
"""The name of a token given alone (``--token``, or a token file of one line without a name)."""

DEFAULT_USER = "local"
"""Who acts when nothing says otherwise (no token is required: a loopback workbench)."""


@dataclass(frozen=True)
class Actor:
    """A named token's holder: its name (the audit trail's user) and role. ``named``: it authenticated
    with a token (False for the default actor of a server without tokens)."""

    name: str
    role: Role
    named: bool = True

    def may(self, role: Role) -> bool:
        return self.role >= role

    def refusal(self, needed: Role, what: str) -> str | None:
        """Why this holder may not do ``what`` (which needs role ``needed``), or None: the one wording
        of HTTP's 403, TCP's ``ERR`` and the CLI."""
        if self.may(needed):
            return None
        may = " or ".join(r.label for r in Role if r >= needed)
        return f"token {self.name!r} has role {self.role.label}; {what} needs role {may}"


NOBODY = Actor(DEFAULT_USER, Role.OPERATOR, named=False)
"""The actor of a server without tokens: an operator, unnamed (so it may not sign)."""

_ACTOR: contextvars.ContextVar[Actor] = contextvars.ContextVar("eyetohand_actor", default=NOBODY)


def current_actor() -> Actor:
    """Who acts in this context (:data:`NOBODY` unless a token said otherwise)."""
    return _ACTOR.get()


@contextmanager
def acting_as(who: str | Actor) -> Iterator[None]:
    """Act as ``who`` inside (in this context: this request, this connection, this thread); a bare
    name acts as an operator of that name (a tool writing the store, a robot without a token)."""
    actor = who if isinstance(who, Actor) else Actor(who, Role.OPERATOR)
    token = _ACTOR.set(actor)
    try:
        yield
    finally:
        _ACTOR.reset(token)


class TokenTable:
    """The named tokens a server accepts, each with its holder (:class:`Actor`): what the HTTP guard,
    the TCP ``AUTH`` line and the OPC UA user check all consult, so that every named token works on
    every interface and is audited under its name."""

    def __init__(self, named: Mapping[str, str], roles: Mapping[str, Role] | None = None):
        roles = roles or {}
        self.entries = tuple(
            (Actor(name, roles.get(name, Role.OPERATOR)), token.encode())
            for name, token in named.items()
            if token
        )

    @classmethod
    def of(
        cls, token: str | Mapping[str, str] | TokenTable | None, roles: Mapping[str, Role] | None = None
    ) -> TokenTable:
        """From one token (named ``default``, operator), names to tokens (``roles``: their roles,
        operator where not given), or a table already made."""
        if isinstance(token, TokenTable):
            return token
        return cls({DEFAULT_TOKEN_NAME: token} if isinstance(token, str) else dict(token or {}), roles)

    def __bool__(self) -> bool:
        return bool(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def match(self, given: bytes | str) -> Actor | None:
        """The holder of token ``given``, or None. Every token is compared, with no early exit, so
        the time taken does not tell which one came close."""
        raw = given.encode() if isinstance(given, str) else given
        import hmac  # on first use: `eyetohand apply` loads no OpenSSL hashes (tests/test_startup_path.py)

        found = [actor for actor, t in self.entries if hmac.compare_digest(raw, t)]
        return found[0] if found else None

    def actor(self, name: str) -> Actor | None:
        """The holder named ``name`` (the OPC UA user name), or None."""
        return next((a for a, _ in self.entries if a.name == name), None)

    def token_of(self, name: str) -> bytes | None:
        return next((t for a, t in self.entries if a.name == name), None)


__all__ = [
    "DEFAULT_TOKEN_NAME",
    "TokenTable",
    "DEFAULT_USER",
    "NOBODY",
    "ROLE_NAMES",
    "Actor",
    "Role",
    "acting_as",
    "current_actor",
]
