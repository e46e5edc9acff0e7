"""``calibrate``, ``evaluate``, ``apply``, ``compare``: point pairs in, a calibration and its figures out."""

from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ..evaluate import evaluate
from ..pairs import load_image_points, load_pairs
from .common import (
    CliError,
    add_fit_options,
    emit_json,
    parse_image_size,
    print_points,
    run_calibration,
    stats_line,
)


def cmd_calibrate(args) -> int:
    pairs = load_pairs(args.pairs)
    check = load_pairs(args.check) if args.check else None
    return run_calibration(args, pairs, check)


def cmd_evaluate(args) -> int:
    cal = Calibration.load(args.calibration)
    pairs = load_pairs(args.pairs)
    stats = evaluate(cal, pairs)
    if args.json:
        emit_json(stats.to_dict())
    else:
        print(f"{args.calibration}: model {cal.model_name} on {args.pairs}")
        print(stats_line("eval", stats))
        print_points(stats)
    return 0


def cmd_apply(args) -> int:
    cal = Calibration.load(args.calibration)
    if args.uv is not None:
        if args.input:
            raise CliError("apply: give either --uv U V or an input CSV, not both")
        xyz = cal.image_to_robot(np.array([args.uv], float), args.z)
        print(" ".join(f"{v:.6f}" for v in xyz[0]))
        return 0
    if not args.input:
        raise CliError("apply: give --uv U V or an input CSV with u,v columns")
    if not args.output:
        raise CliError("apply: an input CSV needs -o OUT.csv")
    table = load_image_points(args.input)
    z = table.z_mm if table.z_mm is not None else args.z
    xyz = cal.image_to_robot(table.uv_px, z)
    from ..io import atomic_write_text

    atomic_write_text(args.output, table.with_columns({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}))
    print(f"wrote {args.output} ({len(xyz)} points)")
    return 0


def cmd_compare(args) -> int:
    from ..compare import compare, format_compare

    pairs = load_pairs(args.pairs)
    check = load_pairs(args.check)
    rows = compare(pairs, check, image_size=parse_image_size(args.image_size), seed=args.seed)
    if args.json:
        emit_json({"rows": rows})
    else:
        print(format_compare(rows))
    return 0


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="fit an image-to-robot calibration from point pairs")
    p.add_argument("pairs", help="CSV (u,v,x,y[,z][,id]) or JSON of point pairs")
    p.add_argument("--check", help="check pairs, not used for fitting")
    add_fit_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("evaluate", help="statistics of a calibration on pairs")
    p.add_argument("calibration")
    p.add_argument("pairs")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("apply", help="map image points to robot points")
    p.add_argument("calibration")
    p.add_argument("input", nargs="?", help="CSV with u,v (and z for multi-height models)")
    p.add_argument("--uv", nargs=2, type=float, metavar=("U", "V"))
    p.add_argument("--z", type=float, default=None, help="object height in mm")
    p.add_argument("-o", "--output", help="output CSV (input columns plus x,y,z)")
    p.set_defaults(func=cmd_apply)

    p = sub.add_parser("compare", help="every model x solver side by side on check pairs")
    p.add_argument("pairs")
    p.add_argument("--check", required=True)
    p.add_argument("--image-size", metavar="WxH")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_compare)
