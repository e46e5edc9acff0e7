"""Calibration from images: robot poses + photographs of the target → point pairs → calibration.

``POSES.csv`` has columns ``image,x,y,z`` (``z`` optional, and an optional ``angle`` in degrees: the
tool's rotation, used to estimate a tool-centre offset): the robot's position (mm) when each image was
taken, image paths relative to an images folder (default: the folder of POSES.csv). Each image is
searched for the target; images where detection fails are listed with the reason and left out — a
pair is never formed from a doubtful centre.
"""

from __future__ import annotations

import csv
import io
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .pairs import PointPairs, _csv_rows, _number, _read_text


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
        return {"image": self.image, "ok": self.ok, "u": self.u, "v": self.v,
                "diameter_px": self.diameter_px, "score": self.score, "reason": self.reason}


def load_poses(path: str | os.PathLike, images_dir: str | os.PathLike | None = None) -> list[Pose]:
    """Read POSES.csv (``image,x,y[,z][,angle]``); image paths are resolved against ``images_dir``."""
    path = Path(path)
    name = str(path)
    rows, first = _csv_rows(_read_text(path), name)
    header = [h.strip().lower() for h in rows[first]]
    missing = [c for c in ("image", "x", "y") if c not in header]
    if missing:
        raise InputError(f"{name} line {first + 1}: missing column(s) {', '.join(missing)}; "
                         "expected image,x,y[,z]")
    col = {c: header.index(c) for c in ("image", "x", "y", "z", "angle") if c in header}
    base = Path(images_dir) if images_dir is not None else path.parent
    poses, seen = [], {}
    for k, row in enumerate(rows[first + 1:], start=first + 2):
        if not row or all(not c.strip() for c in row):
            continue
        where = f"{name} line {k}"
        if len(row) != len(header):
            raise InputError(f"{where}: {len(row)} fields, the header has {len(header)}")
        image = row[col["image"]].strip()
        if not image:
            raise InputError(f"{where}, field 'image': empty, expected an image file name")
        if image in seen:
            raise InputError(f"{where}, field 'image': {image!r} is listed twice (first at {seen[image]})")
        seen[image] = where
        xyz = tuple(_number(row[col[c]], where, c) if c in col else 0.0 for c in ("x", "y", "z"))
        angle = _number(row[col["angle"]], where, "angle") if "angle" in col else None
        poses.append(Pose(image, base / image, xyz, where, angle))
    if not poses:
        raise InputError(f"{name}: header only, no poses")
    return poses


def detect_poses(poses: list[Pose], *, progress: bool = False, **detect_options) -> list[ImageResult]:
    """Detect the target in each pose's image; failures carry their reason."""
    from .detect import detect_target

    results = []
    for i, pose in enumerate(poses):
        if progress:
            done = int(30 * i / len(poses))
            sys.stderr.write(f"\rdetecting [{'#' * done}{'.' * (30 - done)}] {i}/{len(poses)} "
                             f"{pose.image[-30:]:<30}")
            sys.stderr.flush()
        try:
            det = detect_target(pose.path, name=pose.image, **detect_options)
        except InputError as exc:
            results.append(ImageResult(pose.image, False, reason=str(exc)))
            continue
        if det.ok:
            results.append(ImageResult(pose.image, True, float(det.u), float(det.v),
                                       float(det.diameter_px), float(det.score)))
        else:
            results.append(ImageResult(pose.image, False, reason=det.reason or "no target found"))
    if progress:
        sys.stderr.write(f"\rdetecting [{'#' * 30}] {len(poses)}/{len(poses)} {'':<30}\n")
    return results


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


