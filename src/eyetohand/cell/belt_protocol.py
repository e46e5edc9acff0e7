"""The conveyor's line protocol: map parts seen on the belt to where they are now, and collect a belt
calibration from the robot's side.

Transport-independent, like :mod:`eyetohand.cell.collect`: :meth:`BeltProtocol.handle` takes one command
line and returns one reply line (no line end); the TCP service feeds it the lines starting ``BELT``.
Fields are separated by commas, ``.`` is the decimal point, encoder counts are whole numbers in the
counter's range (``Encoder.check``); every reply is ``OK …`` or ``ERR <reason>`` (numbers fixed-point,
4 decimals for mm and px, 8 for mm per count, 6 for degrees).

Mapping (needs a conveyor calibration, :class:`~eyetohand.cell.conveyor.ConveyorCalibration`):

``BELT <u>,<v>,<e_image>,<e_now>[,a=<deg>][,s=<N>][,t=<deg>]``
    The part seen at pixel (u, v) in the image latched at ``e_image`` → ``OK x,y,z`` where it is when
    the encoder reads ``e_now`` (counts taken modulo the counter's range: a rollover in between is
    fine); with ``a=`` the image angle of the part (deg, +u towards +v) also its robot ``rz``
    (``OK x,y,z,rz``: the belt translates, it does not turn the part); ``s=`` and ``t=`` as on the
    TCP mapping line (rz folded for a part symmetric under 360/N turns; the gripper's rz when aligned
    with the image's +u). Refused, with how far: a part
    outside the robot's window (``ERR the part is 12.3 mm downstream of the robot window's far end
    …``) and a pixel outside the calibrated image region.
``BELT TRACK <u>,<v>,<e_image>``
    What a controller's own conveyor tracking wants → ``OK x,y,z,bx,by,bz``: the part's position at
    the latched count (the latch delay applied) and the belt vector (mm per count); the controller
    adds ``b · Δe`` itself. The image-region guard applies (the window is the controller's).

Collecting (needs a camera ``source``; the session is journaled to ``<store_dir>/belt.jsonl`` and
survives a restart like the CAL collection):

``BELT BEGIN <name>[,<model>]`` → ``OK`` (``model`` default ``homography-radial``; a BEGIN identical to
    the open session's resumes it)
``BELT SIGHT <id>[,<e>][,stopped]``
    Grab one image and detect the part's target in it; ``e`` the count latched with the image (left
    out: the count the source latched with the frame, ``source.encoder_count``, where the source
    provides one — ``folder:DIR?encoder=1`` and ``genicam:CTI?encoder=1`` do, see
    :mod:`eyetohand.vision.sources`; else give it); ``stopped`` when the belt stood
    still for the image (sightings with the belt both stopped and running let END fit the latch
    delay) → ``OK <u>,<v>``. A part may be sighted again — another frame of it, e.g. once with the belt
    stopped under the camera and once running: END then tests the latch delay within each part, its
    touches' errors cancelling. Counts going back by more than the noise allowance (5 counts) are an
    ERR.
``BELT TOUCH <id>,<x>,<y>,<z>,<e>`` — the robot touched part ``id`` at (x, y, z) mm with the belt
    stopped at count ``e`` → ``OK <n_touches>``; a part not sighted yet in the session is an ERR
    naming the missing ``BELT SIGHT``.
``BELT END`` — :func:`~eyetohand.cell.conveyor.calibrate_conveyor` on the session (rows in the order they
    came), saved as ``<store_dir>/<name>.conveyor.json``, and served by the mapping commands from then
    on → ``OK <parts>,<touches>,<mm_per_count>,<yaw_deg>,<pitch_deg>,<rms_mm>``; on ERR the session
    stays open.
``BELT ABORT`` → ``OK``; ``BELT STATUS`` → ``OK <name>,<sightings>,<touches>,<state>`` (state ``none``,
    ``collecting``, ``calibrated`` or ``aborted``).
"""

from __future__ import annotations

import math
import os
import threading
from pathlib import Path

