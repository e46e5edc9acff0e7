"""``eyetohand grab URI``: one frame from any camera source, its size and timestamp, optionally saved
and with the target detected in it (the way to check a camera before a collection)."""

from __future__ import annotations

import json
import sys
from datetime import datetime
from pathlib import Path

import eyetohand.sim  # noqa: F401  (registers the sim: source)
from eyetohand.core import InputError, atomic_write_bytes, check_output_path
from eyetohand.vision import GrabTimeout, annotate, detect_target, open_source

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def _check_output(path: str) -> None:
    """Before the camera is opened: an image file name that can be written."""
    if Path(path).suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(f"-o {path}: expected an image file name ({', '.join(IMAGE_SUFFIXES)})")
    check_output_path(path)


def _encode(image, path: str) -> bytes:
    import cv2

    suffix = Path(path).suffix.lower()
    try:
        ok, data = cv2.imencode(suffix, image)
    except cv2.error:
        ok = False
    if not ok:
        raise InputError(f"-o {path}: OpenCV cannot write this frame ({image.dtype}) as {suffix}")
    return data.tobytes()


def _grab_json(image, timestamp_s: float, output, detection) -> dict:
    out = {
        "width": int(image.shape[1]),
        "height": int(image.shape[0]),
        "channels": 1 if image.ndim == 2 else int(image.shape[2]),
        "dtype": str(image.dtype),
        "timestamp_s": timestamp_s,
        "output": output,
    }
    if detection is not None:
        out["target"] = (
            {
                "u": detection.u,
                "v": detection.v,
                "diameter_px": detection.diameter_px,
                "score": detection.score,
            }
            if detection.ok
            else None
        )
        out["reason"] = None if detection.ok else detection.reason
    return out


def cmd_grab(args) -> int:
    if args.output:
        _check_output(args.output)
    if args.timeout is not None and not args.timeout > 0:
        raise InputError(f"--timeout: expected positive seconds, got {args.timeout:g}")
    if args.pose is not None and len(args.pose) not in (3, 4):
        raise InputError(f"--pose: expected X Y Z [ANGLE] (mm, deg), got {len(args.pose)} numbers")
    overrides = {} if args.timeout is None else {"timeout_s": args.timeout}
    with open_source(args.uri, **overrides) as source:
        try:
            image, timestamp_s = source.grab(pose=args.pose)
        except GrabTimeout as exc:
            raise InputError(str(exc)) from None
    kind = "grey" if image.ndim == 2 else f"{image.shape[2]} channels"
    when = datetime.fromtimestamp(timestamp_s).astimezone().isoformat(timespec="milliseconds")
    detection = detect_target(image) if args.detect else None
    if args.output:
        atomic_write_bytes(
            args.output, _encode(annotate(image, detection) if detection else image, args.output)
        )
    if args.json:
        print(json.dumps(_grab_json(image, timestamp_s, args.output, detection), allow_nan=False))
        return 2 if detection is not None and not detection.ok else 0
    print(f"frame {image.shape[1]}x{image.shape[0]} px {kind} {image.dtype}")
    print(f"timestamp {timestamp_s:.6f} s ({when})")
    if args.output:
        print(f"wrote {args.output}" + (" (target drawn)" if detection else ""))
    if detection is None:
        return 0
    if detection.ok:
        print(
            f"target u {detection.u:.3f} v {detection.v:.3f} px  diameter {detection.diameter_px:.2f} px  "
            f"score {detection.score:.3f}"
        )
        return 0
    print(f"target not found — {detection.reason}")
    print("error: no target in the frame", file=sys.stderr)
    return 2


def register(sub) -> None:
    p = sub.add_parser("grab", help="one frame from a camera source: its size and timestamp, saved, detected")
    p.add_argument(
        "uri", metavar="URI", help="camera source: folder:DIR, sim:CELL.toml, aravis:ID, opencv:0, ..."
    )
    p.add_argument(
        "-o", "--output", metavar="FRAME.png", help="write the frame (with --detect: the target drawn)"
    )
    p.add_argument("--detect", action="store_true", help="find the target: its centre, or why not")
    p.add_argument(
        "--pose",
        type=float,
        nargs="+",
        metavar="MM",
        help="X Y Z [ANGLE]: where the robot is (sim: draws the target there; a real camera sees it)",
    )
    p.add_argument("--timeout", type=float, default=None, metavar="S", help="seconds the grab may wait")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_grab)
