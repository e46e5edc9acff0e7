"""``eyetohand simulate`` and ``eyetohand plan``: the virtual cell on the command line."""

from __future__ import annotations

import json
import sys

from eyetohand.cell import VALID_FORMS, parse_numbers, parse_plan
from eyetohand.cli.common import parse_image_size
from eyetohand.core import InputError, atomic_write_text, load_pairs
from eyetohand.sim import (
    DEFAULT_PLANS,
    METRICS,
    VIEW_MARGIN,
    Cell,
    load_cell,
    plan_study,
    plot_study,
    simulate,
    view_rectangle,
    write_simulation,
)

CONFIG_HELP = "cell config (TOML or YAML); default: the built-in cell"


def _heights(text, what):
    return parse_numbers(text, what) if text is not None else None


def cmd_simulate(args) -> int:
    if args.write_config:
        cell = load_cell(args.config) if args.config else Cell.default()
        atomic_write_text(args.write_config, cell.to_toml())
        print(
            f"wrote {args.write_config} (edit it, then: eyetohand simulate --config {args.write_config} ...)"
        )
        return 0
    if args.plate:  # a plate image, its touches and check points (cli/plate.py)
        from eyetohand.cli.plate import cmd_simulate_plate

        return cmd_simulate_plate(args)
    for given, option in (
        (args.touches, "--touches"),
        (args.plate_shift_mm, "--plate-shift-mm"),
        (args.plate_cover, "--plate-cover"),
    ):
        if given is not None:
            raise InputError(f"simulate: {option} goes with --plate SPEC")
    if not args.out:
        raise InputError("simulate: give --out DIR (or --write-config FILE to write the default cell)")
    cell = load_cell(args.config)
    heights = parse_numbers(args.heights, "--heights")
    angles = parse_numbers(args.angles, "--angles", example="0,90,180") if args.angles else None
    sim = simulate(
        cell,
        parse_plan(args.plan),
        heights,
        n_check=args.check,
        check_heights_mm=_heights(args.check_heights, "--check-heights"),
        angles_deg=angles,
        seed=args.seed,
    )
    files = write_simulation(sim, args.out, images=args.images)
    if args.json:
        print(
            json.dumps(
                {
                    "out": str(args.out),
                    "n_pairs": len(sim.pairs),
                    "n_check": 0 if sim.check is None else len(sim.check),
                    "heights_mm": list(sim.heights_mm),
                    "check_heights_mm": list(sim.check_heights_mm),
                    "files": [str(f) for f in files],
                }
            )
        )
        return 0
    h = ", ".join(f"{v:g}" for v in sim.heights_mm)
    print(
        f"simulated {len(sim.pairs)} pairs ({sim.plan.label} at z = {h} mm"
        + (f", angles {', '.join(f'{a:g}' for a in sim.angles_deg)} deg" if sim.angles_deg else "")
        + ")"
    )
    if sim.check is not None:
        ch = ", ".join(f"{v:g}" for v in sim.check_heights_mm)
        print(f"check: {len(sim.check)} points at z = {ch} mm")
    n_img = sum(1 for f in files if f.suffix == ".png")
    names = [f.name for f in files if f.suffix != ".png"]
    print(f"wrote {args.out}: {', '.join(names)}" + (f" and {n_img} images" if n_img else ""))
    size = f"--image-size {cell.image_size[0]}x{cell.image_size[1]}"
    if n_img:  # the images are the point of --images: calibrate from them, as on a real cell
        check = f" --check {args.out}/check_poses.csv" if sim.check is not None else ""
        print(f"next: eyetohand calibrate-images {args.out}/poses.csv{check} {size}")
        print(f"  (or, without detection: eyetohand calibrate {args.out}/pairs.csv {size})")
    else:
        check = f" --check {args.out}/check.csv" if sim.check is not None else ""
        print(f"next: eyetohand calibrate {args.out}/pairs.csv{check} {size}")
    return 0


def cmd_plan_from_view(args) -> int:
    """``plan --from-view --corners FILE --image-size WxH``: the rectangle to collect over, in robot mm."""
    if not args.corners or not args.image_size:
        raise InputError(
            "plan --from-view: give --corners FILE (3 or 4 pairs u,v,x,y,z: the target jogged near the "
            "image's corners) and --image-size WxH (eyetohand grab prints it)"
        )
    view = view_rectangle(load_pairs(args.corners), parse_image_size(args.image_size), margin=args.margin)
    x0, y0, x1, y1 = view["rect_mm"]
    rect = f"{x0:g},{y0:g},{x1:g},{y1:g}"
    view["rect"] = rect
    view["begin"] = f"CAL BEGIN cell1,grid:5x5,{rect},{view['z_mm']:g}"
    if args.json:
        print(json.dumps(view, allow_nan=False))
        return 0
    w, h = view["image_size"]
    print(
        f"view at z = {view['z_mm']:g} mm ({w}x{h} px less {view['margin']:g} of it at each edge), "
        f"from {view['n_pairs']} jogged pairs ({view['map']} map, rough: no lens):"
    )
    print("  " + "  ".join(f"({a:.1f}, {b:.1f})" for a, b in view["view_mm"]))
    print(f"rectangle: x {x0:g} to {x1:g}, y {y0:g} to {y1:g} mm ({x1 - x0:g} x {y1 - y0:g} mm)")
    print(f"--rect {rect} --z {view['z_mm']:g}")
    print(view["begin"])
    return 0


