"""The collection protocol: the robot drives a calibration over a line protocol, the camera is live.

Transport-independent: :meth:`Collector.handle` takes one command line and returns one reply line
(without its line end). The TCP service feeds it the lines that start with ``CAL``; mapping lines
``u,v[,z]`` stay with the line service.

Commands (case-insensitive; fields separated by commas; ``.`` decimal point always; a trailing CR of
a CR LF line is ignored). Every reply is one line, ``OK …`` or ``ERR <reason>``:

``CAL BEGIN <name>[,<model>]`` / ``CAL BEGIN <name>,<plan>,<x0>,<y0>,<x1>,<y1>,<z>[,<model>]``
    Open a collection for calibration ``<name>`` (letters, digits, ``_ - .``; at most 64). With a plan
    (``grid:5x5``, ``radial:17``, ``random:25`` — as ``eyetohand plan`` spells them) over the
    rectangle x0..x1, y0..y1 (mm) at height z, ``CAL NEXT`` hands out its poses (a grid row by row,
    every other row reversed, so the robot snakes; ``random:`` drawn with seed 0). A model name
    (``auto`` when left out) is what ``CAL END`` fits. A BEGIN identical to the open collection's
    resumes it (a robot program restarted after a crash); any other BEGIN while one is open is an
    ERR: ``CAL END`` or ``CAL ABORT`` it first. → ``OK``
``CAL NEXT``
    → ``OK <x>,<y>,<z>``: the first planned pose neither recorded nor failed, or ``OK DONE``.
``CAL POINT <x>,<y>,<z>[,<angle>]``
    The robot stands at (x, y, z) mm, tool angle ``angle`` deg (0 when left out): two grabs, the
    target detected in both; they must agree within ``still_tol_px`` (default
    :data:`STILL_TOL_PX` = 0.2 px, the distance between the two centres) — else ``ERR moving``. The
    point recorded is the first grab's detection (full search and intensity-model refinement); the
    second grab is searched only near it (edge refinement: cheaper, precise enough for 0.2 px).
    → ``OK <n>,<u>,<v>`` (n: points recorded so far), or ``ERR <reason>`` with nothing recorded,
    the reason starting with one of ``target not found``, ``ambiguous``, ``moving``, ``outside the
    image``, ``timeout``. A pose matching a planned one
    (within 0.01 mm) marks it done — or failed on ERR, so ``CAL NEXT`` moves on; a POINT at a pose
    already recorded (1 µm, same angle) records nothing and answers that point's reply again (a
    robot retrying after a lost reply).
``CAL END``
    Fit the points (the BEGIN's model, default ``auto``), save as the calibration's new version
    (``save_fn``) → ``OK <model>,<n>,<loo_rms_mm>,<loo_max_mm>`` (leave-one-out errors of the fit);
    or ``ERR <reason>`` with every point kept, for more POINTs and another END.
``CAL ABORT`` → ``OK`` (the points are dropped from the session; the journal keeps them).
``CAL PLATE <spec>[,<name>[,<placement>]]``, ``CAL TOUCH <label>,<x>,<y>,<z>``, then ``CAL END``
    A plate commissioning session instead of a collection: one image of a calibration plate, the robot's
    touches of its corners (:mod:`eyetohand.cell.plate_session`). ABORT, STATUS and the journal serve
    both kinds of session; NEXT and POINT are a collection's, TOUCH a plate session's.
``CAL STATUS`` → ``OK <name>,<n>,<state>``; state ``none`` (no collection yet: name ``-``),
    ``collecting``, ``calibrated`` (after a successful END) or ``aborted``.
``CAL CHECK <x>,<y>,<z>``
    After calibration: the robot holds the target at (x, y, z); grab (twice, as POINT), detect, map the
    centre with the current calibration → ``OK <dx_mm>,<dy_mm>,<error_mm>`` (mapped minus commanded;
    error the length of (dx, dy)), appended to the verification history ``<name>.checks.jsonl``.

Numbers in replies are fixed-point, 4 decimals (mm and px), never locale-formatted.

**Reply formats.** ``plain`` (above) or ``ur``: for URScript's ``socket_read_ascii_float(4)`` every
reply becomes exactly four numbers in brackets ``(status,a,b,c)``: status 1 for OK, 0 for ``OK DONE``,
a negative code for ERR (the refusal's kind, ``CommandError.code``, numbered by :data:`UR_ERROR_CODES`),
fields padded with 0 — NEXT ``(1,x,y,z)``, POINT ``(1,n,u,v)``, END ``(1,n,loo_rms,loo_max)`` (the
model's name is in the journal), STATUS ``(1,n,state,planned)`` with the state as :data:`UR_STATES`,
CHECK ``(1,dx,dy,error)``, PLATE ``(1,points,4,0)``, TOUCH ``(1,n,u,v)``. A fixed count matters:
``socket_read_ascii_float`` answers ``[0, nan…]`` when it cannot read the count it asked for.

**Persistence.** Every state change is appended to a journal *before* the reply is sent and
``fsync``-ed: a JSONL file ``<store>/collect.jsonl`` (store a folder), or a table in an SQLite file
(store a path ending ``.db``/``.sqlite``/``.sqlite3``; WAL, synchronous=FULL). A record holds the
pose, the detection, and the SHA-256 of the image (optionally the image: ``keep_images``). A new
Collector on the same store replays the journal and continues the open collection with nothing
lost; a torn last line (a kill in mid-write) is cut off. ``CAL END`` journals its intent before it
stores the version and its end after (:mod:`eyetohand.cell.end_store`): a resent END after a crash
between the two stores nothing twice, and a failed journal write after the store still answers OK.

The parts: the session's state (:mod:`eyetohand.cell.session`), the target's grab
(:mod:`eyetohand.cell.grab`), END's store (:mod:`eyetohand.cell.end_store`), the plate's commands
(:mod:`eyetohand.cell.plate_session`); this module is the protocol over them.
"""

