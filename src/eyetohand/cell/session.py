"""The state of one CAL session, rebuilt from its journal records: a collection (``CAL BEGIN``, points
at poses) or a plate session (``CAL PLATE``, touches of the plate's corners); both end with
``CAL END`` (:mod:`eyetohand.cell.collect` has the protocol, :mod:`eyetohand.cell.plate_session` the
plate's commands).

A session is only ever changed by :func:`apply` of a journal record, live or replayed, so a server
restarted on its journal is in the state the robot last saw. ``END`` writes two records: ``ending``
(the intent, before the new version is stored: the session id, the fit's data hash and its reply) and
``end`` once it is stored; a session with an ``ending`` and no ``end`` (a crash between the two, or a
failed journal write after the store) has :attr:`Session.pending` set, which the next ``CAL END``
settles against the store (:mod:`eyetohand.cell.end_store`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

COLLECTION, PLATE = "collection", "plate"


@dataclass
class Session:
    """One session: its BEGIN (or PLATE) record, what was recorded since, its state."""

    begin: dict
    kind: str = COLLECTION
    points: list[dict] = field(default_factory=list)  # POINT records (collection) or TOUCH records (plate)
    images: list[dict] = field(default_factory=list)  # a plate session's placements: PLATE, then PLATE k
    state: str = "collecting"  # collecting, calibrated, aborted
    result: dict | None = None  # the END record
    pending: dict | None = None  # an ``ending`` record not yet followed by its ``end``
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    done: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    failed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    @classmethod
    def from_record(cls, rec: dict) -> Session:
        kind = PLATE if rec["op"] == "plate" else COLLECTION
        poses = np.array(rec.get("poses", []), float).reshape(-1, 3)
        return cls(
            rec,
            kind,
            images=[rec] if kind == PLATE else [],
            poses=poses,
            done=np.zeros(len(poses), bool),
            failed=np.zeros(len(poses), bool),
        )

    @property
    def name(self) -> str:
        return self.begin["name"]

    @property
    def model(self) -> str:
        return self.begin.get("model") or "auto"

    @property
    def id(self) -> str:
        """The session's id: the BEGIN's ``session`` field (journals before it: the BEGIN's time)."""
        return str(self.begin.get("session") or self.begin.get("utc") or "")

    def active(self) -> list[dict]:
        """The points (touches) not dropped."""
        return [p for p in self.points if not p.get("dropped")]

    def status(self) -> dict:
        """A collection as JSON-ready data (the workbench's collection view): plan poses with done/failed
        flags, the points with their detections, the fit result of the last END."""
        poses = [
            {
                "index": i,
                "xyz_mm": [float(v) for v in p],
                "done": bool(self.done[i]),
                "failed": bool(self.failed[i]),
            }
            for i, p in enumerate(self.poses)
        ]
        points = [
            {
                "n": p["n"],
                "xyz_mm": p["xyz_mm"],
                "angle_deg": p["angle_deg"],
                "u": p["u"],
                "v": p["v"],
                "pose_index": p.get("pose_index"),
                "still_shift_px": p["still_shift_px"],
                "dropped": bool(p.get("dropped")),
                "utc": p.get("utc"),
                "detection": {
                    k: p["detection"].get(k)
                    for k in ("diameter_px", "score", "rms_px", "contrast", "blur_px", "method")
                    if k in p["detection"]
                },
            }
            for p in self.points
        ]
        return {
            "name": self.name,
            "state": self.state,
            "model": self.model,
            "plan": self.begin.get("plan"),
            "poses": poses,
            "points": points,
            "result": self.result,
        }


def apply(session: Session | None, rec: dict) -> Session | None:
    """The session after journal record ``rec`` (a BEGIN or PLATE starts a new one)."""
    op = rec["op"]
    if op in ("begin", "plate"):
        return Session.from_record(rec)
    s = session
    if s is None:
        return None
    if op in ("point", "touch"):
        s.points.append(rec)
        if rec.get("pose_index") is not None:
            s.done[rec["pose_index"]] = True
    elif op == "plate_image":
        s.images.append(rec)
    elif op == "miss" and rec.get("pose_index") is not None:
        s.failed[rec["pose_index"]] = True
    elif op == "ending":
        s.pending = rec
    elif op == "end":
        s.state, s.result, s.pending = "calibrated", rec, None
    elif op == "abort":
        s.state, s.points, s.pending = "aborted", [], None
    elif op in ("drop", "keep"):
        for p in s.points:
            if p["n"] == rec["n"]:
                p["dropped"] = op == "drop"
                if p.get("pose_index") is not None:
                    s.done[p["pose_index"]] = op == "keep"
    return s


__all__ = ["COLLECTION", "PLATE", "Session", "apply"]
