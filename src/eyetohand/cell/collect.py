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
CHECK ``(1,dx,dy,error)``. A fixed count matters: ``socket_read_ascii_float`` answers ``[0, nan…]`` when
it cannot read the count it asked for.

**Persistence.** Every state change is appended to a journal *before* the reply is sent and
``fsync``-ed: a JSONL file ``<store>/collect.jsonl`` (store a folder), or a table in an SQLite file
(store a path ending ``.db``/``.sqlite``/``.sqlite3``; WAL, synchronous=FULL). A record holds the
pose, the detection, and the SHA-256 of the image (optionally the image: ``keep_images``). A new
Collector on the same store replays the journal and continues the open collection with nothing
lost; a torn last line (a kill in mid-write) is cut off.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import sqlite3
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from eyetohand.cell.cal_replies import REPLY_FORMATS, UR_STATES, PlainReplies, ReplyFormat, URReplies
from eyetohand.cell.journal import SQLITE_SUFFIXES, JsonlJournal, SqliteJournal, utc_now
from eyetohand.cell.line import UR_ERROR_CODES, CommandError, ErrorCode, ascii_reason, line_numbers
from eyetohand.core import InputError

STILL_TOL_PX = 0.2
POSE_MATCH_MM = 0.01
REPEAT_MATCH_MM = 1e-3
NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")
UR_ERROR_OTHER = UR_ERROR_CODES[ErrorCode.OTHER]


# ------------------------------------------------------------------ helpers


def _f(x: float) -> str:
    return f"{float(x):.4f}"


def plan_poses(plan: str, x0: float, y0: float, x1: float, y1: float, z: float) -> np.ndarray:
    """The poses (n, 3) mm of ``plan`` over the rectangle x0..x1, y0..y1 at height z, in the order
    :meth:`Collector` hands them out (a grid snakes: every other row reversed)."""
    from eyetohand.cell.plans import parse_plan

    p = parse_plan(plan)
    q = p.layout_px((1001, 1001), 0.0, np.random.default_rng(0)) / 1000.0  # unit square
    if p.kind == "grid":
        q = q.reshape(p.rows, p.cols, 2)
        q[1::2] = q[1::2, ::-1]
        q = q.reshape(-1, 2)
    xs = x0 + (x1 - x0) * q[:, 0]
    ys = y0 + (y1 - y0) * q[:, 1]
    return np.column_stack([xs, ys, np.full(len(q), float(z))])


def default_calibrate(pairs, model: str, image_size):
    from eyetohand.calibration import calibrate

    return calibrate(pairs, model=model, image_size=image_size, seed=0)


def _classify(det) -> CommandError:
    """The refusal of a detection that found no target, by its kind (``det.miss``, a
    :class:`eyetohand.vision.Miss`), in its words."""
    from eyetohand.vision import Miss

    r = det.reason.removeprefix("no target found: ")
    if det.miss is Miss.AMBIGUOUS:
        return CommandError(det.reason, ErrorCode.AMBIGUOUS)
    if det.miss is Miss.CUT_BY_BORDER:
        return CommandError(f"outside the image: {r}", ErrorCode.OUTSIDE_IMAGE)
    return CommandError(f"target not found: {r}", ErrorCode.TARGET_NOT_FOUND)


