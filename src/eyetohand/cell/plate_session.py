"""A plate commissioning session on the CAL line protocol: the camera sees a calibration plate lying
on the work plane, the robot touches a few of its corners with a pointer, ``CAL END`` fits and stores a
version (docs/plate.md has the method, docs/collection.md "Plate and touches" the protocol).

``CAL PLATE <spec>[,<name>[,<placement>]]``
    Grab one image, detect the plate ``<spec>`` (``chessboard:9x6:15``, as ``calibrate-plate --plate``),
    keep the image (``images/<name>/plate_<sha>.png`` in the collection's folder) → ``OK <n>,A,B,C,D``:
    the plate's point count and the corners to touch (the labels docs/plate.md and the annotated image
    use; ``r{row}c{col}`` ids name any other). ``<name>``: the calibration (default: the server's
    ``--calibration``). ``<placement>`` (default 1): 1 opens the session; 2, 3, … add another image of
    the plate moved (on a block, tilted), whose own corners the following TOUCHes touch — placements at
    several heights measure the full camera (``camera`` model; docs/plate.md). A placement already
    taken resumes (no new grab).
``CAL TOUCH <label>,<x>,<y>,<z>`` (or ``<label> <x>,<y>,<z>``)
    The pointer's tip on corner ``<label>`` (A–D, or an id ``r2c5``) reads (x, y, z) mm → ``OK <n>,<u>,<v>``
    (touches so far, the corner's pixel). Refused: an unknown label, a reading not a finite number of mm,
    a corner touched already (the same reading again answers that touch's reply: a robot retrying).
``CAL END``
    :func:`eyetohand.calibration.calibrate_detected` with the touches (at least 3, not on one line) →
    ``OK <model>,<n>,<rms_mm>,<max_mm>``: the rigid fit's RMS and largest residual over the touches.
    The plate fit's refusals (collinear or coincident touches, a scale the plate does not have, a
    wrong corner by id, a touch off the plane, ...) come back as ``ERR fit failed: <its words>``, nothing
    stored; the touches stay for another TOUCH (e.g. a 4th corner) and END, or ``CAL ABORT``.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from eyetohand.cell.line import CommandError, ErrorCode, line_numbers
from eyetohand.cell.session import Session
from eyetohand.core import InputError

REPEAT_MATCH_MM = 1e-3
MAX_PLACEMENTS = 20
PLATE_USAGE = "CAL PLATE: expected <spec>[,<name>[,<placement>]], e.g. CAL PLATE chessboard:9x6:15,cell1"
TOUCH_USAGE = "CAL TOUCH: expected <label>,<x>,<y>,<z> (label A-D or a corner id such as r0c0)"


def _f(x: float) -> str:
    return f"{float(x):.4f}"


def parse_plate(args: list[str], default_name: str | None):
    """(spec, name, placement) of ``CAL PLATE``'s fields, refused in the protocol's words."""
    from eyetohand.vision import PlateSpec

    if not args or not args[0] or len(args) > 3:
        raise CommandError(PLATE_USAGE)
    placement = 1
    if len(args) == 3:
        k = args[2]
        if not (k.isdigit() and 1 <= int(k) <= MAX_PLACEMENTS):
            raise CommandError(
                f"CAL PLATE: placement {k[:20]!r}: expected a whole number 1..{MAX_PLACEMENTS}"
            )
        placement = int(k)
    try:
        spec = PlateSpec.parse(args[0])
    except InputError as exc:
        raise CommandError(f"CAL PLATE: {exc}") from None
    name = args[1] if len(args) >= 2 and args[1] else default_name
    if not name:
        raise CommandError("CAL PLATE: no calibration name (the server has no --calibration): " + PLATE_USAGE)
    return spec, name, placement


def grab_plate(source, spec, keep_dir: Path, name: str) -> dict:
    """One grab, the plate detected, the image kept: the fields of the ``plate`` journal record."""
    import cv2

    from eyetohand.core import atomic_write_bytes
    from eyetohand.vision import GrabTimeout, detect_plate

    try:
        img, _ = source.grab()
    except GrabTimeout as exc:
        raise CommandError(f"timeout: {exc}", ErrorCode.TIMEOUT) from None
    try:
        det = detect_plate(img, spec, "the camera's image")
    except InputError as exc:  # PlateNotFound: what was seen, in its words
        raise CommandError(str(exc), ErrorCode.TARGET_NOT_FOUND) from None
    digest = hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest()
    rel = Path("images") / name / f"plate_{digest[:12]}.png"
    atomic_write_bytes(keep_dir / rel, cv2.imencode(".png", img)[1].tobytes())
    return {
        "spec": spec.text,
        "image_sha256": digest,
        "image_file": str(rel),
        "image_size": list(det.image_size),
        # a corner not seen (a ChArUco board seen in part) is null: the journal holds no NaN
        "uv_px": [
            [float(u), float(v)] if ok else None for (u, v), ok in zip(det.uv_px, det.seen, strict=True)
        ],
    }


def _uv(im: dict) -> np.ndarray:
    """A placement's points (N, 2) px, NaN where not seen."""
    return np.array([(np.nan, np.nan) if p is None else p for p in im["uv_px"]], float).reshape(-1, 2)


def _labels(spec, im: dict) -> dict[str, int]:
    """The corners to touch (A–D) among those seen in placement ``im`` (as ``--annotate`` labels them)."""
    return spec.corner_labels(np.isfinite(_uv(im)).all(axis=1))


def plate_reply(s: Session) -> list[str]:
    from eyetohand.vision import PlateSpec

    spec = PlateSpec.parse(s.begin["spec"])
    return [str(spec.n_points), *_labels(spec, s.images[-1])]


