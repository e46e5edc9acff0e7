"""``eyetohand conveyor calibrate | apply | simulate``: conveyor tracking on the command line.

``register(subparsers)`` adds the ``conveyor`` command to ``eyetohand`` (exit 0 ok, 2 bad input with one
``error:`` line on stderr).
"""

from __future__ import annotations

import json

import numpy as np

from eyetohand.cell import (
    ConveyorCalibration,
    Encoder,
    calibrate_conveyor,
    format_report,
    load_session,
)
from eyetohand.cli.common import add_orientation_options
from eyetohand.core import InputError
from eyetohand.geometry import check_symmetry


def _encoder(args) -> Encoder:
    return Encoder(args.counter_bits, args.signed)


def _size(text):
    if text is None:
        return None
    try:
        w, h = (int(p) for p in text.lower().split("x"))
        if w > 0 and h > 0:
            return (w, h)
    except ValueError:
        pass
    raise InputError(f"--image-size: expected WxH in pixels (e.g. 2448x2048), got {text!r}")


def cmd_calibrate(args) -> int:
    session = load_session(args.session)
    direction = None
    if args.belt_yaw_deg is not None or args.belt_pitch_deg is not None:
        direction = (args.belt_yaw_deg or 0.0, args.belt_pitch_deg or 0.0)
    conv = calibrate_conveyor(
        session,
        model=args.model,
        encoder=_encoder(args),
        stated_counts_per_mm=args.pulses_per_mm,
        stated_direction_deg=direction,
        window_mm=tuple(args.window) if args.window else None,
        image_size=_size(args.image_size),
        noise_counts=args.noise_counts,
    )
    if args.output:
        conv.save(args.output)
    if args.json:
        print(json.dumps({"report": conv.report, "output": args.output}, allow_nan=False, default=float))
    else:
        print(format_report(conv.report or {}))
        if args.output:
            print(f"wrote {args.output}")
    return 0


def cmd_apply(args) -> int:
    conv = ConveyorCalibration.load(args.belt)
    uv = np.array([args.uv], float)
    check_symmetry(args.symmetry)  # refused with or without an angle, as apply and the lines do
    if args.tracking:
        if args.angle is not None:
            raise InputError("conveyor apply: --angle gives rz with --e-now; the tracking form has no rz")
        t = conv.tracking_form(uv, args.e_image)
        p, b = t["position_mm"][0], t["belt_mm_per_count"]
        if args.json:
            xyz = dict(zip("xyz", (float(v) for v in p), strict=True))
            belt = [float(v) for v in b]
            print(
                json.dumps(
                    {
                        "u": args.uv[0],
                        "v": args.uv[1],
                        "e_image": args.e_image,
                        **xyz,
                        "belt_mm_per_count": belt,
                    },
                    allow_nan=False,
                )
            )
            return 0
        print(" ".join(f"{v:.6f}" for v in p) + f" {args.e_image} " + " ".join(f"{v:.9g}" for v in b))
        return 0
    if args.e_now is None:
        raise InputError("conveyor apply: give --e-now M (or --tracking for the position at e_image)")
    p = conv.image_to_robot_at(uv, args.e_image, args.e_now, allow_outside=args.allow_outside)[0]
    vals = list(p)
    if args.angle is not None:  # the belt translates the part: its rz is the camera map's
        vals += list(
            conv.rz_deg(uv, args.angle, symmetry=args.symmetry, tool_rz_offset_deg=args.tool_rz_offset)
        )
    if args.json:  # full precision, named as apply --json names them
        names = ("x", "y", "z", "rz")[: len(vals)]
        out = {"u": args.uv[0], "v": args.uv[1], "e_image": args.e_image, "e_now": args.e_now}
        print(json.dumps({**out, **{k: float(v) for k, v in zip(names, vals, strict=True)}}, allow_nan=False))
        return 0
    print(" ".join(f"{v:.6f}" for v in vals))
    return 0


