"""Calibration from images: robot poses + photographs of the target → point pairs → calibration.

``POSES.csv`` has columns ``image,x,y,z`` (``z`` optional, and an optional ``angle`` in degrees: the
tool's rotation, used to estimate a tool-centre offset): the robot's position (mm) when each image was
taken, image paths relative to an images folder (default: the folder of POSES.csv). Each image is
searched for the target; images where detection fails are listed with the reason and left out — a
pair is never formed from a doubtful centre.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from eyetohand.core import InputError, PointPairs, Where, csv_rows, read_pairs_text, record_number

if TYPE_CHECKING:  # detect (and OpenCV) load only when an image is read
    from eyetohand.vision.detect import Detection


@dataclass(frozen=True)
class Pose:
    image: str  # as written in the file
    path: Path  # resolved
    xyz_mm: tuple[float, float, float]
    where: str  # "poses.csv line 3"
    angle_deg: float | None = None


@dataclass(frozen=True)
class ImageResult:
    image: str
    ok: bool
    u: float | None = None
    v: float | None = None
    diameter_px: float | None = None
    score: float | None = None
    reason: str = ""

    def to_dict(self) -> dict:
        return {
            "image": self.image,
            "ok": self.ok,
            "u": self.u,
            "v": self.v,
            "diameter_px": self.diameter_px,
            "score": self.score,
            "reason": self.reason,
        }


def load_poses(path: str | os.PathLike, images_dir: str | os.PathLike | None = None) -> list[Pose]:
    """Read POSES.csv (``image,x,y[,z][,angle]``); image paths are resolved against ``images_dir``."""
    path = Path(path)
    name = str(path)
    rows, first = csv_rows(read_pairs_text(path), name)
    header = [h.strip().lower() for h in rows[first]]
    missing = [c for c in ("image", "x", "y") if c not in header]
    if missing:
        raise InputError(
            f"{name} line {first + 1}: missing column(s) {', '.join(missing)}; expected image,x,y[,z]"
        )
    col = {c: header.index(c) for c in ("image", "x", "y", "z", "angle") if c in header}
    base = Path(images_dir) if images_dir is not None else path.parent
    poses: list[Pose] = []
    seen: dict[str, str] = {}
    for k, row in enumerate(rows[first + 1 :], start=first + 2):
        if not row or all(not c.strip() for c in row):
            continue
        loc = Where(name, line=k)
        where = str(loc)
        if len(row) != len(header):
            raise loc.error(f"{len(row)} fields, the header has {len(header)}")
        image = row[col["image"]].strip()
        if not image:
            raise loc.error("empty, expected an image file name", "image")
        if image in seen:
            raise loc.error(f"{image!r} is listed twice (first at {seen[image]})", "image")
        seen[image] = where
        x, y, z = (record_number(row[col[c]], loc, c) if c in col else 0.0 for c in ("x", "y", "z"))
        angle = record_number(row[col["angle"]], loc, "angle") if "angle" in col else None
        poses.append(Pose(image, base / image, (x, y, z), where, angle))
    if not poses:
        raise InputError(f"{name}: header only, no poses")
    return poses


# progress(done, total, image): called before each image (done = images finished so far) and once
# more at the end with done == total and image ""
Progress = Callable[[int, int, str], None]


def detect_poses(
    poses: list[Pose],
    *,
    progress: Progress | None = None,
    annotate_dir: str | os.PathLike | None = None,
    **detect_options,
) -> list[ImageResult]:
    """Detect the target in each pose's image; failures carry their reason. With ``annotate_dir``,
    each image where it was found is written there as ``<stem>.annotated.png`` (see :func:`detect_images`)."""
    from eyetohand.vision.detect import detect_target

    results = []
    used: set[str] = set()
    for i, pose in enumerate(poses):
        if progress is not None:
            progress(i, len(poses), pose.image)
        res, det = _detect_one(pose.path, pose.image, detect_target, detect_options)
        results.append(res)
        if annotate_dir and det is not None and res.ok:
            _write_annotated(pose.path, det, annotate_dir, used)
    if progress is not None:
        progress(len(poses), len(poses), "")
    return results


def _detect_one(path, name, detect_target, detect_options) -> tuple[ImageResult, Detection | None]:
    """(result, the detection or None when the image could not be read)."""
    try:
        det = detect_target(path, name=name, **detect_options)
    except InputError as exc:
        return ImageResult(name, False, reason=str(exc)), None
    if det.ok:
        return ImageResult(
            name, True, float(det.u), float(det.v), float(det.diameter_px), float(det.score)
        ), det
    return ImageResult(name, False, reason=det.reason or "no target found"), det


def _write_annotated(path, det: Detection, annotate_dir: str | os.PathLike, used: set[str]) -> None:
    """``<stem>.annotated.png`` in ``annotate_dir`` (a new name when two images share a stem)."""
    import cv2

    from eyetohand.core import atomic_write_bytes
    from eyetohand.vision.detect import annotate

    img = annotate(path, det)
    stem = Path(path).stem
    name, k = f"{stem}.annotated.png", 1
    while name in used:  # same file name from different folders
        k += 1
        name = f"{stem}.{k}.annotated.png"
    used.add(name)
    ok, buf = cv2.imencode(".png", img)
    if ok:
        atomic_write_bytes(Path(annotate_dir) / name, buf.tobytes())


def detect_images(
    paths: Sequence[str | os.PathLike], annotate_dir: str | os.PathLike | None = None, **detect_options
) -> list[ImageResult]:
    """Detect the target in each image (results named by the path as given); with ``annotate_dir``,
    each image where it was found is written there as ``<stem>.annotated.png`` with the fit drawn."""
    from eyetohand.vision.detect import detect_target

    out = []
    used: set[str] = set()
    for p in paths:
        res, det = _detect_one(p, str(p), detect_target, detect_options)
        out.append(res)
        if annotate_dir and det is not None and res.ok:
            _write_annotated(p, det, annotate_dir, used)
    return out


def pairs_from_detections(poses: list[Pose], results: list[ImageResult], source: str) -> PointPairs:
    """Pairs of the images whose target was found (ids are the image names)."""
    good = [(p, r) for p, r in zip(poses, results, strict=True) if r.ok]
    if not good:
        raise InputError(f"{source}: the target was found in none of the {len(poses)} images")
    uv = np.array([[r.u, r.v] for _, r in good])
    xyz = np.array([p.xyz_mm for p, _ in good])
    angles = [p.angle_deg for p, _ in good]
    angle_deg = None if any(a is None for a in angles) else np.array(angles, float)
    return PointPairs.from_arrays(uv, xyz, [p.image for p, _ in good], source=source, angle_deg=angle_deg)