from __future__ import annotations

import contextlib
import hashlib
import sqlite3
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from eyetohand.cell import collection_session, plate_session
from eyetohand.cell.cal_replies import REPLY_FORMATS, UR_STATES, PlainReplies, ReplyFormat, URReplies
from eyetohand.cell.checks import CheckHistory, check_record
from eyetohand.cell.collection_session import NAME_RE, plan_poses
from eyetohand.cell.end_store import EndStore
from eyetohand.cell.grab import STILL_TOL_PX, TargetGrabber
from eyetohand.cell.journal import SQLITE_SUFFIXES, Journal, JsonlJournal, SqliteJournal, utc_now
from eyetohand.cell.line import UR_ERROR_CODES, CommandError, ErrorCode, ascii_reason, line_numbers
from eyetohand.cell.session import COLLECTION, PLATE, Session, apply
from eyetohand.core import InputError

UR_ERROR_OTHER = UR_ERROR_CODES[ErrorCode.OTHER]


# ------------------------------------------------------------------ helpers


def _f(x: float) -> str:
    return f"{float(x):.4f}"


def default_calibrate(pairs, model: str, image_size):
    from eyetohand.calibration import calibrate

    return calibrate(pairs, model=model, image_size=image_size, seed=0)


# ------------------------------------------------------------------ the collector


