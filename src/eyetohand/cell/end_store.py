"""``CAL END``'s new version, stored in an order that neither a crash nor a failed journal write can
turn into a second version or into a false "nothing recorded" (issue 40).

1. ``ending`` is journaled (fsync-ed) first: the session id, the points fitted, the fit's data hash
   (``data_sha256``) and the reply. A failed write here is the usual refusal with nothing recorded —
   and nothing is stored.
2. The version is stored (``save_fn``).
3. ``end`` is journaled. A failed write here does not unsay the store: the reply is the END's OK (the
   version is in force), the session is calibrated in memory, and the journal keeps the ``ending``.

A session whose journal ends in an ``ending`` without its ``end`` (killed between 2 and 3, or 3 failed)
is settled by the next ``CAL END`` (a robot resending it, after a restart or not): when no point was
recorded or dropped since and the stored current version has the intent's data hash, it is the one this
session stored — ``end`` is journaled and the first reply is answered again, nothing stored twice;
otherwise (killed between 1 and 2, or the points changed) END fits and stores as usual.
"""

from __future__ import annotations

from collections.abc import Callable

from eyetohand.cell.line import CommandError
from eyetohand.cell.session import Session


def _points(s: Session) -> list[int]:
    """The numbers of the points (touches) an END fits: what its intent was about."""
    return [int(p["n"]) for p in s.active()]


class EndStore:
    """``record(rec)`` journals a record and applies it (raises :class:`CommandError` when the journal
    write fails, nothing recorded); ``apply(rec)`` applies one without journaling it; ``save_fn(name, cal)``
    stores a new version; ``load_fn(name)`` the current one (None: none)."""

    def __init__(
        self,
        record: Callable[[dict], None],
        apply: Callable[[dict], None],
        save_fn: Callable,
        load_fn: Callable,
    ):
        self.record, self.apply, self.save_fn, self.load_fn = record, apply, save_fn, load_fn

    def settle(self, s: Session) -> dict | None:
        """The END record of ``s``'s pending END when the store has its version (module docstring),
        else None (nothing pending, or the store never got it)."""
        p = s.pending
        if p is None or p.get("session") != s.id or p.get("points") != _points(s):
            return None  # nothing pending, or points recorded (dropped) since: not this END's data
        current = self.load_fn(s.name)
        if current is None or current.data_sha256 != p["data_sha256"]:
            return None
        return self._finish(p)

    def store(self, s: Session, cal, result: dict) -> dict:
        """Journal the intent, store ``cal`` as ``s``'s new version, journal the end; the END record
        (``result`` holds its fields, ``reply`` the reply's)."""
        intent = {
            **result,
            "op": "ending",
            "name": s.name,
            "session": s.id,
            "data_sha256": cal.data_sha256,
            "points": _points(s),
        }
        self.record(intent)  # refused: nothing recorded and nothing stored
        self.save_fn(s.name, cal)
        return self._finish(intent)

    def _finish(self, intent: dict) -> dict:
        end = {k: v for k, v in intent.items() if k != "utc"} | {"op": "end"}
        try:
            self.record(end)
        except CommandError:
            # the version is in force: say so (OK); the journal keeps the intent for the next END to settle
            self.apply(end)
        return end


__all__ = ["EndStore"]
