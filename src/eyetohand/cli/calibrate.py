"""``calibrate``, ``evaluate``, ``apply``, ``compare``: point pairs in, a calibration and its figures out."""

from __future__ import annotations

import json
import sys

import numpy as np

from eyetohand.calibration import Calibration, load_sign_key
from eyetohand.cli.common import (
    CliError,
    add_fit_options,
    add_max_pairs_option,
    add_orientation_options,
    emit_json,
    fit_request,
    parse_image_size,
    print_points,
    run_calibration,
    stats_line,
)
from eyetohand.core import (
    ROBOT_UNITS,
    InputError,
    atomic_write_text,
    check_output_path,
    image_points_from_text,
    load_image_points,
    load_pairs,
    output_units,
)


def print_notes(*loaded) -> None:
    """``note:`` lines on stderr for what the loaders assumed of these pairs or tables (the CSV
    dialect, a missing z): the library records notes, the CLI prints them."""
    for item in loaded:
        for note in getattr(item, "notes", ()) if item is not None else ():
            print(f"note: {note}", file=sys.stderr)


def print_warnings(warnings) -> None:
    """``warning:`` lines on stderr (the library's findings, e.g. a mixed-up convention)."""
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)


def cmd_calibrate(args) -> int:
    key = _sign_key(args)
    if args.output:  # before any work: a fit must not be lost to an output that cannot be written
        check_output_path(args.output)
    request = fit_request(args)  # the options before the files: a bad one is refused first
    pairs = load_pairs(args.pairs, max_pairs=args.max_pairs).scaled_to_mm(args.robot_units)
    check = (
        load_pairs(args.check, max_pairs=args.max_pairs).scaled_to_mm(args.robot_units)
        if args.check
        else None
    )
    print_notes(check)  # the training pairs' notes are the calibration's own, printed with it
    rc = run_calibration(args, pairs, check, request=request)
    if rc == 0 and key is not None:
        # the file as written, proved and signed in place (atomically: never half a file)
        Calibration.load(args.output).save(args.output, sign_key=key)
    return rc


def _sign_key(args) -> bytes | None:
    """--sign-key FILE: the key (read before any work), refused without -o."""
    if getattr(args, "sign_key", None) is None:
        return None
    if not args.output:
        raise CliError("--sign-key signs the calibration file: give -o FILE too")
    try:
        return load_sign_key(args.sign_key)
    except InputError as exc:
        raise CliError(f"--sign-key {exc}") from None


def cmd_evaluate(args) -> int:
    cal = Calibration.load(args.calibration)
    pairs = load_pairs(args.pairs, max_pairs=args.max_pairs)
    print_notes(pairs)
    from eyetohand.calibration import evaluate_pairs  # here: `apply` needs none of calibration.checking

    ev = evaluate_pairs(cal, pairs, allow_outside=args.allow_outside)
    print_warnings(ev.warnings)
    if args.json:
        emit_json(ev.to_dict())
    else:
        print(f"{args.calibration}: model {cal.model_name} on {args.pairs}")
        print(stats_line("eval", ev.stats))
        print_points(ev.stats)
    return 0


def cmd_apply(args) -> int:
    if args.output:
        check_output_path(args.output)
    units = output_units(args.units, args.angle_units)  # refused before the file is read
    cal = Calibration.load(args.calibration)
    opts = {
        "allow_outside": args.allow_outside,
        "symmetry": args.symmetry,
        "tool_rz_offset_deg": args.tool_rz_offset,
        "part_diameter_mm": args.part_diameter_mm,
    }
    if args.uv is not None:
        if args.input:
            raise CliError("apply: give either --uv U V or an input CSV, not both")
        m = cal.map(np.array([args.uv], float), units.in_length(args.z), angle_deg=args.angle, **opts)
        if args.json:
            print(json.dumps(mapped_json(m, units), allow_nan=False))
        else:
            vals = [units.out_length(float(v)) for v in m.xyz_mm[0]]
            vals += [] if m.rz_deg is None else [units.out_angle(float(m.rz_deg[0]))]
            print(" ".join(repr(float(v)) for v in vals))
        _warn_outside(m)
        return 0
    if not args.input:
        raise CliError("apply: give --uv U V or an input CSV with u,v columns ('-' reads standard input)")
    if args.input == "-":
        table = image_points_from_text(sys.stdin.read(), "<stdin>")
    else:
        table = load_image_points(args.input)
    print_notes(table)
    if table.z_mm is not None and args.z is not None:
        raise CliError("apply: the input has a z column; --z would contradict it")
    if table.angle_deg is not None and args.angle is not None:
        raise CliError("apply: the input has an angle column; --angle would contradict it")
    if table.part_diameter_mm is not None and args.part_diameter_mm is not None:
        raise CliError(
            "apply: the input has a part_diameter_mm column; --part-diameter-mm would contradict it"
        )
    if table.part_diameter_mm is not None:
        opts["part_diameter_mm"] = table.part_diameter_mm  # one per row
    z = table.z_mm if table.z_mm is not None else args.z  # the input's z column: in --units too
    ang = table.angle_deg if table.angle_deg is not None else args.angle
    m = cal.map(table.uv_px, units.in_length(z), angle_deg=ang, **opts)
    if args.json:
        text = json.dumps(mapped_json(m, units), allow_nan=False) + "\n"
    else:
        xyz = units.out_length(m.xyz_mm)
        cols = {"x": xyz[:, 0], "y": xyz[:, 1]}
        if table.z_mm is None:
            cols["z"] = xyz[:, 2]
        if m.rz_deg is not None:
            cols["rz"] = units.out_angle(m.rz_deg)
        if m.sigma_mm is not None:
            cols[units.sigma_key] = units.out_length(m.sigma_mm)
        cols["inside"] = m.inside
        text = table.with_columns(cols)
    if args.output:
        atomic_write_text(args.output, text)
        print(f"wrote {args.output} ({len(m.xyz_mm)} points)", file=sys.stderr)
    else:
        sys.stdout.write(text)
    _warn_outside(m)
    return 0