class Collector:
    """The collection state machine over a camera ``source`` (see the module docstring).

    ``store``: a folder (journal ``collect.jsonl``, default calibrations ``<name>.json`` and the
    verification histories ``<name>.checks.jsonl``) or an SQLite file (journal table; the other files beside
    it). ``calibrate_fn(pairs, model, image_size) -> Calibration`` (default:
    :func:`eyetohand.calibration.fit.calibrate` with seed 0); ``save_fn(name, cal)`` stores a new version
    (default: ``<name>.json`` written atomically); ``load_fn(name) -> Calibration | None`` the current one,
    for CHECK (default: that file). ``calibration``: the name CHECK uses before any BEGIN (the server's
    ``--calibration``). ``detect_options`` go to :func:`eyetohand.vision.detect.detect_target`.
    ``reply_format``: a name of :data:`REPLY_FORMATS` (``plain`` or ``ur``), held as :attr:`replies`.
    ``begin_rule(name)``: why a collection for ``name`` is refused at BEGIN, or None (the server: only
    the calibration its mapping lines serve). ``served_fn() -> (name, version, cal, error)``: the
    calibration CHECK checks instead of ``load_fn(calibration)`` (the server: the one its mapping lines
    use, so a check and a mapping answer never come from two calibrations). ``journal``: where the
    records go instead of the store's own (a :class:`~eyetohand.cell.journal.Journal`; the tests' seam
    for a failing write).
    """

    def __init__(
        self,
        store,
        source,
        *,
        calibrate_fn: Callable | None = None,
        save_fn: Callable | None = None,
        load_fn: Callable | None = None,
        calibration: str | None = None,
        reply_format: str = "plain",
        still_tol_px: float = STILL_TOL_PX,
        detect_options: dict | None = None,
        keep_images: bool = False,
        begin_rule: Callable[[str], str | None] | None = None,
        served_fn: Callable[[], tuple[str, int | None, Any, str | None]] | None = None,
        on_check: Callable[[dict], None] | None = None,
        journal: Journal | None = None,
    ):
        """``on_check(record)``: called with each CAL CHECK record once it is kept in the history
        (``serve`` adds it to its store's audit trail)."""
        if reply_format not in REPLY_FORMATS:
            raise InputError(f"reply format {reply_format!r}: expected one of {', '.join(REPLY_FORMATS)}")
        self.grabber = TargetGrabber(source, still_tol_px, detect_options)
        store = Path(store)
        self.journal: Journal
        if store.suffix.lower() in SQLITE_SUFFIXES:
            self.dir = store.parent
            self.journal = journal or SqliteJournal(store)
        else:
            if store.exists() and not store.is_dir():
                raise InputError(f"{store}: exists and is not a folder")
            self.dir = store
            self.journal = journal or JsonlJournal(store / "collect.jsonl")
        self.source = source
        self.checks = CheckHistory(self.dir)
        self.calibrate_fn = calibrate_fn or default_calibrate
        self.save_fn = save_fn or self._save_file
        self.load_fn = load_fn or self._load_file
        self.on_check = on_check
        self.replies: ReplyFormat = REPLY_FORMATS[reply_format]()
        self.keep_images = keep_images
        self.calibration_name = calibration
        self.begin_rule = begin_rule
        self.served_fn = served_fn
        self.image_size: tuple[int, int] | None = None
        self._lock = threading.Lock()  # one command at a time; a live view takes it only when free
        self.session: Session | None = None
        for rec in self.journal.records():
            self._apply(rec)
        self.end_store = EndStore(
            self._record, lambda rec: self._apply({**rec, "utc": utc_now()}), self.save_fn, self.load_fn
        )

    @property
    def last_grab(self) -> tuple | None:
        """(image, Detection, utc) of the last POINT/CHECK grab (the workbench's live view)."""
        return self.grabber.last_grab

    # ---------------------------------------------------------------- files
    def _save_file(self, name: str, cal) -> None:
        cal.save(self.dir / f"{name}.json")

    def _load_file(self, name: str):
        from eyetohand.calibration import Calibration

        path = self.dir / f"{name}.json"
        return Calibration.load(path) if path.exists() else None

    def history_path(self, name: str) -> Path:
        return self.checks.path(name)

    def history(self, name: str) -> list[dict]:
        """The verification history of calibration ``name`` (CAL CHECK records, oldest first)."""
        return self.checks.records(name)

    def close(self) -> None:
        self.journal.close()

    def refuse(self, reason: str) -> str:
        """The reply refusing a command before it ran (the line service's ``ERR busy``), in this
        collector's reply format."""
        return self.replies.error(CommandError(reason, ErrorCode.BUSY))

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- journal replay
    def _record(self, rec: dict) -> None:
        """Journal ``rec`` (fsync-ed), then apply it; a write that fails is a refusal with nothing
        recorded (the journal cuts off what it wrote in part)."""
        rec = {**rec, "utc": utc_now()}
        try:
            self.journal.append(rec)
        except (OSError, sqlite3.Error) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise CommandError(f"journal write failed ({why}); nothing recorded") from None
        self._apply(rec)

    def _apply(self, rec: dict) -> None:
        self.session = apply(self.session, rec)
        if rec["op"] in ("begin", "plate"):
            self.calibration_name = rec["name"]
        if rec["op"] == "point" and rec.get("image_size"):
            self.image_size = tuple(rec["image_size"])

    @property
    def reply_format(self) -> str:
        """The name of the reply format (:data:`REPLY_FORMATS`)."""
        return self.replies.name

    @property
    def state(self) -> str:
        return "none" if self.session is None else self.session.state

    @property
    def points(self) -> list[dict]:
        """The recorded points of the current collection (journal records; a dropped one has
        ``"dropped": True`` and is left out of the fit)."""
        return [] if self.session is None else list(self.session.points)

    def _active(self, s: Session) -> list[dict]:
        return s.active()

    def drop(self, n: int, keep: bool = False) -> dict:
        """Leave point ``n`` out of the fit (``keep``: take it back in), journaled like a command.
        A dropped planned pose is offered again by ``CAL NEXT``. Raises :class:`CommandError`."""
        with self._lock:
            s = self._open()
            match = [p for p in s.points if p["n"] == n]
            if not match:
                raise CommandError(f"no point {n} in collection '{s.name}' (points 1..{len(s.points)})")
            if bool(match[0].get("dropped")) != (not keep):
                self._record({"op": "keep" if keep else "drop", "name": s.name, "n": n})
            return dict(match[0])

    def status(self) -> dict:
        """The collection as JSON-ready data (what the workbench's collection view shows): plan poses
        with done/failed flags, the points with their detections, the fit result of the last END."""
        with self._lock:
            s = self.session
            if s is None:
                return {
                    "name": None,
                    "state": "none",
                    "poses": [],
                    "points": [],
                    "result": None,
                    "calibration": self.calibration_name,
                }
            if s.kind == PLATE:
                return {**plate_session.status(s), "calibration": self.calibration_name}
            return {**s.status(), "calibration": self.calibration_name}

    # ---------------------------------------------------------------- protocol
    @contextlib.contextmanager
    def camera_if_idle(self) -> Iterator[bool]:
        """True, holding the collection's lock (no command grabs meanwhile), when no command is running;
        else False at once: for a live view that must never wait behind a command's grab."""
        idle = self._lock.acquire(blocking=False)
        try:
            yield idle
        finally:
            if idle:
                self._lock.release()

    def handle(self, line: str) -> str:
        """The reply (one line, no line end) to one command line. Never raises: a failure of the
        camera or of the fit is answered ``ERR internal error: …`` (journal records are written
        whole or not at all, so the state stays consistent)."""
        if isinstance(line, bytes):
            try:
                line = line.decode("ascii")
            except UnicodeDecodeError:
                return self.replies.error(CommandError("not ASCII text"))
        text = line.rstrip("\r\n").strip()
        with self._lock:
            try:
                cmd, fields = self._dispatch(text)
            except CommandError as exc:
                return self.replies.error(exc)
            except InputError as exc:
                return self.replies.error(CommandError(str(exc).splitlines()[0]))
            except Exception as exc:  # a camera or a fit that breaks: still one ERR line, state intact
                return self.replies.error(CommandError(f"internal error: {type(exc).__name__}: {exc}"))
            planned = 0 if self.session is None else len(self.session.poses)
        if fields is None:
            return self.replies.done()
        return self.replies.ok(cmd, fields, planned)

    def _dispatch(self, text: str) -> tuple[str, list[str] | None]:
        """The command word and its reply fields (None: NEXT has no pose left)."""
        words = text.split(None, 2)
        if len(words) < 2 or words[0].upper() != "CAL":
            raise CommandError(
                "unknown command; expected CAL BEGIN|NEXT|POINT|END|ABORT|STATUS|CHECK|PLATE|TOUCH"
            )
        cmd = words[1].upper()
        args = [a.strip() for a in words[2].split(",")] if len(words) > 2 else []
        handler = {
            "BEGIN": self._begin,
            "NEXT": self._next,
            "POINT": self._point,
            "END": self._end,
            "ABORT": self._abort,
            "STATUS": self._status,
            "CHECK": self._check,
            "PLATE": self._plate,
            "TOUCH": self._touch,
        }.get(cmd)
        if handler is None:
            raise CommandError(
                f"unknown command CAL {cmd[:20]}; expected BEGIN, NEXT, POINT, END, ABORT, STATUS, CHECK, "
                "PLATE or TOUCH"
            )
        if cmd in ("NEXT", "END", "ABORT", "STATUS") and args:
            raise CommandError(f"CAL {cmd} takes no fields")
        return cmd, handler(args)

    # -- BEGIN, NEXT, POINT (eyetohand.cell.collection_session)
    def _begin(self, args: list[str]) -> list:
        fields = collection_session.parse_begin(args)
        name = fields["name"]
        why = self.begin_rule(name) if self.begin_rule is not None else None
        if why:
            raise CommandError(f"CAL BEGIN {name}: {why}")
        collection_session.check_model(fields["model"])
        s = self.session
        if s is not None and s.state == "collecting":
            if collection_session.same_begin(s, fields):
                return []  # resume
            self._busy(s)
        self._record({"op": "begin", "session": uuid.uuid4().hex, **fields})
        return []

    @staticmethod
    def _busy(s: Session) -> None:
        what = "plate session" if s.kind == PLATE else "collection"
        raise CommandError(
            f"busy: {what} '{s.name}' is open with {len(s.points)} "
            + ("touches" if s.kind == PLATE else "points")
            + "; send CAL END or CAL ABORT first",
            ErrorCode.BUSY,
        )

    def _open(self, kind: str | None = None) -> Session:
        """The open session (of ``kind``, when given), or the refusal."""
        s = self.session
        if s is None or s.state != "collecting":
            raise CommandError("no collection open; send CAL BEGIN <name> first", ErrorCode.NO_COLLECTION)
        if kind == PLATE and s.kind != PLATE:
            raise CommandError(
                f"collection '{s.name}' is open, not a plate session: CAL TOUCH follows CAL PLATE <spec>",
                ErrorCode.NO_COLLECTION,
            )
        if kind is not None and kind != PLATE and s.kind == PLATE:
            raise CommandError(
                f"plate session '{s.name}' is open: send CAL TOUCH <label>,<x>,<y>,<z> for its corners, "
                "then CAL END",
                ErrorCode.NO_COLLECTION,
            )
        return s

    # -- PLATE, TOUCH (eyetohand.cell.plate_session)
    def _plate(self, args: list[str]) -> list:
        spec, name, placement = plate_session.parse_plate(args, self.calibration_name)
        if not NAME_RE.match(name):
            raise CommandError(f"CAL PLATE: name {name[:30]!r}: use letters, digits, _ - . (at most 64)")
        why = self.begin_rule(name) if self.begin_rule is not None else None
        if why:
            raise CommandError(f"CAL PLATE {name}: {why}")
        s = self.session
        if s is not None and s.state == "collecting":
            if s.kind != PLATE or not plate_session.same_plate(s, spec, name):
                self._busy(s)
            taken = len(s.images)
            if placement <= taken:
                return plate_session.plate_reply(s)  # resume: no new grab
            if placement > taken + 1:
                raise CommandError(
                    f"CAL PLATE: placement {placement}: this session has {taken}; the next is {taken + 1}"
                )
            found = plate_session.grab_plate(self.source, spec, self.dir, name)
            self._record({"op": "plate_image", "name": name, "placement": placement, **found})
            return plate_session.plate_reply(s)
        if placement != 1:
            raise CommandError(
                f"CAL PLATE: placement {placement}: no plate session is open; placement 1 opens one"
            )
        found = plate_session.grab_plate(self.source, spec, self.dir, name)
        self._record({"op": "plate", "name": name, "session": uuid.uuid4().hex, **found})
        assert self.session is not None
        return plate_session.plate_reply(self.session)

    def _touch(self, args: list[str]) -> list:
        s = self._open(PLATE)
        rec, reply = plate_session.touch(s, args)
        if rec is not None:
            self._record(rec)
        return reply

    def _next(self, args) -> list[str] | None:
        return collection_session.next_pose(self._open(COLLECTION))

    def _point(self, args: list[str]) -> list:
        xyz, angle, angle_given = collection_session.parse_point(args)
        s = self._open(COLLECTION)
        again = collection_session.repeat_reply(s, xyz, angle)
        if again is not None:
            return again
        idx = collection_session.pose_index(s, xyz)
        try:
            grab = self.grabber.acquire(xyz, angle)
        except CommandError as exc:
            if idx is not None and not s.done[idx]:
                miss = {"op": "miss", "pose_index": idx, "xyz_mm": xyz, "angle_deg": angle}
                self._record({**miss, "reason": ascii_reason(str(exc))})
            raise
        self.image_size = grab.image_size
        n = len(s.points) + 1
        digest = hashlib.sha256(np.ascontiguousarray(grab.image).tobytes()).hexdigest()
        image_file = None
        if self.keep_images:
            import cv2

            from eyetohand.core import atomic_write_bytes

            rel = Path("images") / s.name / f"{n:04d}_{digest[:12]}.png"
            atomic_write_bytes(self.dir / rel, cv2.imencode(".png", grab.image)[1].tobytes())
            image_file = str(rel)
        rec = collection_session.point_record(s, xyz, angle, angle_given, idx, grab, digest, image_file)
        self._record(rec)
        return [str(n), _f(grab.uv_px[0]), _f(grab.uv_px[1])]

    # -- END
    def pairs(self):
        """The current collection's points as :class:`~eyetohand.core.pairs.PointPairs`."""
        return collection_session.pairs(self._open(COLLECTION))

    def _end(self, args) -> list:
        s = self._open()
        settled = self.end_store.settle(s)  # an END stored before a crash or a failed journal write
        if settled is not None:
            return list(settled["reply"])
        if s.kind == PLATE:
            cal, result = plate_session.fit_plate(s)
        else:
            cal, result = collection_session.fit_collection(s, self.calibrate_fn, self.image_size)
        return list(self.end_store.store(s, cal, result)["reply"])

    def _abort(self, args) -> list:
        s = self._open()
        self._record({"op": "abort", "name": s.name, "n": len(s.points)})
        return []

    def _status(self, args) -> list:
        s = self.session
        if s is None:
            return ["-", "0", "none"]
        n = s.result["n"] if s.state == "calibrated" and s.result else len(self._active(s))
        return [s.name, str(n), s.state]

    # -- CHECK
    def _check(self, args: list[str]) -> list:
        if len(args) != 3:
            raise CommandError(f"CAL CHECK: {len(args)} fields; expected <x>,<y>,<z>")
        xyz = line_numbers(args, ("x", "y", "z"), "CAL CHECK")
        version = None
        if self.served_fn is not None:  # what the mapping lines use, whatever was collected
            name, version, cal, why = self.served_fn()
            if cal is None:
                raise CommandError(f"no calibration to check: {why}", ErrorCode.NO_CALIBRATION)
        else:
            name = self.calibration_name or ""
            cal = self.load_fn(name) if name else None
            if cal is None or not name:
                raise CommandError(
                    "no calibration to check"
                    + (f": '{name}' has none yet" if name else "; send CAL BEGIN … CAL END first"),
                    ErrorCode.NO_CALIBRATION,
                )
        grab = self.grabber.acquire(xyz, 0.0)
        self.image_size = grab.image_size
        rec = check_record(name, version, cal, xyz, grab.uv_px, grab.image)
        self.checks.append(rec)
        if self.on_check is not None:
            self.on_check(rec)
        return [_f(rec["dx_mm"]), _f(rec["dy_mm"]), _f(rec["error_mm"])]


__all__ = [
    "REPLY_FORMATS",
    "STILL_TOL_PX",
    "UR_ERROR_CODES",
    "UR_ERROR_OTHER",
    "UR_STATES",
    "Collector",
    "PlainReplies",
    "ReplyFormat",
    "URReplies",
    "NAME_RE",
    "default_calibrate",
    "plan_poses",
]
