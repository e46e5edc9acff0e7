"""What a positioning transport serves (:class:`Served`): the calibration in force, why nothing may be
mapped now (a typed :class:`~eyetohand.cell.Refusal`), who it is (:class:`Identity`) — one protocol
that the TCP line service (:mod:`.tcp`), Modbus (:mod:`.modbus`), OPC UA (:mod:`.opcua`) and LOCATE
(:mod:`.locate`) all take, read at every request.

Two kinds live here: a file (:class:`FixedCalibration`, never changes) and none yet
(:class:`PendingCalibration`, until a collection creates one). The server adds a stored calibration
that follows the database (``eyetohand.server.stored.StoredCalibration``); a test or an embedding
program may serve anything that has these methods.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

from eyetohand.calibration import Calibration
from eyetohand.cell import ErrorCode, Refusal


@dataclass(frozen=True)
class Identity:
    """Who a served calibration is, as every transport names it: ``name`` (a stored calibration's name,
    a file's name without its folder and ``.json``, '' for none), ``version`` (a stored calibration's;
    0 for a file, which has no versions, or for none), ``file`` (a file's path: a collection does not
    change it; '' otherwise), ``cal_id`` (the store's id of a stored calibration, else None)."""

    name: str = ""
    version: int = 0
    file: str = ""
    cal_id: int | None = None


@runtime_checkable
class Served(Protocol):
    """What a positioning transport serves. ``cal``: the calibration in force (None while there is
    none); everything else through the methods, so no transport asks which kind it has."""

    cal: Calibration | None

    def problem(self) -> Refusal | None:
        """Why nothing may be mapped now (None: map with :attr:`cal`). Cheap: asked for every line."""
        ...

    def identity(self) -> Identity:
        """Its name and version (Modbus registers, OPC UA variables, CAL CHECK)."""
        ...

    def version_line(self) -> str:
        """The line protocol's answer to ``VERSION`` while there is no problem (``OK …``)."""
        ...

    def describe(self) -> str:
        """What a service maps with, for its start-up line."""
        ...

    def poll(self) -> None:
        """Bring :attr:`cal` up to date (blocking; called off the event loop). Nothing for a file."""
        ...


class FixedCalibration:
    """A calibration that does not change (a file, or one given in code): ``VERSION`` names it."""

    def __init__(self, cal: Calibration, label: str = "calibration", sha256: str = ""):
        self.cal: Calibration | None = cal
        self.label = label
        self.sha256 = sha256 or cal.to_dict()["content_sha256"]

    @classmethod
    def from_file(cls, path) -> FixedCalibration:
        p = Path(path)
        cal = Calibration.load(p)
        return cls(cal, str(p.resolve()), hashlib.sha256(p.read_bytes()).hexdigest())

    def problem(self) -> Refusal | None:
        return None

    def identity(self) -> Identity:
        return Identity(Path(self.label).stem if self.label else "", 0, self.label)

    def version_line(self) -> str:
        return f"OK {self.label},{self.sha256}"

    def describe(self) -> str:
        return f"the file {self.label} (sha256 {self.sha256[:12]}…)"

    def poll(self) -> None:
        """A file does not change."""


class PendingCalibration:
    """Stands in for the served calibration before one exists (``serve --camera`` with a new name):
    every mapping line is one ERR until a collection creates it."""

    def __init__(self, name: str | None):
        self.name = name
        self.cal: Calibration | None = None
        what = f"'{name}' has none yet" if name else "none is served"
        self.refusal = Refusal(
            ErrorCode.NO_CALIBRATION,
            f"no calibration to map with: {what}; collect one (CAL BEGIN ... CAL END) "
            "or start serve with --calibration NAME",
        )

    def problem(self) -> Refusal | None:
        return self.refusal

    def identity(self) -> Identity:
        return Identity(self.name or "")

    def version_line(self) -> str:
        return f"ERR {self.refusal.reason}"

    def describe(self) -> str:
        return "no calibration yet (a collection creates it)"

    def poll(self) -> None:
        """Nothing to follow yet (a collection replaces it: :meth:`~.tcp.LineServer.follow`)."""


__all__ = ["FixedCalibration", "Identity", "PendingCalibration", "Served"]
