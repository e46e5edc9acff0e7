"""A collection's commands on the CAL line protocol (``CAL BEGIN`` / ``NEXT`` / ``POINT``, and what
``CAL END`` fits): the parsing, the plan, the records they journal and the fit — the protocol itself, its
state and its order are :class:`eyetohand.cell.collect.Collector`'s (module docstring there)."""

from __future__ import annotations

import re

import numpy as np

from eyetohand.cell.grab import TargetGrab
from eyetohand.cell.line import CommandError, ErrorCode, line_numbers
from eyetohand.cell.session import Session
from eyetohand.core import InputError

POSE_MATCH_MM = 0.01
REPEAT_MATCH_MM = 1e-3
REPEAT_MATCH_DEG = 1e-3  # a resent line carries the same reading: its angle to the same 0.001 deg
NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


def _f(x: float) -> str:
    return f"{float(x):.4f}"


def plan_poses(plan: str, x0: float, y0: float, x1: float, y1: float, z: float) -> np.ndarray:
    """The poses (n, 3) mm of ``plan`` over the rectangle x0..x1, y0..y1 at height z, in the order
    the collection hands them out (a grid snakes: every other row reversed)."""
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


def parse_begin(args: list[str]) -> dict:
    """``CAL BEGIN``'s fields → the ``begin`` record's (name, plan, rect, model, poses); the model is
    checked by :func:`check_model`, after the server's rule on the name."""
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
    return {"name": name, "plan": plan, "rect": rect, "model": model, "poses": poses}


def check_model(model: str) -> None:
    """``auto`` or a model's name; another refused listing the choices."""
    from eyetohand.calibration import resolve_model

    try:
        resolve_model(model)
    except InputError as exc:
        raise CommandError(f"CAL BEGIN: {exc}") from None


def same_begin(s: Session, fields: dict) -> bool:
    """A BEGIN identical to the open collection's (a robot program restarted): it resumes."""
    b = s.begin
    return (
        b["op"] == "begin"
        and s.name == fields["name"]
        and b.get("plan") == fields["plan"]
        and b.get("rect") == fields["rect"]
        and s.model == fields["model"]
    )


def next_pose(s: Session) -> list[str] | None:
    """``CAL NEXT``: the first planned pose neither recorded nor failed (None: none left)."""
    if not len(s.poses):
        raise CommandError(  # the code the ur replies have always sent for it
            "no collection plan: CAL BEGIN was given no plan; send your own POINTs",
            ErrorCode.NO_COLLECTION,
        )
    left = np.flatnonzero(~(s.done | s.failed))
    if not len(left):
        return None
    return [_f(v) for v in s.poses[left[0]]]


def parse_point(args: list[str]) -> tuple[list[float], float, bool]:
    """``CAL POINT``'s fields → (x, y, z mm, angle deg, angle given)."""
    if len(args) not in (3, 4):
        raise CommandError(f"CAL POINT: {len(args)} fields; expected <x>,<y>,<z>[,<angle>]")
    xyz = line_numbers(args[:3], ("x", "y", "z"), "CAL POINT", "mm")
    angle = line_numbers(args[3:], ("angle",), "CAL POINT", "deg")
    return xyz, (angle[0] if angle else 0.0), bool(angle)


def repeat_reply(s: Session, xyz: list[float], angle: float) -> list[str] | None:
    """The reply of a point already recorded at this pose (1 µm) and angle (0.001 deg): a robot retrying."""
    for k, p in enumerate(s.points):
        if p.get("dropped"):
            continue
        if (
            max(abs(a - b) for a, b in zip(p["xyz_mm"], xyz, strict=True)) <= REPEAT_MATCH_MM
            and abs(p["angle_deg"] - angle) <= REPEAT_MATCH_DEG
        ):
            return [str(k + 1), _f(p["u"]), _f(p["v"])]
    return None


def pose_index(s: Session, xyz: list[float]) -> int | None:
    """The planned pose within :data:`POSE_MATCH_MM` of ``xyz``, or None."""
    if not len(s.poses):
        return None
    d = np.abs(s.poses - np.array(xyz)).max(axis=1)
    j = int(np.argmin(d))
    return j if d[j] <= POSE_MATCH_MM else None


def point_record(
    s: Session,
    xyz: list[float],
    angle: float,
    angle_given: bool,
    idx: int | None,
    grab: TargetGrab,
    digest: str,
    image_file: str | None,
) -> dict:
    """The ``point`` journal record of a grab at the pose."""
    return {
        "op": "point",
        "name": s.name,
        "n": len(s.points) + 1,
        "xyz_mm": xyz,
        "angle_deg": angle,
        "angle_given": angle_given,
        "pose_index": idx,
        "u": grab.uv_px[0],
        "v": grab.uv_px[1],
        "still_shift_px": grab.shift_px,
        "image_sha256": digest,
        "image_file": image_file,
        "image_size": list(grab.image_size),
        "detection": grab.detection.to_dict(),  # type: ignore[attr-defined]
    }


def pairs(s: Session):
    """The collection's points (not dropped) as :class:`~eyetohand.core.pairs.PointPairs`."""
    from eyetohand.core import PointPairs

    pts = s.active()
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


def fit_collection(s: Session, calibrate_fn, image_size):
    """``CAL END`` of a collection: (the calibration, the END record's fields with its ``reply``)."""
    p = pairs(s)
    try:
        cal = calibrate_fn(p, s.model, image_size)
    except InputError as exc:
        raise CommandError(f"fit failed: {len(p)} points: {exc}", ErrorCode.FIT_FAILED) from None
    if cal.loo is None:
        raise CommandError(
            f"fit failed: {len(p)} points are too few to fit and cross-check model {cal.model_name}",
            ErrorCode.FIT_FAILED,
        )
    result = {
        "model": cal.model_name,
        "n": len(p),
        "loo_rms_mm": cal.loo.rms_mm,
        "loo_max_mm": cal.loo.max_mm,
    }
    reply = [cal.model_name, str(len(p)), _f(cal.loo.rms_mm), _f(cal.loo.max_mm)]
    return cal, {**result, "reply": reply}


__all__ = [
    "NAME_RE",
    "POSE_MATCH_MM",
    "REPEAT_MATCH_MM",
    "check_model",
    "fit_collection",
    "next_pose",
    "pairs",
    "parse_begin",
    "parse_point",
    "plan_poses",
    "point_record",
    "pose_index",
    "repeat_reply",
    "same_begin",
]
