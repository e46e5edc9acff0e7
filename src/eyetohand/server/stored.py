"""A stored calibration served by the positioning transports: the current version in the database,
followed (:class:`StoredCalibration`, a :class:`eyetohand.positioning.Served`), while the database path
still names the file the store opened (:class:`SameFile`); and the rules that make a collection and
CAL CHECK use what the mapping lines serve (through the :class:`~eyetohand.positioning.Served`
protocol: no kind is asked for)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from eyetohand.calibration import Calibration
from eyetohand.cell import MAX_REASON, ErrorCode, Refusal
from eyetohand.core import InputError
from eyetohand.positioning import Identity
from eyetohand.server.signatures import SigningPolicy
from eyetohand.server.storage import NotFound, StorageError

if TYPE_CHECKING:
    from eyetohand.positioning import LineServer


class SameFile:
    """Whether the database path still names the file the store opened (deleted, or replaced by a copy,
    a restore, another cell's database: the truth HTTP answers from is that path).

    Uses the store's own ``check_same_file()`` when it has one; else one ``os.stat`` of ``store.path``
    compared with the (device, inode) seen when this was made (make it when the store is opened)."""

    def __init__(self, store):
        self.path = Path(store.path)
        self._check = getattr(store, "check_same_file", None)
        self.identity: tuple[int, int] | None = None
        if self._check is None:
            st = os.stat(self.path)
            self.identity = (st.st_dev, st.st_ino)

    def problem(self) -> str | None:
        """None while the path names the opened file; else why not (``database replaced or missing: …``).
        No SQLite, no lock: cheap enough for every line."""
        if self._check is not None:
            try:
                self._check()
            except StorageError as exc:
                return str(exc)
            return None
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return (
                f"database replaced or missing: {self.path} was deleted under the running server "
                "(put it back, or restart the server on the database to use)"
            )
        except OSError as exc:
            return f"database replaced or missing: cannot stat {self.path} ({exc.strerror or exc})"
        if (st.st_dev, st.st_ino) != self.identity:
            return (
                f"database replaced or missing: {self.path} is no longer the file this server opened "
                "(restart the server to use the new one)"
            )
        return None


class StoredCalibration:
    """The current version of a stored calibration, refreshed by :meth:`poll` (blocking: the line
    server runs it on a thread of its own). A deleted calibration sets ``error``, and so does a
    database file replaced or deleted under the server (``same_file``, until the path names the opened
    file again); a database that cannot be read for a moment keeps the version in force. With
    ``signing`` requiring signatures (``--require-signed``) an unsigned current version is refused in
    the words HTTP uses (:func:`~eyetohand.server.signatures.waits_for_signature`) until it is signed
    (the next poll after the signature serves it)."""

    def __init__(
        self, store, cal_id: int, same_file: SameFile | None = None, signing: SigningPolicy | None = None
    ):
        self.store = store
        self.same_file = same_file or SameFile(store)
        self.signing = signing
        self.waiting = False  # the current version waits for a signature
        self.cal_id = cal_id
        self.cal: Calibration | None = None
        self.error: Refusal | None = None
        self.name = ""
        self.version = 0
        self.created_utc = ""
        self.poll()
        if self.cal is None and not self.waiting:  # one waiting for a signer is served once signed
            raise InputError(self.error.reason if self.error else f"no calibration with id {cal_id}")

    def version_line(self) -> str:
        return f"OK {self.name},{self.version},{self.created_utc}"

    def problem(self) -> Refusal | None:
        """Why nothing may be mapped now (per line: the file check is one stat), or None."""
        gone = self.same_file.problem()
        return Refusal(ErrorCode.DATABASE, gone) if gone is not None else self.error

    def identity(self) -> Identity:
        return Identity(self.name, self.version, cal_id=self.cal_id)

    def describe(self) -> str:
        return (
            f"calibration {self.name!r} (id {self.cal_id}, version {self.version}, followed: a "
            "new version or a rollback takes effect within a second)"
        )

    def poll(self) -> None:
        gone = self.same_file.problem()
        if gone is not None:
            self.error = Refusal(ErrorCode.DATABASE, gone)  # the version in force is kept for when it is back
            return
        try:
            now = self.store.current(self.cal_id)
            if now is None:
                self.error = self._deleted()
                self.cal = None
                return
            name, version = now
            self.name = name
            if version == self.version and self.cal is not None:
                self.error = None
                return
            ver = self.store.version(self.cal_id, version)
            cal = Calibration.from_dict(ver.calibration, f"calibration {name!r} version {version}")
            unsigned = None if self.signing is None else self.signing.refusal(self.store, name, ver)
        except NotFound:
            self.error = self._deleted()
            self.cal = None
            return
        except StorageError:
            return  # keep what is in force; the next poll tries again
        except InputError as exc:
            why = f"calibration '{self.name}' version {version} cannot be used: {exc}"[:MAX_REASON]
            self.error = Refusal(ErrorCode.NO_CALIBRATION, why, broken=True)
            self.cal = None
            return
        self.waiting = unsigned is not None
        if unsigned is not None:  # stored, not in force: nothing is mapped with it until it is signed
            self.error = Refusal(ErrorCode.NO_CALIBRATION, unsigned[:MAX_REASON], broken=True)
            self.cal, self.version, self.created_utc = None, ver.version, ver.created_utc
            return
        # one assignment each, read by the event loop between lines (the GIL makes them atomic)
        self.cal, self.version, self.created_utc, self.error = cal, ver.version, ver.created_utc, None

    def _deleted(self) -> Refusal:
        return Refusal(ErrorCode.NO_CALIBRATION, f"calibration '{self.name or self.cal_id}' was deleted")


def collection_rule(
    server_fn: Callable[[], LineServer | None], wanted: str | None
) -> Callable[[str], str | None]:
    """``begin_rule`` for the server's Collector: with ``--calibration`` (``wanted``) a collection must be
    for the calibration the mapping lines serve (a file is never collected into); without it, any name
    (the mapping lines follow what a collection saves)."""

    def rule(name: str) -> str | None:
        if wanted is None:
            return None
        server = server_fn()
        ident = server.source.identity() if server is not None else Identity()
        if ident.file:
            return (
                f"this server maps with the file {ident.file} (--calibration), which a collection does "
                f"not change; start serve with --calibration {name} to collect it"
            )
        served = ident.name or wanted
        served = served[5:] if served.lower().startswith("name:") else served
        if name == served:
            return None
        return (
            f"mapping lines and CAL CHECK use calibration '{served}' (serve --calibration); send "
            f"CAL BEGIN {served}, or restart serve with --calibration {name}"
        )

    return rule


def served_for_check(server_fn: Callable[[], LineServer | None]):
    """``served_fn`` for the server's Collector: ``(name, version, cal, why_none)`` of the calibration the
    mapping lines use now, so CAL CHECK checks exactly that."""

    def served() -> tuple[str, int | None, Calibration | None, str | None]:
        server = server_fn()
        if server is None:
            return "", None, None, "the line service is not started yet"
        src = server.source
        ident, problem = src.identity(), src.problem()
        version = ident.version or None  # a file (or none yet) has no versions
        if problem is None and src.cal is not None:
            return ident.name, version, src.cal, None
        return ident.name, version, None, problem.reason if problem else "no calibration to map with"

    return served


__all__ = ["SameFile", "StoredCalibration", "collection_rule", "served_for_check"]