def mapped_json(m, units) -> dict:
    """``apply --json``: the points (u, v, x, y, z, [rz], sigma_<unit>, inside) in ``units``, which it
    names (``units``, ``angle_units``); mm and deg: every number as ``Mapped.records`` has it."""
    recs = m.records()
    if not units.is_default:
        for rec in recs:
            for k in ("x", "y", "z"):
                rec[k] = units.out_length(rec[k])
            if "rz" in rec:
                rec["rz"] = units.out_angle(rec["rz"])
            sigma = rec.pop("sigma_mm")
            rec[units.sigma_key] = None if sigma is None else units.out_length(sigma)
            rec["inside"] = rec.pop("inside")  # last, as in mm
    return {"units": units.length, "angle_units": units.angle, "points": recs}


def _warn_outside(m) -> None:
    n = int((~m.inside).sum())
    if n:
        print(
            f"warning: {n} point(s) outside the calibrated region, mapped because --allow-outside was "
            "given (inside = false)",
            file=sys.stderr,
        )


def cmd_compare(args) -> int:
    from eyetohand.calibration import compare, format_compare

    pairs = load_pairs(args.pairs, max_pairs=args.max_pairs)
    check = load_pairs(args.check, max_pairs=args.max_pairs)
    print_notes(pairs, check)
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
    p.add_argument(
        "--robot-units",
        choices=sorted(ROBOT_UNITS),
        default="mm",
        help="units of the robot x, y, z in the pairs (and --check): converted to mm before fitting",
    )
    add_fit_options(p)
    add_max_pairs_option(p)
    p.add_argument(
        "--sign-key",
        metavar="FILE",
        default=None,
        help="sign the calibration file (-o) with the HMAC-SHA256 key in FILE (>= 16 bytes, e.g. "
        "head -c 32 /dev/urandom > FILE), for 'serve --sign-key FILE --require-signed'",
    )
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser(
        "evaluate",
        help="statistics of a calibration on pairs (refused outside its region; mixed-up columns named)",
    )
    p.add_argument("calibration")
    p.add_argument("pairs")
    p.add_argument(
        "--allow-outside",
        action="store_true",
        help="evaluate pairs outside the calibrated region or heights too (a warning counts them)",
    )
    p.add_argument("--json", action="store_true", help="the statistics and 'warnings' as one JSON object")
    add_max_pairs_option(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("apply", help="map image points to robot points")
    p.add_argument("calibration")
    p.add_argument(
        "input",
        nargs="?",
        help="CSV with u,v [,z] [,angle] [,part_diameter_mm] ('-': standard input); output: its columns plus "
        "x,y[,z][,rz],sigma_mm,inside",
    )
    p.add_argument("--uv", nargs=2, type=float, metavar=("U", "V"))
    p.add_argument("--z", type=float, default=None, help="object height in mm (in --units)")
    add_orientation_options(p)
    p.add_argument(
        "--allow-outside",
        action="store_true",
        help="map points outside the calibrated region too (flagged inside = false)",
    )
    p.add_argument(
        "--part-diameter-mm",
        type=float,
        default=None,
        metavar="MM",
        help="the circular part's diameter (mm, whatever --units says): its detected centres are "
        "corrected for perspective as a calibration fitted with --target-diameter-mm needs "
        "(0: the points are their own images; a part_diameter_mm column gives one per row)",
    )
    p.add_argument(
        "--json", action="store_true", help="JSON with every point's u v x y z [rz] sigma_mm inside"
    )
    p.add_argument(
        "--units",
        default=None,
        metavar="mm|m",
        help="length unit of x, y, z and sigma (sigma_m) in the output, and of --z and the input's z "
        "column (default mm; m = mm / 1000)",
    )
    p.add_argument(
        "--angle-units", default=None, metavar="deg|rad", help="unit of rz in the output (default deg)"
    )
    p.add_argument("-o", "--output", help="output file (default: standard output)")
    p.set_defaults(func=cmd_apply)

    p = sub.add_parser("compare", help="every model x solver side by side on check pairs")
    p.add_argument("pairs")
    p.add_argument("--check", required=True)
    p.add_argument("--image-size", metavar="WxH")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    add_max_pairs_option(p)
    p.set_defaults(func=cmd_compare)
