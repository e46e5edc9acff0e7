"""``eyetohand export``: a calibration as a matrix, the file itself, or a lookup grid."""

from __future__ import annotations

import sys

from eyetohand.calibration import FORMATS, Calibration, export_text
from eyetohand.core import atomic_write_text, check_output_path, read_bounded_text


def cmd_export(args) -> int:
    if args.output:
        check_output_path(args.output)
    cal = Calibration.load(args.calibration)
    text = read_bounded_text(args.calibration, what="a calibration file") if args.format == "json" else None
    out = export_text(cal, args.format, file_text=text, as_text=args.text, pitch_px=args.pitch, z_mm=args.z)
    if args.output:
        atomic_write_text(args.output, out)
        print(f"wrote {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(out)
    return 0


def register(sub) -> None:
    p = sub.add_parser("export", help="a calibration as a px->mm matrix, the JSON file, or a CSV lookup grid")
    p.add_argument("calibration", metavar="CAL.json")
    p.add_argument(
        "--format",
        required=True,
        choices=FORMATS,
        help="matrix: 3x3 homography / 2x3 affine (planar models); json: the file; "
        "csv: a grid u,v,x,y,z,sigma_mm over the calibrated region",
    )
    p.add_argument("--text", action="store_true", help="matrix as plain text rows (default JSON)")
    p.add_argument("--pitch", type=float, default=10.0, metavar="PX", help="csv grid pitch (default 10 px)")
    p.add_argument(
        "--z",
        type=float,
        default=None,
        metavar="MM",
        help="csv: the height to map at (models of several heights)",
    )
    p.add_argument("-o", "--output", metavar="OUT", help="output file (default: standard output)")
    p.set_defaults(func=cmd_export)