def same_plate(s: Session, spec, name: str) -> bool:
    """A PLATE identical to the open session's (a robot program restarted): it resumes, no new grab."""
    return s.begin.get("spec") == spec.text and s.name == name


def _corner(spec, label: str, im: dict) -> tuple[int, str]:
    """The plate point (index) ``label`` names in placement ``im``, and its canonical label (A–D or its
    id); a corner not seen in the image is refused."""
    labels = _labels(spec, im)
    key = label.strip()
    if key.upper() in labels:
        return labels[key.upper()], key.upper()
    ids = spec.ids()
    if key.lower() in ids:
        i = ids.index(key.lower())
        if im["uv_px"][i] is None:
            raise CommandError(
                f"CAL TOUCH: corner {ids[i]} of {spec.text} is not seen in the plate's image "
                "(covered or out of view): touch a corner that is"
            )
        named = [k for k, v in labels.items() if v == i]
        return i, named[0] if named else key.lower()
    raise CommandError(
        f"CAL TOUCH: corner {key[:20]!r} unknown; expected A, B, C, D or a corner id r0c0..{ids[-1]} "
        f"of {spec.text}"
    )


def touch(s: Session, args: list[str]) -> tuple[dict | None, list[str]]:
    """``CAL TOUCH``: (the ``touch`` record to journal, or None for a repeat; the reply fields)."""
    from eyetohand.vision import PlateSpec

    if len(args) == 3 and len(args[0].split()) == 2:  # "<label> <x>,<y>,<z>"
        args = [*args[0].split(), *args[1:]]
    if len(args) != 4:
        raise CommandError(f"{TOUCH_USAGE}; got {len(args)} fields")
    spec = PlateSpec.parse(s.begin["spec"])
    image = len(s.images) - 1  # the latest placement's corners
    i, label = _corner(spec, args[0], s.images[image])
    xyz = line_numbers(args[1:], ("x", "y", "z"), f"CAL TOUCH {label}", "mm")
    uv = s.images[image]["uv_px"][i]
    for p in s.active():
        if p["corner"] != i or p.get("image", 0) != image:
            continue
        if max(abs(a - b) for a, b in zip(p["xyz_mm"], xyz, strict=True)) <= REPEAT_MATCH_MM:
            return None, [str(p["n"]), _f(p["u"]), _f(p["v"])]
        raise CommandError(
            f"CAL TOUCH {label}: corner {spec.ids()[i]} was touched already (touch {p['n']} at "
            + ",".join(_f(v) for v in p["xyz_mm"])
            + "): each corner once; CAL ABORT and CAL PLATE to start again"
        )
    n = len(s.points) + 1
    rec = {
        "op": "touch",
        "name": s.name,
        "n": n,
        "label": label,
        "image": image,
        "corner": i,
        "corner_id": spec.ids()[i],
        "u": float(uv[0]),
        "v": float(uv[1]),
        "xyz_mm": xyz,
    }
    return rec, [str(n), _f(uv[0]), _f(uv[1])]


def fit_plate(s: Session):
    """``CAL END`` of a plate session: (the calibration, the END record's fields with its ``reply``);
    the plate fit's refusals as ``fit failed: <words>``."""
    from eyetohand.calibration import PlateImage, Touch, calibrate_detected
    from eyetohand.vision import PlateSpec

    spec = PlateSpec.parse(s.begin["spec"])
    images = [
        PlateImage(
            f"{k + 1}:{Path(im['image_file']).name}",
            (int(im["image_size"][0]), int(im["image_size"][1])),
            _uv(im),
        )
        for k, im in enumerate(s.images)
    ]
    touches = [
        Touch((p["u"], p["v"]), tuple(p["xyz_mm"]), int(p.get("image", 0)), p["label"], p["n"])
        for p in s.active()
    ]
    try:
        cal = calibrate_detected(spec, images, touches)
    except InputError as exc:
        raise CommandError(f"fit failed: {exc}", ErrorCode.FIT_FAILED) from None
    assert cal.plate is not None  # calibrate_detected keeps its plate record
    res = np.concatenate([np.linalg.norm(pl.fit.residuals_mm, axis=1) for pl in cal.plate.placements])
    rms = float(np.sqrt(np.mean(res**2)))
    worst = float(np.max(res))
    result = {"model": cal.model_name, "n": len(touches), "touch_rms_mm": rms, "touch_max_mm": worst}
    return cal, {**result, "reply": [cal.model_name, str(len(touches)), _f(rms), _f(worst)]}


def status(s: Session) -> dict:
    """A plate session as JSON-ready data (the workbench's collection view): the plate, its corners to
    touch with their pixels, the touches, the fit result of the last END."""
    from eyetohand.vision import PlateSpec

    spec = PlateSpec.parse(s.begin["spec"])
    latest = s.images[-1]
    uv = latest["uv_px"]
    return {
        "name": s.name,
        "kind": "plate",
        "state": s.state,
        "plate": spec.text,
        "placements": len(s.images),
        "image_file": latest["image_file"],
        "image_size": latest["image_size"],
        "corners": [
            {"label": k, "id": spec.ids()[i], "u": uv[i][0], "v": uv[i][1]}
            for k, i in _labels(spec, latest).items()
        ],
        "poses": [],
        "points": [
            {k: p.get(k) for k in ("n", "label", "corner_id", "u", "v", "xyz_mm", "utc")}
            | {"placement": int(p.get("image", 0)) + 1}
            | {"dropped": bool(p.get("dropped"))}
            for p in s.points
        ],
        "result": s.result,
    }


__all__ = [
    "PLATE_USAGE",
    "TOUCH_USAGE",
    "fit_plate",
    "grab_plate",
    "parse_plate",
    "plate_reply",
    "same_plate",
    "status",
    "touch",
]
