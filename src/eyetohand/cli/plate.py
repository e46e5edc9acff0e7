"""``calibrate-plate``: images of a calibration plate and a few robot touches in, a calibration out;
and ``simulate --plate``: a plate image, its touches and check points from the virtual cell."""

from __future__ import annotations

import json
import sys

from eyetohand.cli.common import finish_calibration
from eyetohand.core import ROBOT_UNITS, InputError, atomic_write_bytes, load_pairs


def _write_png(path: str, image) -> None:
    import cv2

    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise InputError(f"{path}: could not encode the annotated image")
    atomic_write_bytes(path, png.tobytes())


def _annotate(args, spec) -> None:
    """--annotate FILE: the first image with the plate's points labelled (A-D: the corners to touch),
    or, when the plate is not found, the points seen — then the refusal is raised again."""
    from eyetohand.vision import PlateNotFound, annotate_plate, detect_plate

    try:
        det = detect_plate(args.images[0], spec)
    except PlateNotFound as exc:
        _write_png(args.annotate, annotate_plate(args.images[0], spec, exc.seen_px, found=False))
        print(f"wrote {args.annotate} (the points seen)", file=sys.stderr)
        raise
    _write_png(args.annotate, annotate_plate(args.images[0], spec, det.uv_px))
    print(f"wrote {args.annotate}", file=sys.stderr)


def cmd_calibrate_plate(args) -> int:
    from eyetohand.calibration import calibrate_plate
    from eyetohand.vision import PlateSpec

    spec = PlateSpec.parse(args.plate)  # the options before the files
    if args.output:
        from eyetohand.core import check_output_path

        check_output_path(args.output)
    if args.annotate:
        _annotate(args, spec)
        if not (args.touches or args.touches_from):
            return 0
    if args.touches and args.touches_from:
        raise InputError("calibrate-plate: give --touches T.csv or --touches-from OLD.json, not both")
    touches = args.touches
    if args.touches_from:
        from eyetohand.calibration import Calibration

        touches = Calibration.load(args.touches_from)
    if not touches:
        raise InputError("calibrate-plate: give --touches T.csv (or --annotate FILE.png to see the corners)")
    check = load_pairs(args.check).scaled_to_mm(args.robot_units) if args.check else None
    cal = calibrate_plate(
        args.images,
        spec,
        touches,
        check=check,
        model=args.model,
        tolerance_mm=args.touch_tolerance_mm,
        touch_noise_mm=args.touch_noise_mm,
        loo=args.loo,
        robot_units=args.robot_units,
    )
    plate = {
        "spec": spec.text,
        "placements": [
            {"image": p.image + 1, "rms_mm": p.fit.rms_mm, "noise_mm": p.noise_mm, "scale": p.fit.scale}
            for p in (cal.plate.placements if cal.plate else ())
        ],
    }
    return finish_calibration(args, cal, {"plate": plate})


def cmd_simulate_plate(args) -> int:
    """``simulate --plate SPEC --touches N --out DIR``."""
    from eyetohand.cell import parse_numbers
    from eyetohand.sim import load_cell, simulate_plate, write_plate_simulation

    if not args.out:
        raise InputError("simulate: give --out DIR")
    shift = (0.0, 0.0)
    if args.plate_shift_mm is not None:
        dx, dy = parse_numbers(
            args.plate_shift_mm, "--plate-shift-mm", example="100,0", count=2, distinct=False
        )
        shift = (dx, dy)
    cover = None
    if args.plate_cover is not None:
        u0, v0, u1, v1 = parse_numbers(
            args.plate_cover, "--plate-cover", example="800,0,1300,2047", count=4, distinct=False
        )
        cover = (u0, v0, u1, v1)
    sim = simulate_plate(
        load_cell(args.config),
        args.plate,
        n_touches=4 if args.touches is None else args.touches,
        touch_noise_mm=args.touch_noise_mm,
        n_check=args.check,
        seed=args.seed,
        shift_mm=shift,
        cover_px=cover,
    )
    files = write_plate_simulation(sim, args.out)
    if args.json:
        print(json.dumps({"out": str(args.out), "plate": sim.spec.text, "files": [str(f) for f in files]}))
        return 0
    print(f"simulated a {sim.spec.text} plate, {len(sim.touched)} touches, {args.check} check points")
    print(f"wrote {args.out}: {', '.join(f.name for f in files)}")
    print(
        f"next: eyetohand calibrate-plate {args.out}/plate.png --plate {sim.spec.text} "
        f"--touches {args.out}/touches.csv --check {args.out}/check.csv -o cal.json"
    )
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "calibrate-plate", help="calibrate from images of a calibration plate and 3-4 robot touches of it"
    )
    p.add_argument("images", nargs="+", metavar="IMAGE", help="the plate's image(s), one per placement")
    p.add_argument(
        "--plate",
        required=True,
        metavar="SPEC",
        help="chessboard|circles|acircles|charuco:COLSxROWS:PITCH_MM (docs/plate.md)",
    )
    p.add_argument("--touches", metavar="T.csv", help="CSV [image,]u,v,x,y,z[,id]: the touched corners")
    p.add_argument(
        "--touches-from",
        metavar="OLD.json",
        help="after a camera bump: the touches of an earlier calibration from this plate, where it lay",
    )
    p.add_argument("--check", metavar="C.csv", help="check pairs, not used for fitting")
    p.add_argument(
        "--model", default=None, help="model (default: homography-radial on one plane, else camera)"
    )
    p.add_argument(
        "--touch-noise-mm",
        type=float,
        default=None,
        help="the robot's pointer noise per axis (default: from the touches' residuals)",
    )
    p.add_argument(
        "--touch-tolerance-mm",
        type=float,
        default=0.5,
        help="largest residual a touch may keep (default 0.5)",
    )
    p.add_argument(
        "--robot-units",
        choices=sorted(ROBOT_UNITS),
        default="mm",
        help="units of the touches' (and --check's) x, y, z: converted to mm",
    )
    p.add_argument(
        "--annotate", metavar="FILE.png", help="write the first image with the corners A-D labelled"
    )
    p.add_argument("--loo", action="store_true", help="also the corners' leave-one-out errors (slower)")
    p.add_argument("-o", "--output", help="write the calibration file")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_calibrate_plate)