def cmd_simulate(args) -> int:
    from eyetohand.sim import (
        ConveyorSetup,
        sightings_from_text,
        simulate_conveyor,
        write_conveyor_simulation,
    )

    setup = ConveyorSetup(
        yaw_deg=args.yaw_deg,
        pitch_deg=args.pitch_deg,
        mm_per_count=args.mm_per_count,
        n_parts=args.parts,
        latch_delay_counts=args.latch_delay,
        stated_scale_error=args.scale_error,
        counter_bits=args.counter_bits,
        signed=args.signed,
        sightings=sightings_from_text(args.sightings),
    )
    sim = simulate_conveyor(setup, seed=args.seed)
    files = write_conveyor_simulation(sim, args.out)
    lo, hi = sim.truth["window_along_belt_mm"]
    w, h = sim.cell.image_size
    if args.json:
        summary = {"out": str(args.out), "rows": len(sim.session), "parts": setup.n_parts}
        print(
            json.dumps(
                {
                    **summary,
                    "files": [str(f) for f in files],
                    "counts_wrap": sim.truth["counts_wrap"],
                    "window_along_belt_mm": [lo, hi],
                    "image_size": [w, h],
                    "pulses_per_mm": setup.stated_counts_per_mm,
                },
                allow_nan=False,
                default=float,
            )
        )
        return 0
    print(
        f"simulated {len(sim.session)} rows ({setup.n_parts} parts, sighted "
        f"{'once' if setup.sightings is None else '/'.join(setup.sightings)}); "
        f"counts wrap: {sim.truth['counts_wrap']}"
    )
    print(f"wrote {', '.join(str(f) for f in files)}")
    print(
        f"next: eyetohand conveyor calibrate {args.out}/session.csv -o belt.json "
        f"--pulses-per-mm {setup.stated_counts_per_mm:.9g} --window {lo:.3f} {hi:.3f} --image-size {w}x{h}"
    )
    return 0


def _counter_options(p) -> None:
    p.add_argument("--counter-bits", type=int, default=24, help="encoder counter width (default 24)")
    p.add_argument("--signed", action="store_true", help="the counter is signed (two's complement)")


def register(sub) -> None:
    conv = sub.add_parser("conveyor", help="conveyor tracking: belt calibration, mapping, simulation")
    csub = conv.add_subparsers(dest="conveyor_command", metavar="ACTION", parser_class=type(conv))

    p = csub.add_parser("calibrate", help="fit camera map + belt (+ latch delay) from a session CSV")
    p.add_argument("session", help="CSV kind,id,u,v,x,y,z,e[,moving], rows in time order")
    p.add_argument("-o", "--output", metavar="BELT.json")
    p.add_argument("--model", default="homography-radial", help="planar model (default homography-radial)")
    p.add_argument("--pulses-per-mm", type=float, default=None, help="stated encoder counts per mm (tested)")
    p.add_argument(
        "--belt-yaw-deg", type=float, default=None, help="stated belt direction (default: nearest axis)"
    )
    p.add_argument("--belt-pitch-deg", type=float, default=None, help="stated belt slope (default level)")
    p.add_argument(
        "--window", nargs=2, type=float, metavar=("LO", "HI"), help="robot window along the belt, mm"
    )
    p.add_argument("--image-size", metavar="WxH")
    p.add_argument("--noise-counts", type=float, default=5.0, help="backward jitter tolerated (counts)")
    p.add_argument("--json", action="store_true")
    _counter_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = csub.add_parser("apply", help="map (u, v, e_image) to the part's robot position at e_now")
    p.add_argument("belt", help="BELT.json from conveyor calibrate")
    p.add_argument("--uv", nargs=2, type=float, metavar=("U", "V"), required=True)
    p.add_argument("--e-image", type=int, required=True, help="encoder count latched with the image")
    p.add_argument("--e-now", type=int, default=None, help="encoder count now")
    p.add_argument(
        "--tracking", action="store_true", help="print x y z at e_image, e_image and the belt vector"
    )
    add_orientation_options(p)
    p.add_argument("--allow-outside", action="store_true", help="answer outside the robot window too")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_apply)

    p = csub.add_parser("simulate", help="write a simulated conveyor session and its truth")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: a fresh session each run)")
    p.add_argument("--parts", type=int, default=120)
    p.add_argument("--yaw-deg", type=float, default=3.0)
    p.add_argument("--pitch-deg", type=float, default=0.5)
    p.add_argument("--mm-per-count", type=float, default=0.01)
    p.add_argument("--latch-delay", type=float, default=0.0, help="planted latch delay (counts)")
    p.add_argument("--scale-error", type=float, default=0.0, help="stated pulses per mm off by this fraction")
    p.add_argument(
        "--sightings",
        default="stopped,running",
        help="each part's frames: a comma list of stopped/running (default stopped,running), or 'one' "
        "(one sighting per part, half of them stopped)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    _counter_options(p)
    p.set_defaults(func=cmd_simulate)
    conv.set_defaults(func=lambda a: (conv.print_help(), 2)[1])