def write_pairs_csv(pairs: PointPairs) -> str:
    """The detected pairs as the CSV ``calibrate`` reads (id = image name)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", "u", "v", "x", "y", "z"])
    for rec in pairs.to_records():
        w.writerow([rec["id"], *(repr(rec[c]) for c in ("u", "v", "x", "y", "z"))])
    return buf.getvalue()


# ------------------------------------------------------------------ CLI


def _detect_many(paths, annotate_dir, detect_options):
    from .detect import annotate, detect_target

    out = []
    used: set[str] = set()
    for p in paths:
        try:
            det = detect_target(p, **detect_options)
        except InputError as exc:
            out.append(ImageResult(str(p), False, reason=str(exc)))
            continue
        res = (ImageResult(str(p), True, float(det.u), float(det.v), float(det.diameter_px),
                           float(det.score)) if det.ok else
               ImageResult(str(p), False, reason=det.reason or "no target found"))
        out.append(res)
        if annotate_dir and det.ok:
            import cv2

            from .io import atomic_write_bytes

            img = annotate(p, det)
            stem = Path(p).stem
            name, k = f"{stem}.annotated.png", 1
            while name in used:  # same file name from different folders
                k += 1
                name = f"{stem}.{k}.annotated.png"
            used.add(name)
            ok, buf = cv2.imencode(".png", img)
            if ok:
                atomic_write_bytes(Path(annotate_dir) / name, buf.tobytes())
    return out


def _detect_options(args) -> dict:
    if args.diameter is not None and not args.diameter > 0:
        raise InputError(f"--diameter: expected a positive number of px, got {args.diameter:g}")
    opts = {"polarity": args.polarity}
    if args.diameter is not None:
        opts["diameter_px"] = args.diameter
    return opts


def cmd_detect(args) -> int:
    import json

    if args.annotate and Path(args.annotate).exists() and not Path(args.annotate).is_dir():
        raise InputError(f"--annotate: {args.annotate} exists and is not a folder")
    opts = _detect_options(args)
    results = _detect_many(args.images, args.annotate, opts)
    failed = [r for r in results if not r.ok]
    if len(results) == 1 and failed:
        r = failed[0]
        raise InputError(r.reason if r.reason.startswith(r.image) else f"{r.image}: {r.reason}")
    if args.json:
        print(json.dumps({"results": [r.to_dict() for r in results], "failed": len(failed)}))
    else:
        for r in results:
            if r.ok:
                print(f"{r.image}: u {r.u:.3f} v {r.v:.3f} px  diameter {r.diameter_px:.2f} px  "
                      f"score {r.score:.3f}")
            else:
                print(f"{r.image}: FAILED — {r.reason}")
    if failed:
        print(f"error: the target was not found in {len(failed)} of {len(results)} images",
              file=sys.stderr)
        return 2
    return 0


def cmd_calibrate_images(args) -> int:
    from .cli import run_calibration

    poses = load_poses(args.poses, args.images)
    progress = sys.stderr.isatty()
    opts = _detect_options(args)
    results = detect_poses(poses, progress=progress, **opts)
    pairs = pairs_from_detections(poses, results, str(args.poses))
    check = None
    check_results = []
    if args.check:
        check_poses = load_poses(args.check, args.check_images)
        check_results = detect_poses(check_poses, progress=progress, **opts)
        check = pairs_from_detections(check_poses, check_results, str(args.check))
    for r in results + check_results:
        if not r.ok:
            print(f"note: left out {r.image}: {r.reason}", file=sys.stderr)
    extra = {"detections": [r.to_dict() for r in results],
             "left_out": [r.image for r in results if not r.ok]}
    if args.check:
        extra["check_detections"] = [r.to_dict() for r in check_results]
        extra["check_left_out"] = [r.image for r in check_results if not r.ok]
    return run_calibration(args, pairs, check, extra=extra)


def register(sub) -> None:
    from .cli import add_fit_options

    p = sub.add_parser("detect", help="find the solid-circle target in images (exit 2 if any fails)")
    p.add_argument("images", nargs="+", metavar="IMAGE")
    p.add_argument("--polarity", default="auto", choices=("auto", "dark", "bright"))
    p.add_argument("--diameter", type=float, default=None, help="expected diameter in px")
    p.add_argument("--annotate", metavar="DIR", help="write pictures with the fitted ellipse drawn")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("calibrate-images", help="detect the target in images of robot poses, then calibrate")
    p.add_argument("poses", help="CSV with image,x,y[,z][,angle]")
    p.add_argument("--images", help="folder of the images (default: the folder of POSES.csv)")
    p.add_argument("--check", help="check poses CSV (image,x,y[,z]), not used for fitting")
    p.add_argument("--check-images", help="folder of the check images (default: the folder of CHECK)")
    p.add_argument("--polarity", default="auto", choices=("auto", "dark", "bright"))
    p.add_argument("--diameter", type=float, default=None, help="expected target diameter in px")
    add_fit_options(p)
    p.set_defaults(func=cmd_calibrate_images)
