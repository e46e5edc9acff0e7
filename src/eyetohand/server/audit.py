"""The audit trail: who changed which calibration, when, from which version to which, and why.

Every write of the store appends one entry in the same transaction as the change (so there is no
change without its entry, nor an entry without its change); entries are never changed or removed
(the tables' triggers refuse it: :mod:`eyetohand.server.schema`).

Who: the name of the token the request came with (``--token-file`` lines ``name:token`` or
``name:role:token``), set for the request by the token guard, or for a TCP connection by its ``AUTH``
line, with :func:`acting_as` (:mod:`eyetohand.core.actor`); a write made outside a request (a collection's
CAL END on the TCP service, a command-line tool) names what made it.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import asdict, dataclass

from eyetohand.core import DEFAULT_TOKEN_NAME, NOBODY, acting_as, current_actor

ACTIONS = (
    "create",  # a new calibration from a fit
    "import",  # a calibration file stored (a new calibration, or a new version of one)
    "new_version",  # a refit saved as a new version
    "cal_end",  # a collection's CAL END saved its calibration (TCP)
    "rollback",  # an earlier version made current again (as a new version that copies it)
    "rename",
    "delete",
    "check",  # a verification's result kept in the history
    "sign",  # a signer signed a version with the server's key (the act --require-signed waits for)
)

DEFAULT_USER = NOBODY.name
"""Who a write is by when nothing says otherwise (no token is required: a loopback workbench)."""


def current_user() -> str:
    """The name the writes made now are audited under (the acting token's name: core's actor)."""
    return current_actor().name


def action_of(request: dict, new: bool) -> str:
    """The audit action of storing a version made by ``request`` (its ``source`` says what made it)."""
    source = request.get("source")
    if source == "import":
        return "import"
    if source == "collection":
        return "cal_end"
    return "create" if new else "new_version"


def check_note(entry: dict) -> str:
    """The audit note of a verification entry: its verdict and figures."""
    verdict = "passed" if entry.get("passed") else "failed"
    rms, worst, tol = entry.get("rms_mm"), entry.get("max_mm"), entry.get("tolerance_mm")
    figures = []
    if isinstance(rms, int | float):
        figures.append(f"rms {rms:.3f} mm")
    if isinstance(worst, int | float):
        figures.append(f"max {worst:.3f} mm")
    if isinstance(tol, int | float):
        figures.append(f"tolerance {tol:g} mm")
    n = entry.get("n")
    head = f"{verdict} on {n} points" if isinstance(n, int) else verdict
    cause = entry.get("cause")
    return ", ".join([head, *figures]) + (f" ({cause})" if cause else "")


@dataclass(frozen=True)
class AuditEntry:
    id: int
    utc: str
    user: str
    action: str
    calibration_id: int | None
    calibration: str
    version_before: int | None
    version_after: int | None
    note: str

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class AuditQuery:
    """Which entries to list, newest first: of one calibration (its id; or its name as the entries
    recorded it, for one deleted since), by one user, within [since, until] (ISO 8601 UTC), older
    than the entry ``before`` (the page's cursor), at most ``limit``."""

    calibration_id: int | None = None
    calibration_name: str | None = None
    user: str | None = None
    since: str | None = None
    until: str | None = None
    before: int | None = None
    limit: int = 100

    MAX_LIMIT = 1000

    def where(self) -> tuple[str, tuple]:
        """The SQL condition (``?`` placeholders) and its arguments."""
        conds: list[str] = []
        args: list = []
        for sql, value in (
            ("calibration_id = ?", self.calibration_id),
            ("calibration = ?", self.calibration_name),
            ("user_name = ?", self.user),
            ("utc >= ?", self.since),
            ("utc <= ?", self.until),
            ("id < ?", self.before),
        ):
            if value is not None:
                conds.append(sql)
                args.append(value)
        return (" WHERE " + " AND ".join(conds)) if conds else "", tuple(args)


def parse_utc(text: str, what: str) -> str:
    """``text`` (ISO 8601; a date alone is its midnight; no zone: UTC) as the store writes times
    (``YYYY-MM-DDTHH:MM:SS.mmm+00:00``), so that they compare as text; ValueError naming ``what``."""
    try:
        t = _dt.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"{what}: expected an ISO 8601 time such as 2026-12-04 or 2026-12-04T05:30:00Z, got {text!r}"
        ) from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.UTC)
    return t.astimezone(_dt.UTC).isoformat(timespec="milliseconds")


__all__ = [
    "ACTIONS",
    "DEFAULT_TOKEN_NAME",
    "DEFAULT_USER",
    "AuditEntry",
    "AuditQuery",
    "acting_as",
    "action_of",
    "check_note",
    "current_user",
    "parse_utc",
]
