"""``eyetohand detect`` and ``eyetohand calibrate-images``: the target found in images, then calibrated."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from eyetohand.cli.common import add_fit_options, fit_request, run_calibration
from eyetohand.core import InputError, atomic_write_text, check_output_path
from eyetohand.vision import detect_images, detect_poses, load_poses, pairs_from_detections


def _detect_options(args) -> dict:
    if args.diameter is not None and not args.diameter > 0:
        raise InputError(f"--diameter: expected a positive number of px, got {args.diameter:g}")
    opts = {"polarity": args.polarity}
    if args.diameter is not None:
        opts["diameter_px"] = args.diameter
    if getattr(args, "roi", None) is not None:
        x, y, w, h = args.roi
        if min(x, y) < 0 or min(w, h) <= 0:
            raise InputError(f"--roi: expected X Y >= 0 and W H > 0 (px), got {x} {y} {w} {h}")
        opts["roi"] = (x, y, w, h)
    return opts


def _progress_bar(done: int, total: int, image: str) -> None:
    """The detection progress bar on stderr (only used when stderr is a terminal)."""
    if done < total:
        filled = int(30 * done / total)
        sys.stderr.write(
            f"\rdetecting [{'#' * filled}{'.' * (30 - filled)}] {done}/{total} {image[-30:]:<30}"
        )
        sys.stderr.flush()
    else:
        sys.stderr.write(f"\rdetecting [{'#' * 30}] {total}/{total} {'':<30}\n")


def _progress_lines(done: int, total: int, image: str) -> None:
    """Detection progress when stderr is not a terminal (a log, a pipe): one line per image."""
    if done < total:
        sys.stderr.write(f"detecting {done + 1}/{total}: {image}\n")
    else:
        sys.stderr.write(f"detected {total} images\n")
    sys.stderr.flush()


def _check_annotate_dir(path) -> None:
    if path and Path(path).exists() and not Path(path).is_dir():
        raise InputError(f"--annotate: {path} exists and is not a folder")


def cmd_detect(args) -> int:
    _check_annotate_dir(args.annotate)
    opts = _detect_options(args)
    results = detect_images(args.images, args.annotate, **opts)
    failed = [r for r in results if not r.ok]
    if len(results) == 1 and failed:
        r = failed[0]
        raise InputError(r.reason if r.reason.startswith(r.image) else f"{r.image}: {r.reason}")
    if args.json:
        print(json.dumps({"results": [r.to_dict() for r in results], "failed": len(failed)}))
    else:
        for r in results:
            if r.ok:
                print(
                    f"{r.image}: u {r.u:.3f} v {r.v:.3f} px  diameter {r.diameter_px:.2f} px  "
                    f"score {r.score:.3f}"
                )
            else:
                print(f"{r.image}: FAILED — {r.reason}")
    if failed:
        print(f"error: the target was not found in {len(failed)} of {len(results)} images", file=sys.stderr)
        return 2
    return 0


def cmd_calibrate_images(args) -> int:
    # before detecting: the work must not be lost to an output that cannot be written
    _check_annotate_dir(args.annotate)
    for out in (args.output, args.pairs_out):
        if out:
            check_output_path(out)
    request = fit_request(args)  # and the fit options, before detecting
    poses = load_poses(args.poses, args.images)
    progress = _progress_bar if sys.stderr.isatty() else _progress_lines
    opts = _detect_options(args)
    results = detect_poses(poses, progress=progress, annotate_dir=args.annotate, **opts)
    pairs = pairs_from_detections(poses, results, str(args.poses))
    check = None
    check_results = []
    if args.check:
        check_poses = load_poses(args.check, args.check_images)
        check_results = detect_poses(check_poses, progress=progress, annotate_dir=args.annotate, **opts)
        check = pairs_from_detections(check_poses, check_results, str(args.check))
    if args.pairs_out:  # the detected pairs, to calibrate again without detecting (eyetohand calibrate)
        atomic_write_text(args.pairs_out, pairs.to_csv_text())
        print(f"wrote {args.pairs_out}: {len(pairs)} detected pairs", file=sys.stderr)
    for r in results + check_results:
        if not r.ok:
            print(f"note: left out {r.image}: {r.reason}", file=sys.stderr)
    extra = {"detections": [r.to_dict() for r in results], "left_out": [r.image for r in results if not r.ok]}
    if args.check:
        extra["check_detections"] = [r.to_dict() for r in check_results]
        extra["check_left_out"] = [r.image for r in check_results if not r.ok]
    return run_calibration(args, pairs, check, extra=extra, request=request)


def register(sub) -> None:
    p = sub.add_parser("detect", help="find the solid-circle target in images (exit 2 if any fails)")
    p.add_argument("images", nargs="+", metavar="IMAGE")
    p.add_argument("--polarity", default="auto", choices=("auto", "dark", "bright"))
    p.add_argument("--diameter", type=float, default=None, help="expected diameter in px")
    p.add_argument(
        "--roi",
        type=int,
        nargs=4,
        metavar=("X", "Y", "W", "H"),
        help="search only this rectangle (px, top-left corner and size): picks one of several equal targets",
    )
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
    p.add_argument(
        "--pairs-out",
        metavar="PAIRS.csv",
        help="also write the detected pairs (id = image) as CSV, for eyetohand calibrate",
    )
    p.add_argument("--annotate", metavar="DIR", help="write each image with the fitted ellipse drawn")
    add_fit_options(p)
    p.set_defaults(func=cmd_calibrate_images)