def cmd_plan(args) -> int:
    if args.from_view:
        return cmd_plan_from_view(args)
    cell = load_cell(args.config)
    plans = [p for item in (args.plan or DEFAULT_PLANS) for p in item.split(",") if p.strip()]
    study = plan_study(
        cell,
        plans,
        parse_numbers(args.heights, "--heights"),
        target_error_mm=args.target_error,
        metric=args.target_metric,
        runs=args.runs,
        n_check=args.check,
        check_heights_mm=_heights(args.check_heights, "--check-heights"),
        model=args.model,
        seed=args.seed,
    )
    if args.plot:
        plot_study(study, args.plot)
    if args.json:
        out = {**study, "plans": [{k: v for k, v in r.items() if k != "rms_runs_mm"} for r in study["plans"]]}
        if args.plot:
            out["plot"] = str(args.plot)
        print(json.dumps(out, allow_nan=False))
        return 0
    heights = ", ".join(f"{h:g}" for h in study["plans"][0]["heights"])
    print(
        f"Monte Carlo: {study['runs']} simulated sessions per plan, pairs at z = {heights} mm, "
        f"{study['check_points_per_height']} check points per height"
    )
    print(f"  {'plan':<12} {'pairs':>5} {'model':<18} {'rms_mm':>8} {'max_mm':>8} {'max_p90_mm':>10}")
    for r in study["plans"]:
        if r.get("predicted_rms_mm") is None:
            print(f"  {r['plan']:<12} {r['n_pairs']:>5} n/a: {r['error']}")
            continue
        flag = ""
        if "meets_target" in r:
            flag = "  meets target" if r["meets_target"] else ""
        print(
            f"  {r['plan']:<12} {r['n_pairs']:>5} {r['model']:<18} {r['predicted_rms_mm']:>8.4f} "
            f"{r['predicted_max_mm']:>8.4f} {r['max_p90_mm']:>10.4f}{flag}"
        )
    if study["target_error_mm"] is not None:
        if study["recommended"]:
            print(
                f"recommended: {study['recommended']} (fewest pairs with predicted "
                f"{study['target_metric']} <= {study['target_error_mm']:g} mm)"
            )
        else:
            print(
                f"no plan meets the target ({study['target_metric']} <= {study['target_error_mm']:g} mm): "
                "try denser plans, a second height, or a cell with less noise",
                file=sys.stderr,
            )
    if args.plot:
        print(f"wrote {args.plot}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("simulate", help="simulate a calibration session in a virtual cell")
    p.add_argument("--config", metavar="CELL.toml", help=CONFIG_HELP)
    p.add_argument("--write-config", metavar="FILE", help="write the cell as commented TOML and stop")
    p.add_argument("--plan", default="grid:5x5", help=f"{VALID_FORMS} (default grid:5x5)")
    p.add_argument("--heights", default="150", help="robot z of the pairs, mm, comma-separated (default 150)")
    p.add_argument("--check", type=int, default=20, metavar="N", help="check points per height (default 20)")
    p.add_argument("--check-heights", metavar="Z[,Z..]", help="check point heights (default: --heights)")
    p.add_argument(
        "--angles",
        metavar="A0,A1,..",
        help="tool angles (deg): all pairs at A0, the centre position again at A1, .. (9 + 2)",
    )
    p.add_argument("--out", metavar="DIR", help="output folder")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (default: a fresh session each run; same seed, same session)",
    )
    p.add_argument("--images", action="store_true", help="also render the target images")
    p.add_argument(
        "--plate", metavar="SPEC", help="instead: a plate image (e.g. chessboard:9x6:15) and its touches"
    )
    p.add_argument(
        "--touches", type=int, default=None, metavar="N", help="with --plate: 3 or 4 touches (default 4)"
    )
    p.add_argument(
        "--touch-noise-mm",
        type=float,
        default=0.05,
        help="with --plate: the pointer's noise per axis (default 0.05)",
    )
    p.add_argument(
        "--plate-shift-mm",
        metavar="DX,DY",
        help="with --plate: move the plate along its own x, y from the view's centre (part may leave view)",
    )
    p.add_argument(
        "--plate-cover",
        metavar="U0,V0,U1,V1",
        help="with --plate: blank this rectangle of the image (px), as a part lying on the plate",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("plan", help="predict the accuracy of calibration plans (Monte Carlo)")
    p.add_argument("--config", metavar="CELL.toml", help=CONFIG_HELP)
    p.add_argument(
        "--plan",
        action="append",
        metavar="P",
        help=f"a plan, repeatable or comma-separated: {VALID_FORMS} (default {','.join(DEFAULT_PLANS)})",
    )
    p.add_argument("--heights", default="150", help="robot z of the pairs, mm, comma-separated (default 150)")
    p.add_argument("--check-heights", metavar="Z[,Z..]", help="heights to check at (default: --heights)")
    p.add_argument("--check", type=int, default=30, metavar="N", help="check points per height (default 30)")
    p.add_argument("--target-error", type=float, metavar="MM", help="required accuracy (mm)")
    p.add_argument(
        "--target-metric",
        default="max",
        choices=METRICS,
        help="compare the target with the predicted max (default) or RMS",
    )
    p.add_argument("--runs", type=int, default=20, help="simulated sessions per plan (default 20)")
    p.add_argument("--model", default="auto", help="model to calibrate with (default auto)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--plot", metavar="FILE.png", help="write a bar chart of the predictions")
    p.add_argument(
        "--from-view",
        action="store_true",
        help="instead: the rectangle (robot mm) to collect over, from what the camera sees (--corners)",
    )
    p.add_argument(
        "--corners",
        metavar="PAIRS.csv",
        help="3-4 pairs u,v,x,y,z: the target jogged near the image's corners at the work height",
    )
    p.add_argument("--image-size", metavar="WxH", help="image size in px (with --from-view)")
    p.add_argument(
        "--margin",
        type=float,
        default=VIEW_MARGIN,
        help=f"fraction of the image kept clear at each edge (with --from-view; default {VIEW_MARGIN:g})",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_plan)