class _Session:
    def __init__(self, rec: dict):
        self.begin = rec
        self.name = rec["name"]
        self.model = rec.get("model", "auto")
        self.poses = np.array(rec["poses"], float).reshape(-1, 3)
        self.done = np.zeros(len(self.poses), bool)
        self.failed = np.zeros(len(self.poses), bool)
        self.points: list[dict] = []
        self.state = "collecting"
        self.result: dict | None = None


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
    use, so a check and a mapping answer never come from two calibrations).
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
    ):
        """``on_check(record)``: called with each CAL CHECK record once it is kept in the history
        (``serve`` adds it to its store's audit trail)."""
        if reply_format not in REPLY_FORMATS:
            raise InputError(f"reply format {reply_format!r}: expected one of {', '.join(REPLY_FORMATS)}")
        if not (still_tol_px > 0):
            raise InputError(f"still_tol_px: expected a positive number of px, got {still_tol_px!r}")
        store = Path(store)
        self.journal: SqliteJournal | JsonlJournal
        if store.suffix.lower() in SQLITE_SUFFIXES:
            self.dir = store.parent
            self.journal = SqliteJournal(store)
        else:
            if store.exists() and not store.is_dir():
                raise InputError(f"{store}: exists and is not a folder")
            self.dir = store
            self.journal = JsonlJournal(store / "collect.jsonl")
        self.source = source
        self.calibrate_fn = calibrate_fn or default_calibrate
        self.save_fn = save_fn or self._save_file
        self.load_fn = load_fn or self._load_file
        self.on_check = on_check
        self.replies: ReplyFormat = REPLY_FORMATS[reply_format]()
        self.still_tol_px = float(still_tol_px)
        self.detect_options = dict(detect_options or {})
        self.keep_images = keep_images
        self.calibration_name = calibration
        self.begin_rule = begin_rule
        self.served_fn = served_fn
        self.image_size: tuple[int, int] | None = None
        self.last_grab: tuple | None = None  # (image, Detection, utc) of the last POINT/CHECK grab
        self._lock = threading.Lock()  # one command at a time; a live view takes it only when free
        self.session: _Session | None = None
        for rec in self.journal.records():
            self._apply(rec)

    # ---------------------------------------------------------------- files
    def _save_file(self, name: str, cal) -> None:
        cal.save(self.dir / f"{name}.json")

    def _load_file(self, name: str):
        from eyetohand.calibration import Calibration

        path = self.dir / f"{name}.json"
        return Calibration.load(path) if path.exists() else None

    def history_path(self, name: str) -> Path:
        return self.dir / f"{name}.checks.jsonl"

    def history(self, name: str) -> list[dict]:
        """The verification history of calibration ``name`` (CAL CHECK records, oldest first)."""
        path = self.history_path(name)
        if not path.exists():
            return []
        return [json.loads(x) for x in path.read_text(encoding="utf-8").splitlines() if x.strip()]

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
        op = rec["op"]
        s = self.session
        if op == "begin":
            self.session = _Session(rec)
            self.calibration_name = rec["name"]
        elif op == "point" and s is not None:
            s.points.append(rec)
            if rec.get("pose_index") is not None:
                s.done[rec["pose_index"]] = True
            if rec.get("image_size"):
                self.image_size = tuple(rec["image_size"])
        elif op == "miss" and s is not None and rec.get("pose_index") is not None:
            s.failed[rec["pose_index"]] = True
        elif op == "end" and s is not None:
            s.state, s.result = "calibrated", rec
        elif op == "abort" and s is not None:
            s.state, s.points = "aborted", []
        elif op in ("drop", "keep") and s is not None:
            for p in s.points:
                if p["n"] == rec["n"]:
                    p["dropped"] = op == "drop"
                    if p.get("pose_index") is not None:
                        s.done[p["pose_index"]] = op == "keep"

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

    def _active(self, s: _Session) -> list[dict]:
        return [p for p in s.points if not p.get("dropped")]

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
            poses = [
                {
                    "index": i,
                    "xyz_mm": [float(v) for v in p],
                    "done": bool(s.done[i]),
                    "failed": bool(s.failed[i]),
                }
                for i, p in enumerate(s.poses)
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
                for p in s.points
            ]
            return {
                "name": s.name,
                "state": s.state,
                "model": s.model,
                "plan": s.begin.get("plan"),
                "poses": poses,
                "points": points,
                "result": s.result,
                "calibration": self.calibration_name,
            }

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
            raise CommandError("unknown command; expected CAL BEGIN|NEXT|POINT|END|ABORT|STATUS|CHECK")
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
        }.get(cmd)
        if handler is None:
            raise CommandError(
                f"unknown command CAL {cmd[:20]}; expected BEGIN, NEXT, POINT, END, ABORT, STATUS or CHECK"
            )
        if cmd in ("NEXT", "END", "ABORT", "STATUS") and args:
            raise CommandError(f"CAL {cmd} takes no fields")
        return cmd, handler(args)

    # -- BEGIN
    def _begin(self, args: list[str]) -> list:
        from eyetohand.calibration import resolve_model

        if not args or not args[0]:
            raise CommandError("CAL BEGIN: expected <name>[,<plan>,<x0>,<y0>,<x1>,<y1>,<z>][,<model>]")
        name = args[0]
        if not NAME_RE.match(name):
            raise CommandError(f"CAL BEGIN: name {name[:30]!r}: use letters, digits, _ - . (at most 64)")
        model, plan, rect, poses = "auto", None, None, []
        rest = args[1:]
        if len(rest) in (6, 7):
            plan = rest[0]
            x0, y0, x1, y1, z = line_numbers(rest[1:6], ("x0", "y0", "x1", "y1", "z"), "CAL BEGIN", "mm")
            if x0 == x1 and y0 == y1:
                raise CommandError("CAL BEGIN: the plan's rectangle has no area (x0 = x1 and y0 = y1)")
            try:
                poses = plan_poses(plan, x0, y0, x1, y1, z).tolist()
            except InputError as exc:
                raise CommandError(f"CAL BEGIN: {exc}") from None
            rect = [x0, y0, x1, y1, z]
            rest = rest[6:]
        if len(rest) == 1:
            model = rest[0]
        elif rest:
            raise CommandError(
                f"CAL BEGIN: {len(args)} fields; expected <name>[,<model>] or "
                "<name>,<plan>,<x0>,<y0>,<x1>,<y1>,<z>[,<model>]"
            )
        why = self.begin_rule(name) if self.begin_rule is not None else None
        if why:
            raise CommandError(f"CAL BEGIN {name}: {why}")
        try:
            resolve_model(model)  # "auto" or a model's name; another refused listing the choices
        except InputError as exc:
            raise CommandError(f"CAL BEGIN: {exc}") from None
        s = self.session
        if s is not None and s.state == "collecting":
            same = (
                s.name == name
                and s.begin.get("plan") == plan
                and s.begin.get("rect") == rect
                and s.model == model
            )
            if same:
                return []  # resume
            raise CommandError(
                f"busy: collection '{s.name}' is open with {len(s.points)} points; "
                "send CAL END or CAL ABORT first",
                ErrorCode.BUSY,
            )
        self._record(
            {"op": "begin", "name": name, "plan": plan, "rect": rect, "model": model, "poses": poses}
        )
        return []

    def _open(self) -> _Session:
        s = self.session
        if s is None or s.state != "collecting":
            raise CommandError("no collection open; send CAL BEGIN <name> first", ErrorCode.NO_COLLECTION)
        return s

    # -- NEXT
    def _next(self, args) -> list[str] | None:
        s = self._open()
        if not len(s.poses):
            raise CommandError(  # the code the ur replies have always sent for it
                "no collection plan: CAL BEGIN was given no plan; send your own POINTs",
                ErrorCode.NO_COLLECTION,
            )
        left = np.flatnonzero(~(s.done | s.failed))
        if not len(left):
            return None
        return [_f(v) for v in s.poses[left[0]]]

    # -- acquisition
    def _acquire(self, xyz, angle):
        """Two grabs at the pose, the target in both → ((u, v), detection, image)."""
        from eyetohand.vision import GrabTimeout, detect_target

        try:
            self.source.set_robot_pose(*xyz, angle)
            img1, _ = self.source.grab()
            img2, _ = self.source.grab()
        except GrabTimeout as exc:
            raise CommandError(f"timeout: {exc}", ErrorCode.TIMEOUT) from None
        d1 = detect_target(img1, name="grab 1", **self.detect_options)
        self.last_grab = (img1, d1, utc_now())
        if not d1.ok:
            raise _classify(d1)
        assert d1.u is not None and d1.v is not None and d1.diameter_px is not None  # found: all set
        r = 2.0 * d1.diameter_px + 8
        h, w = img2.shape[:2]
        x = int(max(0, math.floor(d1.u - r)))
        y = int(max(0, math.floor(d1.v - r)))
        roi = (x, y, int(min(w, math.ceil(d1.u + r)) - x), int(min(h, math.ceil(d1.v + r)) - y))
        opts = {**self.detect_options, "diameter_px": d1.diameter_px, "refine": "edge"}
        try:
            d2 = detect_target(img2, name="grab 2", roi=roi, **opts)
        except InputError:
            d2 = None
        if d2 is None or not d2.ok:
            raise CommandError("moving: the target was not found again in the second grab", ErrorCode.MOVING)
        assert d2.u is not None and d2.v is not None
        shift = math.hypot(d2.u - d1.u, d2.v - d1.v)
        if shift > self.still_tol_px:
            raise CommandError(
                f"moving: the target moved {shift:.2f} px between two grabs "
                f"(tolerance {self.still_tol_px:g} px)",
                ErrorCode.MOVING,
            )
        self.image_size = (int(w), int(h))
        self.last_grab = (img1, d1, utc_now())
        return (float(d1.u), float(d1.v)), d1, img1, shift

    # -- POINT
    def _point(self, args: list[str]) -> list:
        if len(args) not in (3, 4):
            raise CommandError(f"CAL POINT: {len(args)} fields; expected <x>,<y>,<z>[,<angle>]")
        vals = line_numbers(args[:3], ("x", "y", "z"), "CAL POINT", "mm")
        vals += line_numbers(args[3:], ("angle",), "CAL POINT", "deg")
        s = self._open()
        xyz, angle = vals[:3], (vals[3] if len(vals) == 4 else 0.0)
        for k, p in enumerate(s.points):
            if p.get("dropped"):
                continue
            if (
                max(abs(a - b) for a, b in zip(p["xyz_mm"], xyz, strict=True)) <= REPEAT_MATCH_MM
                and abs(p["angle_deg"] - angle) <= REPEAT_MATCH_MM
            ):
                return [str(k + 1), _f(p["u"]), _f(p["v"])]
        idx = None
        if len(s.poses):
            d = np.abs(s.poses - np.array(xyz)).max(axis=1)
            j = int(np.argmin(d))
            idx = j if d[j] <= POSE_MATCH_MM else None
        try:
            uv, det, img, shift = self._acquire(xyz, angle)
        except CommandError as exc:
            if idx is not None and not s.done[idx]:
                self._record(
                    {
                        "op": "miss",
                        "pose_index": idx,
                        "xyz_mm": xyz,
                        "angle_deg": angle,
                        "reason": ascii_reason(str(exc)),
                    }
                )
            raise
        n = len(s.points) + 1
        assert self.image_size is not None  # _acquire grabbed: the camera's size is known
        digest = hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest()
        image_file = None
        if self.keep_images:
            import cv2

            from eyetohand.core import atomic_write_bytes

            rel = Path("images") / s.name / f"{n:04d}_{digest[:12]}.png"
            atomic_write_bytes(self.dir / rel, cv2.imencode(".png", img)[1].tobytes())
            image_file = str(rel)
        self._record(
            {
                "op": "point",
                "name": s.name,
                "n": n,
                "xyz_mm": xyz,
                "angle_deg": angle,
                "angle_given": len(vals) == 4,
                "pose_index": idx,
                "u": uv[0],
                "v": uv[1],
                "still_shift_px": shift,
                "image_sha256": digest,
                "image_file": image_file,
                "image_size": list(self.image_size),
                "detection": det.to_dict(),
            }
        )
        return [str(n), _f(uv[0]), _f(uv[1])]

    # -- END
    def pairs(self):
        """The current collection's points as :class:`~eyetohand.core.pairs.PointPairs`."""
        from eyetohand.core import PointPairs

        s = self._open()
        pts = self._active(s)
        if not pts:
            raise CommandError("fit failed: no points recorded", ErrorCode.FIT_FAILED)
        uv = np.array([[p["u"], p["v"]] for p in pts])
        xyz = np.array([p["xyz_mm"] for p in pts])
        angles = None
        if any(p["angle_given"] for p in pts):
            angles = np.array([p["angle_deg"] for p in pts])
        return PointPairs.from_arrays(
            uv, xyz, [str(p["n"]) for p in pts], source=f"collection {s.name}", angle_deg=angles
        )

    def _end(self, args) -> list:
        s = self._open()
        pairs = self.pairs()
        try:
            cal = self.calibrate_fn(pairs, s.model, self.image_size)
        except InputError as exc:
            raise CommandError(f"fit failed: {len(pairs)} points: {exc}", ErrorCode.FIT_FAILED) from None
        if cal.loo is None:
            raise CommandError(
                f"fit failed: {len(pairs)} points are too few to fit and cross-check model {cal.model_name}",
                ErrorCode.FIT_FAILED,
            )
        self.save_fn(s.name, cal)
        self._record(
            {
                "op": "end",
                "name": s.name,
                "model": cal.model_name,
                "n": len(pairs),
                "loo_rms_mm": cal.loo.rms_mm,
                "loo_max_mm": cal.loo.max_mm,
                "data_sha256": cal.data_sha256,
            }
        )
        return [cal.model_name, str(len(pairs)), _f(cal.loo.rms_mm), _f(cal.loo.max_mm)]

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
        uv, det, img, _ = self._acquire(xyz, 0.0)
        with np.errstate(all="ignore"):
            got = cal.image_to_robot(  # the target's centre, as a circle-centre calibration was fitted
                np.array([uv]), xyz[2], part_diameter_mm=cal.image_points.circle_diameter_mm
            )[0]
        if not np.isfinite(got).all():
            raise CommandError(
                "target not found: the centre maps to no finite robot point", ErrorCode.TARGET_NOT_FOUND
            )
        dx, dy = float(got[0] - xyz[0]), float(got[1] - xyz[1])
        err = math.hypot(dx, dy)
        rec = {
            "utc": utc_now(),
            "name": name,
            "version": version,
            "calibration_created_utc": cal.created_utc,
            "data_sha256": cal.data_sha256,
            "xyz_mm": xyz,
            "u": uv[0],
            "v": uv[1],
            "mapped_mm": [float(v) for v in got],
            "dx_mm": dx,
            "dy_mm": dy,
            "error_mm": err,
            "image_sha256": hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest(),
        }
        path = self.history_path(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab") as fh:
            fh.write((json.dumps(rec, allow_nan=False) + "\n").encode())
            fh.flush()
            os.fsync(fh.fileno())
        if self.on_check is not None:
            self.on_check(rec)
        return [_f(dx), _f(dy), _f(err)]


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
    "default_calibrate",
    "plan_poses",
]