import numpy as np

from eyetohand.cell.collect import NAME_RE
from eyetohand.cell.conveyor import ConveyorCalibration, Encoder, Session, calibrate_conveyor
from eyetohand.cell.journal import JsonlJournal, utc_now
from eyetohand.cell.line import CommandError, ErrorCode, Refusal, ascii_reason, line_count, line_numbers
from eyetohand.cell.replies import PLAIN, LineReplies
from eyetohand.core import InputError
from eyetohand.geometry import check_symmetry

NOISE_COUNTS = 5
DEFAULT_MODEL = "homography-radial"
USAGE = (
    "BELT u,v,e_image,e_now[,a=DEG][,s=N][,t=DEG] | BELT TRACK u,v,e_image | "
    "BELT BEGIN|SIGHT|TOUCH|END|ABORT|STATUS"
)


def _count(text: str, name: str, encoder: Encoder) -> int:
    t = text.strip()
    try:
        if "_" in t:  # not a plain decimal (as for every other number on the line)
            raise ValueError(t)
        v = int(t)
    except ValueError:
        raise CommandError(f"{name}: {t[:20]!r} is not a whole number of counts") from None
    try:
        encoder.check(v, name)
    except InputError as exc:
        raise CommandError(str(exc).splitlines()[0]) from None
    return v


#: ``BELT u,v,e_image,e_now`` words, as on the TCP mapping line: the part's image angle (deg), its
#: rotational symmetry (rz folded into 360/N), the gripper's rz when aligned with the image's +u (deg)
ORIENTATION_WORDS = ("a", "s", "t")


def _mm(v: float) -> str:
    return f"{float(v):.4f}"


class BeltProtocol:
    """The BELT commands (module docstring). ``conveyor``: a ConveyorCalibration or its JSON file (or
    None until a BELT END fits one); ``source``: the camera for SIGHT; ``store_dir``: where the session
    journal and fitted conveyors go; ``encoder``: the counter for collecting without a served
    conveyor (default the served one's, else 24-bit unsigned)."""

    def __init__(
        self,
        conveyor=None,
        *,
        source=None,
        store_dir: str | os.PathLike | None = None,
        encoder: Encoder | None = None,
        detect_options: dict | None = None,
        replies: LineReplies = PLAIN,
    ):
        if conveyor is not None and not isinstance(conveyor, ConveyorCalibration):
            conveyor = ConveyorCalibration.load(conveyor)
        self.conveyor: ConveyorCalibration | None = conveyor
        self.source = source
        self.replies = replies  # the server's reply format: its refusals are worded (and coded) here
        self.encoder = encoder or (conveyor.encoder if conveyor is not None else Encoder())
        self.detect_options = dict(detect_options or {})
        self.dir = Path(store_dir) if store_dir is not None else None
        self.journal = JsonlJournal(self.dir / "belt.jsonl") if self.dir is not None else None
        self._lock = threading.Lock()
        self.session: dict | None = None
        self.image_size: tuple[int, int] | None = None
        if self.journal is not None:
            for rec in self.journal.records():
                self._apply(rec)

    def close(self) -> None:
        if self.journal is not None:
            self.journal.close()

    # ---------------------------------------------------------------- journal
    def _record(self, rec: dict) -> None:
        rec = {**rec, "utc": utc_now()}
        if self.journal is not None:
            self.journal.append(rec)
        self._apply(rec)

    def _apply(self, rec: dict) -> None:
        op, s = rec["op"], self.session
        if op == "begin":
            self.session = {"name": rec["name"], "model": rec["model"], "rows": [], "state": "collecting"}
        elif s is None:
            return
        elif op in ("sight", "touch"):
            s["rows"].append(rec)
            if rec.get("image_size"):
                self.image_size = tuple(rec["image_size"])
        elif op == "end":
            s["state"], s["result"] = "calibrated", rec
        elif op == "abort":
            s["state"] = "aborted"

    # ---------------------------------------------------------------- protocol
    def handle(self, line) -> str:
        """The reply to one line (never raises: a failure is one ``ERR`` line)."""
        if isinstance(line, bytes):
            try:
                line = line.decode("ascii")
            except UnicodeDecodeError:
                return self._refused(ErrorCode.OTHER, "not ASCII text")
        text = line.rstrip("\r\n").strip()
        with self._lock:
            try:
                fields = self._dispatch(text)
            except CommandError as exc:
                return self._refused(exc.code, str(exc))
            except InputError as exc:  # one part per line: its index says nothing (as on the TCP line)
                reason = exc.reason if exc.index is not None else str(exc)
                return self._refused(ErrorCode.OTHER, reason.splitlines()[0])
            except Exception as exc:  # a camera or a fit that breaks: still one ERR line
                return self._refused(ErrorCode.OTHER, f"internal error: {type(exc).__name__}: {exc}")
        return "OK" + (" " + ",".join(fields) if fields else "")

    def _refused(self, code: ErrorCode, reason: str) -> str:
        """A refusal in the server's reply format: ``ERR <reason>``, or its code in ``ur``."""
        return self.replies.refusal_line(Refusal(code, ascii_reason(reason)), "BELT")

    def _dispatch(self, text: str) -> list[str]:
        words = text.split(None, 1)
        if not words or words[0].upper() != "BELT":
            raise CommandError(f"unknown command; expected {USAGE}")
        rest = words[1] if len(words) > 1 else ""
        head = rest.split(None, 1)
        cmd = head[0].upper() if head else ""
        handlers = {
            "TRACK": self._track,
            "BEGIN": self._begin,
            "SIGHT": self._sight,
            "TOUCH": self._touch,
            "END": self._end,
            "ABORT": self._abort,
            "STATUS": self._status,
        }
        if cmd in handlers:
            args = [a.strip() for a in head[1].split(",")] if len(head) > 1 else []
            if cmd in ("END", "ABORT", "STATUS") and args:
                raise CommandError(f"BELT {cmd} takes no fields")
            return handlers[cmd](args)
        if not rest:
            raise CommandError(f"BELT: no fields; expected {USAGE}")
        return self._map([a.strip() for a in rest.split(",")])

    def _served(self) -> ConveyorCalibration:
        if self.conveyor is None:
            raise CommandError(
                "no conveyor calibration: start serve with --conveyor FILE, or collect one "
                "(BELT BEGIN … BELT END)",
                ErrorCode.NO_CALIBRATION,
            )
        return self.conveyor

    # -- mapping
    def _map(self, args: list[str]) -> list[str]:
        nums = [a for a in args if "=" not in a]
        words = [a.lower() for a in args[len(nums) :]]
        if args[: len(nums)] != nums or len(nums) != 4:
            raise CommandError(f"BELT: {len(nums)} numbers; expected u,v,e_image,e_now[,a=DEG][,s=N][,t=DEG]")
        conv = self._served()
        u, v = line_numbers(nums[:2], ("u", "v"), None)  # refused in the TCP mapping line's words
        e_img = _count(nums[2], "e_image", conv.encoder)
        e_now = _count(nums[3], "e_now", conv.encoder)
        opts: dict[str, float] = {}
        for w in words:  # the orientation words the TCP mapping line takes, with its meanings
            key, sep, text = w.partition("=")
            if not sep or key not in ORIENTATION_WORDS:
                raise CommandError(f"BELT: unknown word {w[:20]!r}; expected a=DEG, s=N or t=DEG")
            if key in opts:
                raise CommandError(f"BELT: {key} given twice")  # which one was meant is not guessed
            opts[key] = line_numbers([text], (key,), None)[0]
        s = opts.get("s", 1.0)
        # with or without an angle, as the TCP line and the library: text "2.0" is the whole number 2
        symmetry = check_symmetry(line_count(s))
        angle = opts.get("a")
        uv = np.array([[u, v]])
        with np.errstate(all="ignore"):
            out = [_mm(c) for c in conv.image_to_robot_at(uv, e_img, e_now)[0]]
            if angle is not None:
                rz = conv.rz_deg(uv, angle, symmetry=symmetry, tool_rz_offset_deg=opts.get("t"))
                out.append(f"{float(rz[0]):.4f}")
        return out

    def _track(self, args: list[str]) -> list[str]:
        if len(args) != 3:
            raise CommandError(f"BELT TRACK: {len(args)} fields; expected u,v,e_image")
        conv = self._served()
        u, v = line_numbers(args[:2], ("u", "v"), "BELT TRACK")
        e_img = _count(args[2], "e_image", conv.encoder)
        with np.errstate(all="ignore"):
            t = conv.tracking_form(np.array([[u, v]]), e_img)
        b = t["belt_mm_per_count"]
        return [_mm(c) for c in t["position_mm"][0]] + [f"{float(c):.8f}" for c in b]

    # -- collecting
    def _open(self) -> dict:
        s = self.session
        if s is None or s["state"] != "collecting":
            raise CommandError("no belt session open; send BELT BEGIN <name> first", ErrorCode.NO_COLLECTION)
        return s

    def _begin(self, args: list[str]) -> list[str]:
        from eyetohand.models import get_model

        if self.journal is None:
            raise CommandError("belt collection needs a store folder (serve --collect-dir)")
        if not args or not args[0] or len(args) > 2:
            raise CommandError("BELT BEGIN: expected <name>[,<model>]")
        name = args[0]
        if not NAME_RE.match(name):
            raise CommandError(f"BELT BEGIN: name {name[:30]!r}: use letters, digits, _ - . (at most 64)")
        model = args[1] if len(args) == 2 and args[1] else DEFAULT_MODEL
        try:
            get_model(model)
        except InputError as exc:
            raise CommandError(f"BELT BEGIN: {exc}") from None
        s = self.session
        if s is not None and s["state"] == "collecting":
            if s["name"] == name and s["model"] == model:
                return []
            raise CommandError(
                f"busy: belt session '{s['name']}' is open with {len(s['rows'])} rows; "
                "send BELT END or BELT ABORT first",
                ErrorCode.BUSY,
            )
        self._record({"op": "begin", "name": name, "model": model})
        return []

    def _check_count(self, s: dict, e: int, where: str) -> None:
        if not s["rows"]:
            return
        back = -int(self.encoder.delta(s["rows"][-1]["e"], e))
        if back > NOISE_COUNTS:
            raise CommandError(
                f"{where}: count {e} is {back} counts before the previous row's "
                f"{s['rows'][-1]['e']} (more than the {NOISE_COUNTS}-count noise allowance)"
            )

    def _sight(self, args: list[str]) -> list[str]:
        from eyetohand.vision import GrabTimeout, detect_target

        s = self._open()
        flags = [a for a in args[1:] if a.lower() in ("stopped", "moving")]
        rest = [a for a in args[1:] if a.lower() not in ("stopped", "moving")]
        if not args or not args[0] or len(rest) > 1:
            raise CommandError("BELT SIGHT: expected <id>[,<e>][,stopped]")
        pid = args[0]
        if self.source is None:
            raise CommandError("BELT SIGHT: no camera (start serve with --camera URI)")
        try:
            img, _ = self.source.grab()
        except GrabTimeout as exc:
            raise CommandError(f"timeout: {exc}", ErrorCode.TIMEOUT) from None
        latched = getattr(self.source, "encoder_count", None)
        if rest:
            e = _count(rest[0], "e", self.encoder)
        elif latched is not None:
            e = _count(str(latched), "e (latched by the camera)", self.encoder)
        else:
            raise CommandError("BELT SIGHT: no count given and the camera latches none; send <id>,<e>")
        self._check_count(s, e, "BELT SIGHT")
        d = detect_target(img, name=f"sighting {pid}", **self.detect_options)
        if not d.ok or d.u is None or d.v is None:
            raise CommandError(f"target not found: {d.reason}", ErrorCode.TARGET_NOT_FOUND)
        h, w = img.shape[:2]
        self._record(
            {
                "op": "sight",
                "id": pid,
                "u": float(d.u),
                "v": float(d.v),
                "e": e,
                "moving": "stopped" not in [f.lower() for f in flags],
                "image_size": [int(w), int(h)],
                "detection": d.to_dict(),
            }
        )
        return [_mm(d.u), _mm(d.v)]

    def _touch(self, args: list[str]) -> list[str]:
        s = self._open()
        if len(args) != 5 or not args[0]:
            raise CommandError(f"BELT TOUCH: {len(args)} fields; expected <id>,<x>,<y>,<z>,<e>")
        xyz = line_numbers(args[1:4], ("x", "y", "z"), "BELT TOUCH", "mm")
        e = _count(args[4], "e", self.encoder)
        if not any(r["op"] == "sight" and r["id"] == args[0] for r in s["rows"]):
            raise CommandError(
                f"BELT TOUCH: part {args[0][:30]!r} was never sighted; send BELT SIGHT {args[0][:30]} "
                "first (a touch pairs with the camera's sighting of the same part)"
            )
        self._check_count(s, e, "BELT TOUCH")
        self._record({"op": "touch", "id": args[0], "xyz_mm": xyz, "e": e})
        return [str(sum(r["op"] == "touch" for r in s["rows"]))]

    def session_rows(self) -> list[dict]:
        """The open session's rows as :meth:`Session.from_rows` takes them."""
        s = self._open()
        rows = []
        for k, r in enumerate(s["rows"], start=1):
            where = f"belt session {s['name']} row {k}"
            if r["op"] == "sight":
                rows.append(
                    {
                        "kind": "sight",
                        "id": r["id"],
                        "u": r["u"],
                        "v": r["v"],
                        "e": r["e"],
                        "moving": "1" if r["moving"] else "0",
                        "_where": where,
                    }
                )
            else:
                x, y, z = r["xyz_mm"]
                rows.append(
                    {"kind": "touch", "id": r["id"], "x": x, "y": y, "z": z, "e": r["e"], "_where": where}
                )
        return rows

    def _end(self, args) -> list[str]:
        s = self._open()
        rows = self.session_rows()
        if not rows:
            raise CommandError("fit failed: no rows recorded", ErrorCode.FIT_FAILED)
        try:
            session = Session.from_rows(rows, f"belt session {s['name']}")
            conv = calibrate_conveyor(
                session,
                model=s["model"],
                encoder=self.encoder,
                image_size=self.image_size,
                noise_counts=NOISE_COUNTS,
            )
        except InputError as exc:
            raise CommandError(f"fit failed: {str(exc).splitlines()[0]}", ErrorCode.FIT_FAILED) from None
        assert self.dir is not None
        path = conv.save(self.dir / f"{s['name']}.conveyor.json")
        rep = conv.report or {}
        belt = conv.belt
        self._record(
            {
                "op": "end",
                "name": s["name"],
                "file": str(path),
                "mm_per_count": belt.mm_per_count,
                "yaw_deg": belt.yaw_deg,
                "pitch_deg": belt.pitch_deg,
                "rms_mm": rep.get("rms_mm"),
            }
        )
        self.conveyor = conv
        return [
            str(rep.get("n_sighted_parts", 0)),
            str(rep.get("n_touches", 0)),
            f"{belt.mm_per_count:.8f}",
            f"{belt.yaw_deg:.6f}",
            f"{belt.pitch_deg:.6f}",
            _mm(float(rep.get("rms_mm", math.nan))),
        ]

    def _abort(self, args) -> list[str]:
        s = self._open()
        self._record({"op": "abort", "name": s["name"]})
        return []

    def _status(self, args) -> list[str]:
        s = self.session
        if s is None:
            return ["-", "0", "0", "none"]
        n_s = sum(r["op"] == "sight" for r in s["rows"])
        return [s["name"], str(n_s), str(len(s["rows"]) - n_s), s["state"]]


__all__ = ["BeltProtocol", "NOISE_COUNTS"]
